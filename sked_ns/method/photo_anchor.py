"""Preservation by the base's own photos: their rays that never come near the editable region.

The paper keeps the base only at the samples of one random view (L_pres), so whatever that view
does not sample -- the far side, the empty space seen from other viewpoints, hash-grid cells
shared with the new content -- may drift: floaters and damage at novel views. The base's
training photos are a cheap, exact anchor: a ray every point of which has preservation weight
above a threshold shows nothing the edit may change, so the edit must still render that photo's
pixel, as the base was trained to. One small batch of such rays per step anchors everything
the edit must keep from every training viewpoint.

A ray is tested cheaply: it is safe if it misses the box holding every point with w below the
threshold (found once on a grid over the scene box and the edit box: search_box), else if all
points sampled along its stretch inside that box have w above the threshold.
"""

from __future__ import annotations

import warnings
from typing import Callable, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from sked_ns.errors import SkedWarning
from sked_ns.sketches.cameras import ray_aabb

MIN_BASE_PHOTO_PSNR = 15.0
"""PSNR (dB) under which the base does not explain the photos it is given, so they must not anchor the edit:
a trained base renders its own training photos far above the threshold, a barely fitted one or other photos far
below it (docs/method.md, Photo anchor)."""
LOW_BASE_PHOTO_PSNR = 20.0
"""Under this the anchor pulls kept content towards photos the base fits poorly: warned."""
GRID_RESOLUTION = 64
"""Cells per side of the grid that finds the editable region's box."""
SAMPLES_INSIDE = 64
"""Points tested along a ray's stretch inside that box."""


@torch.no_grad()
def editable_box(preservation_weight: Callable[[Tensor], Tensor], region: Tensor, threshold: float,
                 resolution: int = GRID_RESOLUTION) -> Optional[Tensor]:
    """(6,) min and max of every grid point of `region` ((2, 3): search_box) with w <= threshold, dilated by one
    cell; None if there is none."""
    low, high = region[0].float(), region[1].float()
    axis = torch.linspace(0, 1, resolution)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    points = low + grid * (high - low)
    weight = torch.cat([preservation_weight(chunk).reshape(-1) for chunk in points.split(1 << 18)])
    editable = points[weight.cpu() <= threshold]
    if len(editable) == 0:
        return None
    cell = (high - low) / (resolution - 1)
    return torch.cat([editable.amin(dim=0) - cell, editable.amax(dim=0) + cell])


def search_box(scene_aabb: Tensor, edit_low: np.ndarray, edit_high: np.ndarray, reach: float,
               bounds: Optional[np.ndarray]) -> Tensor:
    """(2, 3) where editable_box looks: the scene box, and on each side where the edit box reaches past it (a
    contracted base's may: a capture's object on the box's face), out to the edit box and `reach` of its size beyond;
    within `bounds` (the space a bounded base holds; None: unbounded)."""
    pad = reach * (np.asarray(edit_high) - np.asarray(edit_low))
    scene = scene_aabb.detach().cpu().double().numpy()
    low = np.where(edit_low < scene[0], edit_low - pad, scene[0])
    high = np.where(edit_high > scene[1], edit_high + pad, scene[1])
    if bounds is not None:
        low, high = np.maximum(low, bounds[0]), np.minimum(high, bounds[1])
    return torch.as_tensor(np.stack([low, high]), dtype=scene_aabb.dtype)


@torch.no_grad()
def rays_away_from_edit(origins: Tensor, directions: Tensor, nears: Tensor, fars: Tensor, box: Optional[Tensor],
                        preservation_weight: Callable[[Tensor], Tensor], threshold: float,
                        samples: int = SAMPLES_INSIDE) -> Tensor:
    """(N,) True where every point of the ray (between near and far) has w above `threshold`."""
    safe = torch.ones(len(origins), dtype=torch.bool, device=origins.device)
    if box is None:
        return safe
    entry, exit_ = ray_aabb(origins, directions, box.to(origins))
    entry = torch.maximum(entry, nears.reshape(-1))
    exit_ = torch.minimum(exit_, fars.reshape(-1))
    crossing = exit_ > entry
    if crossing.any():
        t = torch.linspace(0, 1, samples, device=origins.device)
        depths = entry[crossing, None] + (exit_ - entry)[crossing, None] * t
        points = origins[crossing, None] + directions[crossing, None] * depths[..., None]
        lowest = preservation_weight(points.reshape(-1, 3)).reshape(-1, samples).amin(dim=-1)
        safe[crossing] = lowest > threshold
    return safe


def check_base_explains_photos(predicted: Tensor, photos: Tensor) -> Tuple[float, bool]:
    """The base's render of photo rays against the photos (both (N, 3) in [0, 1]): (PSNR in dB, whether they may
    anchor the edit). Photos the base does not explain (not its own, or a base barely trained) would pull the kept
    content away from the base: the anchor is then turned off, loudly; L_pres still keeps the base."""
    mse = torch.nn.functional.mse_loss(predicted.detach().float(), photos.detach().float()).clamp_min(1e-10)
    psnr = float(-10.0 * torch.log10(mse))
    if psnr < MIN_BASE_PHOTO_PSNR:
        warnings.warn(
            f"--data: the base renders these photos at only {psnr:.1f} dB PSNR ({len(photos)} rays away from the "
            f"sketches; a trained base renders its own photos at 20-35 dB). They are not the photos it was trained "
            "on, or it is barely trained: the photo anchor is OFF for this edit (as with --pipeline.model.lambda-photo "
            "0). Pass the data the base was trained on to keep it.", SkedPhotoWarning, stacklevel=2)
        return psnr, False
    if psnr < LOW_BASE_PHOTO_PSNR:
        warnings.warn(f"--data: the base renders these photos at only {psnr:.1f} dB PSNR; the photo anchor will pull "
                      "what the edit keeps towards them. If they are not the photos the base was trained on, pass "
                      "those, or --pipeline.model.lambda-photo 0.", SkedPhotoWarning, stacklevel=2)
    return psnr, True


class SkedPhotoWarning(SkedWarning):
    """The base's photos do not match what it renders."""


def anchor_rays(rays, rgb: Tensor, safe: Tensor) -> Tuple[object, Tensor]:
    """The safe subset of a photo ray batch and its colours."""
    index = safe.nonzero()[:, 0]
    return rays[index], rgb[index]


def correct_poses(rays, camera_optimizers) -> None:
    """Apply the base's learnt pose corrections to its photo rays, as nerfacto did when it trained on them."""
    for optimizer in camera_optimizers:
        correction = optimizer(rays.camera_indices.reshape(-1))
        rays.origins = rays.origins + correction[:, :3, 3]
        rays.directions = torch.bmm(correction[:, :3, :3], rays.directions[..., None])[..., 0]
