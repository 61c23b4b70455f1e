"""SKED on an instant-ngp base: occupancy-grid sampling with the edit box switched on.

An NGP base's occupancy grid is off wherever the base is empty, so new content could never
be sampled there. During the warm-up the edit box's cells are switched on and no cell is
pruned; after it, the grid follows the edited field as in instant-ngp. The grid sampler is
nerfacc's on CUDA and a plain-torch one elsewhere (`sked_ns.occupancy`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Tuple, Type

import nerfacc
import torch
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.ray_samplers import VolumetricSampler
from nerfstudio.models.instant_ngp import InstantNGPModelConfig, NGPModel
from torch import Tensor
from torch.nn import Parameter

from sked_ns.edit_box import occupancy_grid_mask
from sked_ns.occupancy import PortableOccGridEstimator, render_weights
from sked_ns.preservation import check_beta
from sked_ns.sked_core import SkedMixin, SkedOptions, copy_architecture, without_lpips

NGP_ARCHITECTURE_FIELDS = (
    "grid_resolution", "grid_levels", "max_res", "log2_hashmap_size", "alpha_thre", "cone_angle",
    "render_step_size", "near_plane", "far_plane", "use_gradient_scaling", "use_appearance_embedding",
    "background_color", "disable_scene_contraction",
)


@dataclass
class SkedNGPModelConfig(InstantNGPModelConfig, SkedOptions):
    """SKED on an instant-ngp field. Architecture fields are copied from the base."""

    _target: Type = field(default_factory=lambda: SkedNGPModel)
    grid_update_interval: int = 16
    """Iterations between occupancy-grid updates (instant-ngp: 16)."""


class SkedNGPModel(SkedMixin, NGPModel):
    """Editable NGP field and occupancy grid + frozen base + sketch geometry + guidance."""

    config: SkedNGPModelConfig
    BASE_PREFIXES = ("field.", "occupancy_grid.")

    def populate_modules(self) -> None:
        check_beta(self.config.beta)
        self.step = 0
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
        self._freeze_base(self.field, self.occupancy_grid)
        self._base.append(VolumetricSampler(occupancy_grid=self._base[1], density_fn=None))
        resolution = self.occupancy_grid.resolution.tolist()
        cells = occupancy_grid_mask(self.edit_box, self.scene_aabb.tolist(), resolution, self.config.grid_levels)
        self.register_buffer("edit_box_cells", cells.to(self.occupancy_grid.binaries.device), persistent=False)
        self._switch_on_edit_box()

    # ---- the occupancy grid ----------------------------------------------------------------
    @torch.no_grad()
    def _switch_on_edit_box(self) -> None:
        self.occupancy_grid.binaries |= self.edit_box_cells

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        return [TrainingCallback(where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                                 update_every_num_iters=1, func=self.update_occupancy_grid)]

    @torch.no_grad()
    def update_occupancy_grid(self, step: int) -> None:
        """instant-ngp's EMA update; during the warm-up no cell turns off and the edit box stays on."""
        self.step = step
        grid = self.occupancy_grid
        before = grid.binaries.clone()
        # The base's cells are already known: sample them like instant-ngp after its own warm-up.
        grid.update_every_n_steps(
            step=step, occ_eval_fn=lambda x: self.field.density_fn(x) * self.config.render_step_size,
            n=self.config.grid_update_interval, warmup_steps=0,
        )
        if self.edit_box_boost() > 0:
            grid.binaries |= before | self.edit_box_cells

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return self._hash_grid_groups(fields=self.field)

    # ---- rendering ------------------------------------------------------------------------
    def _render_with(self, ray_bundle: RayBundle, field_module, sampler) -> Tuple[Dict[str, Tensor], RaySamples, Dict]:
        num_rays = len(ray_bundle)
        with torch.no_grad():
            ray_samples, ray_indices = sampler(
                ray_bundle=ray_bundle, near_plane=self.config.near_plane, far_plane=self.config.far_plane,
                render_step_size=self.config.render_step_size, alpha_thre=self.config.alpha_thre,
                cone_angle=self.config.cone_angle,
            )
        field_outputs = field_module(ray_samples)
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
        return outputs, ray_samples, field_outputs

    def _render(self, ray_bundle: RayBundle):
        return self._render_with(ray_bundle, self.field, self.sampler)

    @torch.no_grad()
    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        base_field, _, base_sampler = self._base
        outputs = self._render_with(ray_bundle, base_field, base_sampler)[0]
        return {key: value for key, value in outputs.items() if not key.startswith("_")}

    def get_outputs(self, ray_bundle: RayBundle):
        outputs, samples, _ = self._render(ray_bundle)
        weights, ray_indices = outputs.pop("_weights"), outputs.pop("_ray_indices")
        if not self.training:
            preservation = self.preservation_weight(samples.frustums.get_positions())
            preserved = nerfacc.accumulate_along_rays(
                (weights * preservation)[..., 0], values=None, ray_indices=ray_indices, n_rays=len(ray_bundle)
            )
            # Background counts as preserved: the viewer shows where the edit may act.
            outputs["preservation_weight"] = preserved + (1 - outputs["accumulation"]).clamp(0, 1)
            outputs = self._steer(ray_bundle, outputs)
        return outputs


def copy_ngp_architecture(target: SkedNGPModelConfig, base_model_config) -> None:
    """Make the edit's field and grid the base's shape."""
    copy_architecture(target, base_model_config, NGP_ARCHITECTURE_FIELDS)
