"""SKED on a nerfacto base: proposal-network sampling, forced into the edit box at first."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Type

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import interlevel_loss
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from torch import Tensor
from torch.nn import Parameter

from sked_ns.preservation import check_beta
from sked_ns.sked_core import (  # noqa: F401  (re-exported: the public names of the edit model)
    SkedMixin,
    SkedOptions,
    SkedSettingsWarning,
    copy_architecture,
    warn_degenerate_settings,
    without_lpips as _without_lpips,
)

# Architecture of the base that the edit must share to load its weights.
ARCHITECTURE_FIELDS = (
    "hidden_dim", "hidden_dim_color", "hidden_dim_transient", "num_levels", "base_res", "max_res",
    "log2_hashmap_size", "features_per_level", "num_proposal_iterations", "num_proposal_samples_per_ray",
    "num_nerf_samples_per_ray", "proposal_net_args_list", "use_same_proposal_network", "use_appearance_embedding",
    "appearance_embed_dim", "use_average_appearance_embedding", "disable_scene_contraction", "predict_normals",
    "implementation", "background_color", "near_plane", "far_plane", "proposal_initial_sampler",
    "average_init_density", "use_single_jitter",
)


@dataclass
class SkedModelConfig(NerfactoModelConfig, SkedOptions):
    """SKED on a nerfacto-style field. Architecture fields are copied from the base."""

    _target: Type = field(default_factory=lambda: SkedModel)
    edit_box_density: float = 2.0
    """Proposal density added inside the edit box during warm-up, per unit of box diagonal."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Edits keep the base's cameras."""


class SkedModel(SkedMixin, NerfactoModel):
    """Editable nerfacto field + frozen base + sketch geometry + guidance."""

    config: SkedModelConfig
    BASE_PREFIXES = ("field.", "proposal_networks.")

    def populate_modules(self) -> None:
        check_beta(self.config.beta)
        self.config = self._scaled_config()
        scale = self.config.samples_per_ray_scale
        self.config.num_nerf_samples_per_ray = max(4, round(self.config.num_nerf_samples_per_ray * scale))
        self.config.num_proposal_samples_per_ray = tuple(
            max(4, round(n * scale)) for n in self.config.num_proposal_samples_per_ray
        )
        with _without_lpips():
            super().populate_modules()
        self._setup_sked()
        self._load_base_weights()
        self._freeze_base(self.field, self.proposal_networks)
        self._boost_proposals_in_edit_box()
        self._captured: Dict[str, object] = {}
        self._capture_field_samples()

    @torch.no_grad()
    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """The frozen base seen along `ray_bundle` (already collided), e.g. for comparisons."""
        edit_field, edit_density_fns = self.field, self.density_fns
        captured = self._captured
        base_field, base_proposals = self._base
        try:
            object.__setattr__(self, "field", base_field)  # swap without registering a submodule
            self.density_fns = [network.density_fn for network in base_proposals]
            return NerfactoModel.get_outputs(self, ray_bundle)
        finally:
            object.__setattr__(self, "field", edit_field)
            self.density_fns = edit_density_fns
            self._captured = captured

    # ---- sampling the edit region -----------------------------------------------------------
    def _boost_proposals_in_edit_box(self) -> None:
        """Add density inside the edit box to the proposal networks during warm-up.

        A nerfacto base has no mass where the new content goes, so its proposal networks
        would never place samples there; the boost does until they learn the new mass.
        """
        low = torch.tensor(self.edit_box.min, dtype=torch.float32)
        high = torch.tensor(self.edit_box.max, dtype=torch.float32)
        diagonal = float(torch.linalg.norm(high - low).clamp_min(1e-6))

        def boosted(density_fn):
            def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
                value = density_fn(positions, times)
                strength = self.config.edit_box_density * self.edit_box_boost()
                if strength > 0:
                    inside = ((positions >= low.to(positions.device)) & (positions <= high.to(positions.device))).all(-1)
                    value = value + strength / diagonal * inside[..., None].to(value.dtype)
                return value

            return density

        self.density_fns = [boosted(fn) for fn in self.density_fns]

    def _capture_field_samples(self) -> None:
        """Keep the last samples and field outputs: L_pres needs them, nerfacto returns neither.

        nerfacto calls `self.field.forward(...)` directly, which skips module hooks, so the
        bound method is wrapped instead.
        """
        forward = self.field.forward

        def capturing_forward(ray_samples, *args, **kwargs):
            outputs = forward(ray_samples, *args, **kwargs)
            self._captured = {"ray_samples": ray_samples, "field_outputs": outputs}
            return outputs

        self.field.forward = capturing_forward

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = self._hash_grid_groups(proposal_networks=self.proposal_networks, fields=self.field)
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    # ---- rendering ------------------------------------------------------------------------
    def _render(self, ray_bundle: RayBundle):
        outputs = NerfactoModel.get_outputs(self, ray_bundle)
        return outputs, self._captured["ray_samples"], self._captured["field_outputs"]

    def _sampling_losses(self, rendered: Sequence[Dict[str, Tensor]]) -> Dict[str, Tensor]:
        loss = sum(interlevel_loss(r["weights_list"], r["ray_samples_list"]) for r in rendered)
        return {"interlevel_loss": self.config.interlevel_loss_mult * loss}

    def get_outputs(self, ray_bundle: RayBundle):
        outputs = super().get_outputs(ray_bundle)
        samples = self._captured.get("ray_samples")
        if samples is not None and not self.training:
            weights = outputs.get("weights_list", [None])[-1]
            if weights is None:
                weights = samples.get_weights(self._captured["field_outputs"][FieldHeadNames.DENSITY])
            preservation = self.preservation_weight(samples.frustums.get_positions())
            # Background counts as preserved: the viewer shows where the edit may act.
            accumulation = weights.sum(dim=-2)
            outputs["preservation_weight"] = (weights * preservation).sum(dim=-2) + (1 - accumulation).clamp(0, 1)
            outputs = self._steer(ray_bundle, outputs)
        return outputs


def copy_base_architecture(target: SkedModelConfig, base_model_config) -> None:
    """Make the edit's field the base's shape (hash grids, MLPs, proposal networks)."""
    copy_architecture(target, base_model_config, ARCHITECTURE_FIELDS)
