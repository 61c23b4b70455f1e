"""What a splat edit saves: what it changed, and nothing its base holds.

Its checkpoint holds its editable Gaussians (and their Adam state) and which of its base's Gaussians it keeps
(`kept_in_base`); the kept Gaussians are read from its copy of the base when it is built. L_pres's targets are saved
once refinement has moved them (a split Gaussian's children are held where the split put them); until then they are
the base's own values for its editable Gaussians, read from the base like the kept ones, and the seeds', which L_pres
never weighs (they have no base value).
"""

from __future__ import annotations

from typing import Dict

import torch
from torch import Tensor

from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS

TARGETS = "reference."
"""L_pres's targets in the edit's state dict."""


def base_in_its_order(frozen: Dict[str, Tensor], kept: Tensor) -> Dict[str, Tensor]:
    """The frozen base (held kept rows first) in the order of its checkpoint."""
    count = int(kept.sum())
    base = {}
    for name, value in frozen.items():
        base[name] = torch.empty_like(value)
        base[name][kept], base[name][~kept] = value[:count], value[count:]
    return base


def targets_are_the_bases(targets: Dict[str, Tensor], editable: int, base: Dict[str, Tensor], kept: Tensor) -> bool:
    """Whether L_pres's targets are still those set up: one per editable Gaussian, the base's editable ones first,
    holding the base's values, then the seeds."""
    count = int((~kept).sum())
    from_base = targets["from_base"]
    if len(from_base) != editable or not bool(from_base[:count].all()) or bool(from_base[count:].any()):
        return False
    return all(torch.equal(targets[name][:count], base[name][~kept]) for name in GAUSSIAN_PARAMS)


def targets_from_the_base(base: Dict[str, Tensor], kept: Tensor, set_up: Dict[str, Tensor],
                          editable: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The targets of an edit saved before refinement moved them (keys as saved): the base's values for its editable
    Gaussians, then the seeds' as set up (`set_up`, the targets this model was built with), or, where this build seeded
    another count, the saved seeds' own values (`editable`, the saved Gaussians), never weighed either way."""
    count = int((~kept).sum())
    seeds = {name: value[~set_up["from_base"]] for name, value in set_up.items()}
    seeded = len(editable["means"]) - count
    if len(seeds["means"]) != seeded:
        seeds = {name: value[count:].to(base[name]) for name, value in editable.items()}
    targets = {f"{TARGETS}{name}": torch.cat([base[name][~kept], seeds[name].to(base[name])]) for name in GAUSSIAN_PARAMS}
    from_base = torch.zeros(count + seeded, dtype=torch.bool, device=kept.device)
    from_base[:count] = True
    targets[f"{TARGETS}from_base"] = from_base
    return targets
