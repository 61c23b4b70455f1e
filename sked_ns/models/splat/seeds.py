"""The splat edit's seeds: new Gaussians where the sketches may add content, for the edit to shape."""

from __future__ import annotations

import math
import warnings
from typing import Callable, Dict

import torch
from torch import Tensor


@torch.no_grad()
def hull_seeds(count: int, edit_box, in_sketch_hull: Callable[[Tensor], Tensor], seed_opacity: float,
               seed_size: float, rest_bases: int) -> Dict[str, Tensor]:
    """`count` grey, nearly transparent, isotropic Gaussians spread uniformly over the sketches' visual hull (where
    every view's mask agrees) inside the edit box, sized to their spacing times `seed_size`; `rest_bases`: the SH
    coefficients past degree 0 each holds (zeros)."""
    low = torch.as_tensor(edit_box.min, dtype=torch.float32)
    high = torch.as_tensor(edit_box.max, dtype=torch.float32)
    generator = torch.Generator().manual_seed(0)  # the same seeds for every load of the edit
    found, drawn, hits = [], 0, 0
    while count > 0 and hits < count and drawn < 64 * count:
        points = low + torch.rand((4 * count, 3), generator=generator) * (high - low)
        inside = points[in_sketch_hull(points)]
        found.append(inside)
        drawn, hits = drawn + len(points), hits + len(inside)
    points = torch.cat(found)[:count] if found else torch.zeros((0, 3))
    if count > 0 and len(points) == 0:
        warnings.warn("The sketches' visual hull is empty at the sampled points: no Gaussians are seeded for new "
                      "content, so the edit can only reshape the base's Gaussians near the sketches.", stacklevel=2)
    n = len(points)
    hull_volume = float(torch.prod(high - low)) * hits / max(drawn, 1)
    spacing = (hull_volume / max(n, 1)) ** (1.0 / 3.0)
    size = max(spacing * seed_size, 1e-6)
    return {
        "means": points,
        "scales": torch.full((n, 3), math.log(size)),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
        "features_dc": torch.zeros((n, 3)),  # grey: SH 0 -> 0.5, and sigmoid(0) = 0.5 without SH
        "features_rest": torch.zeros((n, rest_bases, 3)),
        "opacities": torch.full((n, 1), math.log(seed_opacity / (1 - seed_opacity))),
    }
