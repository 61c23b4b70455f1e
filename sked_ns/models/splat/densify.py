"""splatfacto's refinement (gsplat's DefaultStrategy) on the editable Gaussians only, with L_pres's targets following
each split, duplicate and prune."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Dict, List, Optional

import torch
from torch import Tensor

from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS


class EditableRefinement:
    """Mixed into the splat edit model: the strategy sees the editable Gaussians' share of each render."""

    def step_post_backward(self, step: int) -> None:
        """splatfacto's densification and pruning (gsplat's DefaultStrategy) on the editable Gaussians, from the
        gradients of the step's renders. Step 0 is skipped: the strategy resets opacities at every multiple of its
        reset interval, 0 included, which would fade the editable base at once."""
        infos, self._step_infos = self._step_infos, []
        count = len(self.gauss_params["means"])
        info = self._editable_info(infos)
        if step == 0 or info is None or count == 0:
            return
        self.strategy_state["sked_row"] = torch.arange(count, device=self.device)  # the strategy carries it along
        try:
            self.strategy.step_post_backward(params=self.gauss_params, optimizers=self.optimizers,
                                             state=self.strategy_state, step=step, info=info, packed=False)
        finally:
            rows = self.strategy_state.pop("sked_row")
        if len(rows) != count or not torch.equal(rows, torch.arange(count, device=rows.device)):
            self._follow_densification(rows, count)

    def _editable_info(self, infos: List[Dict]) -> Optional[Dict]:
        """The editable Gaussians' part of the step's renders, as one info the strategy reads: kept Gaussians come
        first in every render, so their columns are cut off; renders of different sizes are merged by scaling
        each one's gradients and radii to the strategy's normalisation ([-1, 1] screen units) beforehand."""
        kept = len(self.kept["means"])
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
    def _follow_densification(self, rows: Tensor, count: int) -> None:
        """L_pres's targets after a refinement: `rows` says which earlier Gaussian each one comes from. A pruned one's
        target goes with it; a split or duplicated one's children are held where the split put them (the parent's
        target would pull two children onto one spot, twice as opaque as the base there)."""
        rows = rows.long()
        densified = torch.bincount(rows, minlength=count)[rows] > 1
        targets = {name: value[rows].clone() for name, value in self.reference.tensors().items()}
        for name in GAUSSIAN_PARAMS:
            targets[name][densified] = self.gauss_params[name].detach()[densified].to(targets[name])
        self.reference.assign(targets)
