"""splatfacto's refinement (gsplat's DefaultStrategy) on the editable Gaussians only, with L_pres's targets following
each split, duplicate and prune."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Dict, List, Optional

import torch
from gsplat.strategy import DefaultStrategy
from torch import Tensor

from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS, GaussianSet


class EditableRefinement:
    """gsplat's strategy and its state, as gsplat has them: given the editable Gaussians' parameters, their
    optimisers and the step's renders each time, holding nothing of the model's."""

    def __init__(self, strategy: DefaultStrategy) -> None:
        self.strategy = strategy
        self.state = strategy.initialize_state(scene_scale=1.0)

    def reset(self) -> None:
        """A fresh state (the Gaussian counts changed under it: a loaded checkpoint)."""
        self.state = self.strategy.initialize_state(scene_scale=1.0)

    def step_post_backward(self, step: int, params: torch.nn.ParameterDict, optimizers: Dict, infos: List[Dict],
                           kept: int, reference: GaussianSet) -> None:
        """splatfacto's densification and pruning on the editable Gaussians (`params`), from the gradients of the
        step's renders (`infos`, whose first `kept` Gaussians are the kept ones); L_pres's targets (`reference`)
        follow. Step 0 is skipped: the strategy resets opacities at every multiple of its reset interval, 0
        included, which would fade the editable base at once."""
        count = len(params["means"])
        info = editable_info(infos, kept)
        if step == 0 or info is None or count == 0:
            return
        self.state["sked_row"] = torch.arange(count, device=params["means"].device)  # the strategy carries it along
        try:
            self.strategy.step_post_backward(params=params, optimizers=optimizers, state=self.state, step=step,
                                             info=info, packed=False)
        finally:
            rows = self.state.pop("sked_row")
        if len(rows) != count or not torch.equal(rows, torch.arange(count, device=rows.device)):
            follow_densification(rows, count, params, reference)


def editable_info(infos: List[Dict], kept: int) -> Optional[Dict]:
    """The editable Gaussians' part of the step's renders, as one info the strategy reads: kept Gaussians come first
    in every render, so their `kept` columns are cut off; renders of different sizes are merged by scaling each
    one's gradients and radii to the strategy's normalisation ([-1, 1] screen units) beforehand."""
    grads, absgrads, radii = [], [], []
    for info in infos:
        means2d = info["means2d"]
        if means2d.grad is None or not torch.isfinite(means2d.grad).all():
            continue  # a skipped (non-finite) step leaves nothing to learn from
        to_screen = means2d.grad.new_tensor([info["width"] / 2.0, info["height"] / 2.0]) * info["n_cameras"]
        grad = means2d.grad[:, kept:]
        absgrad = getattr(means2d, "absgrad", None)
        absgrad = absgrad[:, kept:] if absgrad is not None else grad.abs()
        grads.append(grad * to_screen)
        absgrads.append(absgrad * to_screen)
        radius = info["radii"][:, kept:].float()
        radius = radius.amax(dim=-1) if radius.dim() == 3 else radius
        radii.append(radius * 2.0 / max(info["width"], info["height"]))  # the strategy divides by max(2, 2)
    if not grads:
        return None
    means2d = SimpleNamespace(grad=torch.cat(grads), absgrad=torch.cat(absgrads))
    return {"means2d": means2d, "radii": torch.cat(radii), "width": 2, "height": 2, "n_cameras": 1,
            "gaussian_ids": None}


@torch.no_grad()
def follow_densification(rows: Tensor, count: int, params: torch.nn.ParameterDict, reference: GaussianSet) -> None:
    """L_pres's targets after a refinement: `rows` says which of the `count` earlier Gaussians each one comes from. A
    pruned one's target goes with it; a split or duplicated one's children are held where the split put them (the
    parent's target would pull two children onto one spot, twice as opaque as the base there)."""
    rows = rows.long()
    densified = torch.bincount(rows, minlength=count)[rows] > 1
    targets = {name: value[rows].clone() for name, value in reference.tensors().items()}
    for name in GAUSSIAN_PARAMS:
        targets[name][densified] = params[name].detach()[densified].to(targets[name])
    reference.assign(targets)
