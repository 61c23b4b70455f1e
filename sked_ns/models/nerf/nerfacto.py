"""SKED on a nerfacto base: proposal-network sampling, forced into the edit box at first."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import interlevel_loss, scale_gradients_by_distance_squared
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from torch import Tensor
from torch.nn import Parameter

from sked_ns.method.options import (  # noqa: F401  (re-exported: the public names of the edit model)
    SkedOptions,
    SkedSettingsWarning,
    taken_from_the_base,
    warn_degenerate_settings,
    without_lpips,
)
from sked_ns.method.preservation import check_beta
from sked_ns.models.nerf.density_grid import BaseDensityGrid, HullProposal
from sked_ns.models.nerf.field_edit import NERF_EDIT_OWNED, SkedMixin
from sked_ns.models.nerf.local_field import LocalField


@dataclass
class SkedNerfactoModelConfig(NerfactoModelConfig, SkedOptions):
    """SKED on a nerfacto-style field. Architecture fields are copied from the base (options.copy_base_architecture)."""

    EDIT_OWNED = NERF_EDIT_OWNED

    _target: Type = field(default_factory=lambda: SkedNerfactoModel)
    edit_box_density: float = 2.0
    """Proposal density added inside the sketches' visual hull (within the edit box) during warm-up, per unit
    of box diagonal. A local edit samples its new content with it for the whole edit, and renders it with it (its
    proposals are the base's: docs/method.md, Local edit): 0 leaves a local edit nothing new to sample."""
    base_proposal_grid: int = 128
    """The frozen base's proposal densities, which decide where kept space is sampled, read from a grid of this many
    cells a side sampled once per edit (at most each network's finest hash level; models/nerf/density_grid.py), not
    evaluated at every proposal sample of every step. 0: the networks themselves (exact, at every proposal
    sample of every step)."""
    hull_proposal_grid: int = 32
    """Cells a side of a local edit's learned share of its hull's proposal density, a grid over the edit box trained
    by the interlevel loss (models/nerf/density_grid.HullProposal): its samples move to the new surface. 0: none, the
    hull sampled evenly (0.9's local edits, which resume so)."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Edits keep the base's cameras."""



taken_from_the_base(SkedNerfactoModelConfig, NerfactoModelConfig)  # the base's architecture: not typeable

class SkedNerfactoModel(SkedMixin, NerfactoModel):
    """Editable nerfacto field + frozen base + sketch geometry + guidance."""

    config: SkedNerfactoModelConfig
    BASE_PREFIXES = ("field.", "proposal_networks.")

    def populate_modules(self) -> None:
        check_beta(self.config.beta)
        self.config = self._scaled_config()
        scale = self.config.samples_per_ray_scale
        self.config.num_nerf_samples_per_ray = max(4, round(self.config.num_nerf_samples_per_ray * scale))
        self.config.num_proposal_samples_per_ray = tuple(
            max(4, round(n * scale)) for n in self.config.num_proposal_samples_per_ray
        )
        with without_lpips():
            super().populate_modules()
        self._setup_sked()
        self.hull_proposal = self._hull_proposal()
        self._load_base_weights()
        self._freeze_base(field=self.field, proposal_networks=self.proposal_networks)
        # Proposals see kept space as the base does, so a ray through kept space only samples as the base's did:
        # its proposal densities read from grids sampled once (density_grid.py), or its networks (grid 0).
        base_fns = self._base_density_fns = [self.in_chunks(network.density_fn, network)
                                             for network in self.frozen_base.proposal_networks]
        self._base_proposal_grids: Dict[int, BaseDensityGrid] = {}  # built on the device at the first step
        held = [self._base_proposal_grid_fn(i, fn) for i, fn in enumerate(base_fns)] \
            if self.config.base_proposal_grid > 0 and self.__dict__.get("_earlier") is None else base_fns
        self.density_fns = [self.edit_density_fn(fn, held[min(i, len(held) - 1)], proposal=True)
                            for i, fn in enumerate(self.density_fns)]
        self._boost_proposals_in_edit_box()
        self.density_fns = [self.in_chunks(fn, *self.proposal_networks) for fn in self.density_fns]

    def _base_proposal_grid_fn(self, index: int, network_fn):
        """The frozen base's proposal network `index` while training, as a density grid sampled where the model is when
        first read; `network_fn` (the network) in every other render, so what a user sees of kept space is the base's
        own, bit for bit."""
        def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
            if not self.training:
                return network_fn(positions, times)
            grid = self._base_proposal_grids.get(index)
            if grid is None or grid.grid.device != positions.device:
                network = self.frozen_base.proposal_networks[index]
                resolution = min(int(network.max_res), self.config.base_proposal_grid)  # its finest hash level
                grid = self._base_proposal_grids[index] = BaseDensityGrid(network, resolution)
            return grid(positions)

        return density

    @torch.no_grad()
    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """The frozen base seen along `ray_bundle` (already collided), with its own proposal networks."""
        base = self.frozen_base
        outputs, samples, _, weights = self._render_with(ray_bundle, base.field, self._base_density_fns)
        outputs["preservation_weight"] = self.expected_preservation(samples.frustums.get_positions(), weights,
                                                                    outputs["accumulation"])
        return {key: value for key, value in outputs.items() if key not in ("weights_list", "ray_samples_list")}

    # ---- sampling the edit region -----------------------------------------------------------
    def _boost_proposals_in_edit_box(self) -> None:
        """Add density inside the sketches' visual hull to the proposal networks during warm-up.

        A nerfacto base has no mass where the new content goes, so its proposal networks
        would never place samples there; the boost does until they learn the new mass. Only
        the hull (where every view's mask agrees), not the whole edit box: samples, and so new
        mass, in the box's empty corners are haze from other viewpoints.

        A LocalField edit's proposals are the base's and never learn (local_edit.py): its new content is sampled in
        the hull only: the whole hull while training, and in every render the cells where it added mass (its
        added-mass grid). Its new mass renders in the hull alone, and a fresh edit's samples are the base's bit for bit.
        """
        diagonal = float(np.linalg.norm(self.edit_box.max - self.edit_box.min).clip(1e-6))

        def boosted(density_fn):
            def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
                value = density_fn(positions, times)
                local = isinstance(self.local_field, LocalField)
                share = 1.0 if local and self.training else self.edit_box_boost()
                if local and not self.training:  # the cells of its new mass, at the hull's full density
                    share = torch.clamp_min(self._added_mass_grid()(positions), share)
                if local and self.hull_proposal is not None:  # where it learnt the new surface is
                    share = share * self.hull_proposal(positions)
                if local or share > 0:
                    hull = self.in_sketch_hull(positions)[..., None].to(value.dtype)
                    value = value + self.config.edit_box_density / diagonal * share * hull
                return value

            return density

        self.density_fns = [boosted(fn) for fn in self.density_fns]

    def _hull_proposal(self) -> Optional[HullProposal]:
        """A LocalField edit's learned share of its hull's proposal density (density_grid.HullProposal)."""
        if not isinstance(self.local_field, LocalField) or self.config.hull_proposal_grid <= 0:
            return None
        bounds = self.edit_box_bounds.float()
        return HullProposal(bounds[0], bounds[1], self.config.hull_proposal_grid)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """SKED's step, and the proposal sampler's update schedule; no proposal-weight anneal.

        nerfacto's anneal restarts at 0 for every run: the trained base would be sampled almost
        uniformly for hundreds of steps. The base's proposals are trained, so anneal stays 1.
        """
        self.proposal_sampler.set_anneal(1.0)
        return [
            self.sked_step_callback(),
            TrainingCallback(where_to_run=[TrainingCallbackLocation.AFTER_TRAIN_ITERATION], update_every_num_iters=1,
                             func=self.proposal_sampler.step_cb),
        ]

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = self._hash_grid_groups(proposal_networks=self.proposal_networks, fields=self.field)
        if self.hull_proposal is not None:  # a grid of log scales: the grids' rate
            groups.setdefault("hash_grids", []).extend(self.hull_proposal.parameters())
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    # ---- rendering ------------------------------------------------------------------------
    def _render_with(self, ray_bundle: RayBundle, field, density_fns) -> Tuple[Dict, RaySamples, Dict, Tensor]:
        """nerfacto's render with the given field and proposal densities: the edit's, or the frozen base's.

        Returns the outputs, the final samples, the field outputs there and their weights (L_pres
        and the preservation-weight output need them; nerfacto's own get_outputs returns neither).
        """
        ray_samples, weights_list, ray_samples_list = self.proposal_sampler(ray_bundle, density_fns=density_fns)
        evaluate = lambda module, samples: module.forward(samples, compute_normals=self.config.predict_normals)  # noqa: E731
        base_outputs = None
        if field is self.field:
            field_outputs, base_outputs = self._held_outputs(ray_samples, evaluate)
        else:
            field_outputs = self.in_chunks(lambda samples: evaluate(field, samples), field)(ray_samples)
        if self.config.use_gradient_scaling:
            field_outputs = scale_gradients_by_distance_squared(field_outputs, ray_samples)
        weights = ray_samples.get_weights(field_outputs[FieldHeadNames.DENSITY])
        weights_list.append(weights)
        ray_samples_list.append(ray_samples)
        with torch.no_grad():
            depth = self.renderer_depth(weights=weights, ray_samples=ray_samples)
        outputs = {
            "rgb": self.renderer_rgb(rgb=field_outputs[FieldHeadNames.RGB], weights=weights),
            "accumulation": self.renderer_accumulation(weights=weights),
            "depth": depth,
            "expected_depth": self.renderer_expected_depth(weights=weights, ray_samples=ray_samples),
            "weights_list": weights_list,
            "ray_samples_list": ray_samples_list,
        }
        if self.config.predict_normals:
            normals = self.renderer_normals(normals=field_outputs[FieldHeadNames.NORMALS], weights=weights)
            outputs["normals"] = self.normals_shader(normals)
            outputs["pred_normals"] = self.normals_shader(
                self.renderer_normals(field_outputs[FieldHeadNames.PRED_NORMALS], weights=weights))
        for i in range(self.config.num_proposal_iterations):
            outputs[f"prop_depth_{i}"] = self.renderer_depth(weights=weights_list[i], ray_samples=ray_samples_list[i])
        if base_outputs is not None:
            outputs["_base_field_outputs"] = base_outputs  # L_pres compares the two at the same samples
        return outputs, ray_samples, field_outputs, weights

    def _render(self, ray_bundle: RayBundle):
        outputs, samples, field_outputs, weights = self._render_with(ray_bundle, self.field, self.density_fns)
        outputs["_weights"] = weights  # L_sil's editable opacity needs them
        return outputs, samples, field_outputs

    def _sampling_losses(self, rendered: Sequence[Dict[str, Tensor]]) -> Dict[str, Tensor]:
        if self.local_field is not None and self.hull_proposal is None:  # the base's proposals alone: nothing to train
            return {}
        loss = sum(interlevel_loss(r["weights_list"], r["ray_samples_list"]) for r in rendered)
        return {"interlevel_loss": self.config.interlevel_loss_mult * loss}

    def get_outputs(self, ray_bundle: RayBundle):
        outputs, samples, _, weights = self._render_with(ray_bundle, self.field, self.density_fns)
        outputs.pop("_base_field_outputs", None)
        if self.training:
            return outputs
        # Proposal samples use a lot of memory and only the interlevel loss needs them.
        outputs = {key: value for key, value in outputs.items() if key not in ("weights_list", "ray_samples_list")}
        outputs["preservation_weight"] = self.expected_preservation(samples.frustums.get_positions(), weights,
                                                                    outputs["accumulation"])
        return self._steer(ray_bundle, outputs)

