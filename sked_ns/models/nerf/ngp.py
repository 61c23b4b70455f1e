"""SKED on an instant-ngp base: occupancy-grid sampling with the sketches' visual hull switched on.

An NGP base's occupancy grid is off wherever the base is empty, so new content could never
be sampled there. During the warm-up the cells of the sketches' visual hull (inside the edit
box) are switched on and no cell is pruned; after it, the grid follows the edited field as in instant-ngp. The grid sampler is
nerfacc's on CUDA and a plain-torch one elsewhere (`sked_ns.models.nerf.occupancy`).

A local edit (local_field.py) is its base outside its box, and so is its grid: only the cells that box
meets are updated, every other cell stays the frozen base's, and the checkpoint holds the cells that differ from the
base's grid (`occupancy.grid_changes`), rebuilt over the base's grid at load.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.ray_samplers import VolumetricSampler
from nerfstudio.models.instant_ngp import InstantNGPModelConfig, NGPModel
from torch import Tensor
from torch.nn import Parameter

from sked_ns.method.edit_box import EditBox, occupancy_grid_mask
from sked_ns.method.options import SkedOptions, taken_from_the_base, without_lpips
from sked_ns.method.preservation import check_beta
from sked_ns.models.nerf.field_edit import NERF_EDIT_OWNED, SkedMixin
from sked_ns.models.nerf.nerfacc_backend import install_lazy_backend
from sked_ns.models.nerf.occupancy import (
    GRID_CHANGES,
    PortableOccGridEstimator,
    grid_changes,
    grid_with_changes,
    render_weights,
)

EMA_DECAY, OCC_THRESHOLD = 0.95, 0.01
"""instant-ngp's grid update (nerfacc's `OccGridEstimator._update` defaults)."""
GRID_PREFIXES = ("occupancy_grid.", "sampler.occupancy_grid.")
"""Where the edit's grid appears in its state (the sampler holds the same module)."""


@dataclass
class SkedNGPModelConfig(InstantNGPModelConfig, SkedOptions):
    """SKED on an instant-ngp field. Architecture fields are copied from the base (options.copy_base_architecture)."""

    EDIT_OWNED = NERF_EDIT_OWNED

    _target: Type = field(default_factory=lambda: SkedNGPModel)
    grid_update_interval: int = 16
    """Iterations between occupancy-grid updates (instant-ngp: 16)."""



taken_from_the_base(SkedNGPModelConfig, InstantNGPModelConfig)  # the base's architecture: not typeable

class SkedNGPModel(SkedMixin, NGPModel):
    """Editable NGP field and occupancy grid + frozen base + sketch geometry + guidance."""

    config: SkedNGPModelConfig
    BASE_PREFIXES = ("field.", "occupancy_grid.")

    def populate_modules(self) -> None:
        check_beta(self.config.beta)
        install_lazy_backend()  # nerfacc's kernel calls of this process get kernels that build here
        self.config = self._scaled_config()
        with without_lpips():
            super().populate_modules()  # fills in render_step_size when the base left it automatic
        self.config.render_step_size = self.config.render_step_size / self.config.samples_per_ray_scale
        # nerfacc's grid, sampling in torch where its CUDA kernels cannot run.
        self.occupancy_grid = PortableOccGridEstimator(
            roi_aabb=self.scene_aabb, resolution=self.config.grid_resolution, levels=self.config.grid_levels
        )
        self.sampler = VolumetricSampler(occupancy_grid=self.occupancy_grid, density_fn=self.field.density_fn)
        self._setup_sked()
        self._load_base_weights()
        self._freeze_base(field=self.field, occupancy_grid=self.occupancy_grid)
        # The base's own sampler: its grid and its density (culling empty and hidden samples, as the base renders).
        base = self.frozen_base
        self.frozen_base = base.with_sampler(VolumetricSampler(occupancy_grid=base.occupancy_grid, density_fn=base.field.density_fn))
        # The edit's grid and marcher see kept cells as the base's: a kept cell never turns off.
        self.held_density = self.edit_density_fn(self.in_chunks(self.field.density_fn, self.field),
                                                 self.in_chunks(base.field.density_fn, base.field))
        self.sampler.density_fn = self.held_density
        resolution = self.occupancy_grid.resolution.tolist()
        cells = occupancy_grid_mask(self.edit_box, self.scene_aabb.tolist(), resolution, self.config.grid_levels)
        cells = self._hull_cells(cells)
        self.register_buffer("edit_box_cells", cells.to(self.occupancy_grid.binaries.device), persistent=False)
        self.register_buffer("edit_cells", self._edit_cells(), persistent=False)
        self._switch_on_edit_box()

    def _edit_cells(self) -> Optional[Tensor]:
        """Flat indices (as the grid's `occs`) of the cells a local edit can change: those its box meets,
        and the edit box's switched-on cells; None for a whole-field copy, which can change any."""
        if self.local_field is None:
            return None
        low, high = self.local_field.box.cpu().numpy()
        meets = occupancy_grid_mask(EditBox(min=low, max=high), self.scene_aabb.tolist(),
                                    self.occupancy_grid.resolution.tolist(), self.config.grid_levels)
        meets = meets.to(self.edit_box_cells.device) | self.edit_box_cells
        return meets.reshape(-1).nonzero()[:, 0]

    @torch.no_grad()
    def _hull_cells(self, cells: Tensor) -> Tensor:
        """Of the edit box's cells, those the sketches' visual hull reaches (a 3x3x3 lattice per cell tested):
        new mass belongs in the hull, and cells in the box's empty corners only grow haze."""
        index = cells.nonzero()
        if len(index) == 0:
            return cells
        aabbs = self.occupancy_grid.aabbs.cpu()[index[:, 0]]
        resolution = self.occupancy_grid.resolution.cpu().float()
        lattice = torch.stack(torch.meshgrid(*[torch.tensor([0.0, 0.5, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
        unit = (index[:, None, 1:].float() + lattice[None]) / resolution
        points = aabbs[:, None, :3] + unit * (aabbs[:, None, 3:] - aabbs[:, None, :3])
        # Half a lattice step seen from the sketch cameras, in image widths: thin parts between lattice points count.
        step = float(((aabbs[-1, 3:] - aabbs[-1, :3]) / resolution).norm()) / 2  # the coarsest level present
        views = self.sketch_set.views
        tolerance = max(step * view.fl_x / (view.width * float(np.linalg.norm(view.camera_to_world[:, 3] - self.edit_box.center)))
                        for view in views)
        reached = self.in_sketch_hull(points.reshape(-1, 3), tolerance).reshape(len(index), -1).any(dim=-1)
        hull = torch.zeros_like(cells)
        hull[tuple(index[reached].T)] = True
        return hull

    # ---- the occupancy grid ----------------------------------------------------------------
    @torch.no_grad()
    def _switch_on_edit_box(self) -> None:
        self.occupancy_grid.binaries |= self.edit_box_cells

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        return [self.sked_step_callback(),
                TrainingCallback(where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                                 update_every_num_iters=1, func=self.update_occupancy_grid)]

    @torch.no_grad()
    def update_occupancy_grid(self, step: int) -> None:
        """instant-ngp's EMA update; during the warm-up no cell turns off and the visual hull's cells stay on."""
        if step % self.config.grid_update_interval:
            return
        if self.local_field is not None:
            return self._update_edit_cells()
        grid = self.occupancy_grid
        before = grid.binaries.clone()
        # The base's cells are already known: sample them like instant-ngp after its own warm-up.
        grid.update_every_n_steps(
            step=step, occ_eval_fn=lambda x: self.held_density(x) * self.config.render_step_size,
            n=self.config.grid_update_interval, warmup_steps=0,
        )
        if self.edit_box_boost() > 0:
            grid.binaries |= before | self.edit_box_cells

    @torch.no_grad()
    def _update_edit_cells(self) -> None:
        """instant-ngp's EMA update on the cells a local edit can change, each sampled at a random point: outside
        them the edit's density is the base's, and so is its grid."""
        grid, cells = self.occupancy_grid, self.edit_cells
        if len(cells) == 0:  # a box outside every grid level: nothing the edit changes is marched
            return
        boxes = grid.aabbs[cells // grid.cells_per_lvl]
        unit = (grid.grid_coords[cells % grid.cells_per_lvl] + torch.rand(len(cells), 3, device=cells.device)) / grid.resolution
        occupancy = self.held_density(boxes[:, :3] + unit * (boxes[:, 3:] - boxes[:, :3]))[..., 0] * self.config.render_step_size
        occs, binaries = grid.occs, grid.binaries.view(-1)
        occs[cells] = torch.maximum(occs[cells] * EMA_DECAY, occupancy)
        seen = occs >= 0  # nerfacc marks cells no camera sees with -1
        threshold = ((occs * seen).sum() / seen.sum().clamp_min(1)).clamp(max=OCC_THRESHOLD)
        on = occs[cells] > threshold
        if self.edit_box_boost() > 0:
            on |= binaries[cells] | self.edit_box_cells.view(-1)[cells]
        binaries[cells] = on

    # ---- what a checkpoint holds ------------------------------------------------------------
    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """A local edit's grid saved as its changes to the base's grid (the base's is read from the base copy)."""
        state = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        if self.local_field is not None:
            for key in [prefix + grid + name for grid in GRID_PREFIXES for name in ("occs", "binaries")]:
                state.pop(key, None)
            changes = grid_changes(self.occupancy_grid, self.frozen_base.occupancy_grid)
            state.update({f"{prefix}occupancy_grid.{name}": value for name, value in changes.items()})
        return state

    def load_state_dict(self, state_dict, strict: bool = True, *args, **kwargs):
        """A grid saved as its changes is rebuilt over the frozen base's; a whole grid (0.8) loads as it is."""
        state = dict(state_dict)
        if "occupancy_grid.changed_cells" in state:
            changes = {name: state.pop(f"occupancy_grid.{name}") for name in GRID_CHANGES}
            occs, binaries = grid_with_changes(self.frozen_base.occupancy_grid, changes)
            for grid in GRID_PREFIXES:
                state[f"{grid}occs"], state[f"{grid}binaries"] = occs, binaries
        return super().load_state_dict(state, strict, *args, **kwargs)

    def _use_earlier_edit(self, state: Dict[str, Tensor]) -> None:
        super()._use_earlier_edit(state)
        # The earlier edit's grid as it rendered it (its checkpoint may hold only its changes to its own base's).
        self.occupancy_grid.load_state_dict(self.__dict__["_earlier"].occupancy_grid.state_dict())

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return self._hash_grid_groups(fields=self.field)

    # ---- rendering ------------------------------------------------------------------------
    def _render_with(self, ray_bundle: RayBundle, field_module, sampler, alpha_thre: float) -> Tuple[Dict[str, Tensor], RaySamples, Dict]:
        num_rays = len(ray_bundle)
        sampler.train(self.training)  # the frozen base's sampler is outside the module tree: follow the model
        with torch.no_grad():
            ray_samples, ray_indices = sampler(
                ray_bundle=ray_bundle, near_plane=self.config.near_plane, far_plane=self.config.far_plane,
                render_step_size=self.config.render_step_size, alpha_thre=alpha_thre,
                cone_angle=self.config.cone_angle,
            )
        base_outputs = None
        if field_module is self.field:
            field_outputs, base_outputs = self._held_outputs(ray_samples, lambda field, samples: field(samples))
        else:
            field_outputs = self.in_chunks(field_module, field_module)(ray_samples)
        weights = render_weights(
            ray_samples.frustums.starts[..., 0], ray_samples.frustums.ends[..., 0],
            field_outputs[FieldHeadNames.DENSITY][..., 0], ray_indices, num_rays,
        )[..., None]
        outputs = {
            "rgb": self.renderer_rgb(rgb=field_outputs[FieldHeadNames.RGB], weights=weights,
                                     ray_indices=ray_indices, num_rays=num_rays),
            "depth": self.renderer_depth(weights=weights, ray_samples=ray_samples, ray_indices=ray_indices,
                                         num_rays=num_rays),
            "accumulation": self.renderer_accumulation(weights=weights, ray_indices=ray_indices, num_rays=num_rays),
            "num_samples_per_ray": torch.bincount(ray_indices, minlength=num_rays),
        }
        outputs["_weights"], outputs["_ray_indices"] = weights, ray_indices
        if base_outputs is not None:
            outputs["_base_field_outputs"] = base_outputs  # L_pres compares the two at the same samples
        return outputs, ray_samples, field_outputs

    def _render(self, ray_bundle: RayBundle):
        # No alpha culling while training (as the authors' marcher): the new content's samples start
        # with alpha ~0, and culling them would starve L_sil of gradient inside the empty sketch.
        alpha_thre = 0.0 if self.training else self.config.alpha_thre
        return self._render_with(ray_bundle, self.field, self.sampler, alpha_thre)

    @torch.no_grad()
    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        base = self.frozen_base
        outputs, samples, _ = self._render_with(ray_bundle, base.field, base.sampler, self.config.alpha_thre)
        return self._with_preservation(outputs, samples)

    def get_outputs(self, ray_bundle: RayBundle):
        outputs, samples, _ = self._render(ray_bundle)
        if self.training:
            return {key: value for key, value in outputs.items() if not key.startswith("_")}
        return self._steer(ray_bundle, self._with_preservation(outputs, samples))

    def _with_preservation(self, outputs: Dict[str, Tensor], samples: RaySamples) -> Dict[str, Tensor]:
        weights, ray_indices = outputs.pop("_weights"), outputs.pop("_ray_indices")
        outputs.pop("_base_field_outputs", None)
        outputs["preservation_weight"] = self.expected_preservation(
            samples.frustums.get_positions(), weights, outputs["accumulation"], ray_indices=ray_indices)
        return outputs

