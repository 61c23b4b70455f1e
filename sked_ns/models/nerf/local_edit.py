"""A NeRF edit local to its box (local_field.py): what it builds, evaluates, trains and saves.

`SkedMixin` takes these methods. `local_field` is a `LocalField` (the base's networks moved over the box), or a
`LocalResidual` (a residual on the base's outputs) where the base is itself a local edit or the edit was saved so.
With `nerf_edit_field = "full-copy"`, on a base whose grid and MLP are fused (tiny-cuda-nn), and for an edit saved
by 0.7 or earlier (found by its checkpoint's keys) `local_field` is None and the edit is a trainable copy of the
whole base.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.rays import RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from torch import Tensor

from sked_ns.method.frozen_base import FrozenBase, base_weights
from sked_ns.method.photo_anchor import editable_box
from sked_ns.models.nerf.colour_residual import ColourResidual
from sked_ns.models.nerf.density_grid import AddedMassGrid
from sked_ns.models.nerf.edited_base import EditedField, EditedProposal, earlier_edit, is_saved_residual
from sked_ns.models.nerf.held_field import hold
from sked_ns.models.nerf.local_field import (
    FULL_COPY,
    LOCAL_RESIDUAL,
    LocalField,
    LocalResidual,
    base_grid_extent,
    box_grid_shape,
    local_grid_shape,
)

LOCAL_UNSAVED = ("field.", "proposal_networks.")
"""A local edit's modules that are its base's (read from the edit's base copy, never saved with it)."""
BASE_KEY = "base"
"""A chunked LocalField evaluation's outputs: the base's under (this, name) beside the edit's."""
ADDED_GRID_RESOLUTION = 32
"""Cells across a LocalField edit's box in its added-mass grid (density_grid.AddedMassGrid)."""


class LocalEdit:
    """The local edit's part of a NeRF edit model (a mixin of `field_edit.SkedMixin`)."""

    local_field: Optional[torch.nn.Module]  # LocalField or LocalResidual; set by SkedMixin._setup_sked
    hull_proposal: Optional[torch.nn.Module]  # a LocalField edit's learned proposal share (nerfacto.py), else None

    def _local_edit(self) -> torch.nn.Module:
        """The edit's capacity over the box bounding every point with w <= keep_threshold (and the edit box): the
        base's networks moved over it (LocalField), or a residual on the base's outputs (LocalResidual)."""
        low, high = self._local_box()
        if self.config.nerf_edit_field == LOCAL_RESIDUAL:
            shape = local_grid_shape(self.field.mlp_base, base_grid_extent(self.field), high - low)
            # A density per box diagonal: larger scales fill faster but haze the box (docs/method.md, Local edit).
            return LocalResidual(low, high, shape, density_scale=1.0 / max(float(np.linalg.norm(high - low)), 1e-6))
        return LocalField(low, high, box_grid_shape(self.field.mlp_base, base_grid_extent(self.field), high - low),
                          self.field)

    def _local_box(self) -> Tuple[np.ndarray, np.ndarray]:
        box = editable_box(lambda p: self.preservation_weight(p)[..., 0], self.editable_search_box(),
                           min(self.config.keep_threshold, 1.0))
        low, high = self.edit_box.min, self.edit_box.max
        if box is not None:
            low, high = np.minimum(low, box[:3].numpy()), np.maximum(high, box[3:].numpy())
        return low, high

    def _use_residual(self) -> None:
        """The local edit as a residual on its base's outputs (an earlier local edit as the base; a saved residual)."""
        if not isinstance(self.local_field, LocalResidual):
            self.config.nerf_edit_field = LOCAL_RESIDUAL
            self.local_field = self._local_edit().to(self.edit_box_bounds.device)
            self.colour_residual = None  # the residual owns its colour
            self.hull_proposal = None  # it renders with the hull as its proposal density

    # ---- what a checkpoint holds ---------------------------------------------------------------
    def _base_modules(self) -> List[torch.nn.Module]:
        return [getattr(self, prefix.rstrip(".")) for prefix in self.BASE_PREFIXES]

    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """A local edit's checkpoint holds the edit alone: the base's modules are read from its base copy."""
        state = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        if self.local_field is not None:
            unsaved = tuple(prefix + name for name in LOCAL_UNSAVED)
            for key in [key for key in state if key.startswith(unsaved)]:
                del state[key]
        return state

    def load_state_dict(self, state_dict, strict: bool = True, *args, **kwargs):
        """A local edit's checkpoint completed by the base's modules as loaded; an edit saved with a whole field
        (0.7 and before) switches this model to that representation first."""
        state = dict(state_dict)
        if self.local_field is not None and any(key.startswith(LOCAL_UNSAVED) for key in state):
            self._use_full_copy()
        elif self.local_field is not None:
            if is_saved_residual(state):  # e.g. 0.8's local edit under a config.yml that says "local"
                self._use_residual()
            whole = torch.nn.Module.state_dict(self)
            # The base's modules; and for a 0.9 edit a fresh hull proposal and colour residual, which start as nothing.
            completed = LOCAL_UNSAVED + ("hull_proposal.", "colour_residual.")
            state.update({key: value for key, value in whole.items() if key.startswith(completed) and key not in state})
        return super().load_state_dict(state, strict, *args, **kwargs)

    def _use_full_copy(self) -> None:
        """The edit as a trainable copy of the whole base (how 0.7 and earlier saved it)."""
        self.local_field = None
        self.hull_proposal = None  # the copy trains its proposal networks
        self.config.nerf_edit_field = FULL_COPY
        for module in self._base_modules():
            module.requires_grad_(True)
        if getattr(self.field, "embedding_appearance", None) is not None:
            self.field.embedding_appearance.requires_grad_(False)
        if self.config.colour_residual:
            self.colour_residual = ColourResidual(self.edit_box.min, self.edit_box.max).to(self.edit_box_bounds.device)

    def _local_outputs(self, ray_samples: RaySamples, evaluate_base) -> Tuple[Dict, Dict]:
        """(the base's field outputs moved by the local residual, kept samples the base's; the base's)."""
        local, colour = self.local_field, self.config.colour_residual
        if isinstance(local, LocalField):
            return self._local_field_outputs(ray_samples, evaluate_base)
        with torch.no_grad():
            base = self.in_chunks(evaluate_base, self.base_field)(ray_samples)

        def residual(points: Tensor, density: Tensor, rgb: Tensor, editable: Tensor) -> Dict[str, Tensor]:
            inside, raw = local(points)
            return {FieldHeadNames.DENSITY: local.density(density, inside, raw, editable),
                    FieldHeadNames.RGB: local.colour(rgb, inside, raw, editable) if colour else rgb}

        positions = ray_samples.frustums.get_positions()
        weight = self.preservation_weight(positions)
        edited = self.in_chunks(residual, local)(positions, base[FieldHeadNames.DENSITY], base[FieldHeadNames.RGB],
                                                 (1.0 - weight).clamp(0.0, 1.0))
        return hold({**base, **edited}, base, self._held(weight)), base

    def _local_field_outputs(self, ray_samples: RaySamples, evaluate_base) -> Tuple[Dict, Dict]:
        """A LocalField edit's outputs and its base's from one pass: the base's grid features and direction encoding
        are read once for both (LocalField.forward, `with_base`), the preservation weights once for the colour
        residual and the hold. A base predicting normals is also called itself for them (the edit shows its base's)."""
        local, field = self.local_field, self.base_field
        weight = self._sample_weights(ray_samples.frustums.get_positions())

        def both(samples: RaySamples, weight: Optional[Tensor]) -> Dict[str, Tensor]:
            outputs, inside, base = local(field, samples, with_base=True)
            outputs = self._edit_colour(outputs, samples, weight)  # new colours near the sketches (colour_residual.py)
            edited = {key: torch.where(inside, value, base[key].to(value.dtype)) for key, value in outputs.items()}
            return {**edited, **{(BASE_KEY, key): value for key, value in base.items()}}

        # The base's modes (a photo's appearance while training) are the render's in the backward pass's re-run too.
        out = self.in_chunks(both, local, field)(ray_samples, weight)
        base = {key[1]: value for key, value in out.items() if isinstance(key, tuple)}
        if getattr(self.config, "predict_normals", False):
            with torch.no_grad():
                base = {**self.in_chunks(evaluate_base, field)(ray_samples), **base}
        edited = {key: value for key, value in out.items() if not isinstance(key, tuple)}
        return hold({**base, **edited}, base, None if weight is None else self._held(weight)), base

    def edit_density_fn(self, edit_fn, base_fn, proposal: bool = False):
        """The edit's density for samplers and occupancy grids: the base's at kept points; elsewhere `edit_fn` (a
        trainable copy) or, for a local edit, the base's moved by the residual (without gradient). A `proposal`
        network's density is not the field's: a LocalField edit keeps the base's (nerfacto.py adds its new mass)."""
        held = self.held_density_fn(edit_fn, base_fn)

        def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
            if self.local_field is None:
                return held(positions, times)
            if proposal and isinstance(self.local_field, LocalField):  # its new mass: the hull's (nerfacto.py)
                return base_fn(positions, times)
            return self._local_density(base_fn, positions, times)

        return density

    def _added_mass_grid(self) -> AddedMassGrid:
        """A LocalField edit's added-mass grid for its proposals (density_grid.AddedMassGrid), from the field as it is."""
        grid, local = self.__dict__.get("_added_grid"), self.local_field
        if grid is None or grid.box.device != local.box.device:
            grid = self.__dict__["_added_grid"] = AddedMassGrid(local.box[0], local.box[1], ADDED_GRID_RESOLUTION)
        # Any in-place change of a parameter (an optimiser step, a load) bumps its version: a host-side count, no sync.
        version = sum(parameter._version for parameter in local.parameters())
        if version != grid.version:
            grid.refresh(self._added_density, version)
        return grid

    def _added_density(self, positions: Tensor) -> Tensor:
        """A LocalField edit's density above its base's where it renders it: 0 at kept points, which render the base."""
        added = self.local_field.density(self.base_field, positions, added=True)[0]
        kept = self._kept(positions)
        return added if kept is None else added * ~kept[..., None]

    @torch.no_grad()
    def _local_density(self, base_fn, positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        # In the field's chunks: a sampler asks at every sample it marches, and the base's grid, the local field and
        # the preservation weights read over all of them at once grew with the rays (docs/benchmarks.md).
        return self.in_chunks(functools.partial(self._local_density_at, base_fn), self.local_field,
                              self.base_field)(positions, times)

    def _local_density_at(self, base_fn, positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        base = base_fn(positions, times)
        weight = self.preservation_weight(positions)
        kept = self._held(weight)
        if isinstance(self.local_field, LocalField):
            density, _, inside = self.local_field.density(self.base_field, positions)
            edited = torch.where(inside, density.to(base.dtype), base)
        else:
            edited = self.local_field.density_at(base, positions, (1.0 - weight).clamp(0.0, 1.0))
        return edited if kept is None else torch.where(kept[..., None], base, edited)

    def field_density(self, positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        """This local edit's field density at positions, without gradient (the next edit's base density)."""
        return self._local_density(self.base_field.density_fn, positions, times)

    # ---- an earlier local edit as the base (edited_base.py) -------------------------------------
    def _use_earlier_edit(self, state: Dict[str, Tensor]) -> None:
        # The earlier edit's outputs are the base, with no whole field to copy and no grid to read apart from its
        # networks: only a residual on outputs moves them (options.copy_base_architecture chose it already).
        self._use_residual()
        earlier = earlier_edit(base_weights(self.config), state, scene_box=self.scene_box,
                               num_train_data=self.num_train_data, **self.kwargs)
        self.__dict__["_earlier"] = earlier  # not a submodule: never trained or saved; the frozen base holds it
        # What the earlier edit saved of the base's modules (instant-ngp: its occupancy grid), as it left them.
        kept = {key: value for key, value in state.items() if key.startswith(self.BASE_PREFIXES)}
        torch.nn.Module.load_state_dict(self, kept, strict=False)
        self._base_cameras = earlier._base_cameras

    def _earlier_as_base(self, frozen: FrozenBase) -> FrozenBase:
        earlier = self.__dict__["_earlier"]
        proposals = frozen.proposal_networks
        if proposals is not None:
            proposals = torch.nn.ModuleList([EditedProposal(earlier, i) for i in range(len(proposals))])
        # Frozen modules rest in eval mode (the average appearance): training switches them only for a step.
        return dataclasses.replace(frozen, field=EditedField(earlier).eval(), proposal_networks=proposals)
