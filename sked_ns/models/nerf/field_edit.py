"""SKED on a NeRF field, whatever its sampler (nerfacto's proposals, NGP's grid).

`SkedEdit` (edit.py) holds what SKED adds to any representation; this mixin adds what rays
through a field need: rendering along ray samples, L_pres on the random view's samples
against the frozen base's field, the editable opacity along a sketch ray, the photo anchor on
rays, and loading a base field's weights.

A model using `SkedMixin` supplies four things: `_render(ray_bundle)` (outputs plus the
samples and field outputs behind them), `render_base`, `_sampling_losses` and the list of
weight prefixes its base checkpoint must provide.
"""

from __future__ import annotations

import contextlib
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from sked_ns.errors import SkedUserError
from sked_ns.method.edit import SkedEdit, StepTerms
from sked_ns.method.frozen_base import base_weights, check_photo_count, read_model_state, uses_tcnn
from sked_ns.method.hull_carving import SketchRayOpacity
from sked_ns.method.losses import new_mass_loss, occupancy_log_probabilities, preservation_loss
from sked_ns.method.options import (  # noqa: F401  (re-exported: their home was this module)
    AUTO_FIELD_CHUNK,
    CHECKPOINTED_FIELD_CHUNK,
    SkedOptions,
    SkedSettingsWarning,
    is_carving,
    warn_degenerate_settings,
    without_lpips,
)
from sked_ns.method.photo_anchor import anchor_rays, correct_poses, rays_away_from_edit
from sked_ns.models.nerf.chunked import chunked
from sked_ns.models.nerf.colour_residual import ColourResidual
from sked_ns.models.nerf.edited_base import is_local_edit
from sked_ns.models.nerf.hash_grid import use_fast_hash_grids
from sked_ns.models.nerf.held_field import held_field_outputs
from sked_ns.models.nerf.local_edit import LocalEdit
from sked_ns.models.nerf.local_field import (
    FULL_COPY,
    LOCAL,
    LOCAL_RESIDUAL,
    LocalField,
    LocalResidual,
    splits_grid_and_mlp,
)

NERF_EDIT_OWNED = SkedOptions.EDIT_OWNED | {
    # the edit's own losses
    "loss_coefficients", "interlevel_loss_mult", "distortion_loss_mult", "orientation_loss_mult", "pred_normal_loss_mult",
    # schedules of training from scratch: an edit starts from trained proposals (its anneal stays 1)
    "proposal_update_every", "proposal_warmup", "use_proposal_weight_anneal", "proposal_weights_anneal_slope",
    "proposal_weights_anneal_max_num_iters",
    "edit_box_density", "grid_update_interval",  # SKED's sampling of the edit box
    "nerf_edit_field",  # the edit's representation
}
"""The model-config fields a NeRF edit decides, not its base (nerfacto and instant-ngp alike)."""


def per_ray_sum(values: Tensor, accumulation: Tensor, ray_indices: Optional[Tensor] = None) -> Tensor:
    """Sum per-sample values (..., samples, 1) over each ray, shaped as `accumulation`; `ray_indices` for packed
    samples (occupancy grids)."""
    if ray_indices is None:
        return values.sum(dim=-2)
    return torch.zeros_like(accumulation).index_add(0, ray_indices, values)



class SkedMixin(LocalEdit, SkedEdit):
    """SKED on a radiance field rendered along rays: L_pres on field samples, the base's field, photo rays."""

    BASE_PREFIXES: Tuple[str, ...] = ("field.",)
    """Checkpoint keys the base must provide and the edit starts from."""

    # ---- set-up ---------------------------------------------------------------------------
    def _setup_sked(self) -> None:
        """Call after the parent's populate_modules."""
        super()._setup_sked()
        # The appearance of random views is the average embedding: keep it as trained.
        if getattr(self.field, "embedding_appearance", None) is not None:
            self.field.embedding_appearance.requires_grad_(False)
        # The local residual (local_field.py) owns its colour; the local field and the full copy get the colour residual.
        if self.config.nerf_edit_field == LOCAL and not splits_grid_and_mlp(self.field):
            CONSOLE.print("The base's hash grid and MLP are fused (tiny-cuda-nn), so the edit cannot read the grid's "
                          "features: it trains a copy of the whole field (--pipeline.model.nerf-edit-field full-copy).")
            self.config.nerf_edit_field = FULL_COPY
        self.local_field = self._local_edit() if self.config.nerf_edit_field in (LOCAL, LOCAL_RESIDUAL) else None
        self.hull_proposal = None  # nerfacto's LocalField edit learns one (nerfacto.py)
        self.colour_residual = (ColourResidual(self.edit_box.min, self.edit_box.max)
                                if self.config.colour_residual and not isinstance(self.local_field, LocalResidual)
                                else None)
        self.sketch_ray_opacity = SketchRayOpacity(self.sketch_set.views, self.config.silhouette_resolution)

    def _steer(self, ray_bundle: RayBundle, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Evaluation outputs as the viewer controls ask (steer_outputs), the base rendered along the same rays."""
        return self.steer_outputs(outputs, lambda: self.render_base(ray_bundle))

    def _load_base_weights(self) -> None:
        """The editable modules <- the base's weights, after checking they fit."""
        if self.config.base_checkpoint is None:
            raise ValueError("No base checkpoint: run `ns-train sked --load-dir <base run or its nerfstudio_models>`.")
        checkpoint = base_weights(self.config)
        state = read_model_state(checkpoint)
        if is_local_edit(state):  # an earlier local edit (progressive): rebuilt from its run, the frozen base
            return self._use_earlier_edit(state)
        ours = torch.nn.Module.state_dict(self)  # the whole model, the base's modules too
        if uses_tcnn(state) != uses_tcnn(ours):
            trained, here = ("tiny-cuda-nn", "torch") if uses_tcnn(state) else ("torch", "tiny-cuda-nn")
            raise SkedUserError(
                f"{checkpoint}: the base was trained with the {trained} implementation, but this edit builds "
                f"{here} modules, whose weights are laid out differently. "
                + ("Install tinycudann here, or edit on the machine that trained the base." if uses_tcnn(state) else
                   "A new edit takes the base's layout by itself: pass the base's run folder as --load-dir.")
            )
        check_photo_count(state, self.num_train_data, checkpoint)
        wanted = [key for key in ours if key.startswith(self.BASE_PREFIXES)]
        missing = [key for key in wanted if key not in state]
        mismatched = [key for key in wanted if key in state and state[key].shape != ours[key].shape]
        if missing or mismatched:
            raise SkedUserError(
                f"{checkpoint}: the base's weights do not fit this model (missing {missing[:3]}, "
                f"shape mismatch {mismatched[:3]}). Is --data the base's data, and the base a supported method?"
            )
        torch.nn.Module.load_state_dict(self, {key: state[key] for key in wanted}, strict=False)  # the base, as it is
        if isinstance(self.local_field, LocalField):
            self.local_field.take_base_networks(self.field)
        self._base_cameras = self._frozen_base_cameras(state)

    def _frozen_base_cameras(self, state: Dict[str, Tensor]) -> list:
        """The base's learnt pose corrections (nerfacto optimises its cameras): photo rays need them."""
        if self.config.base_camera_optimizer == "off" or "camera_optimizer.pose_adjustment" not in state:
            return []
        from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

        adjustment = state["camera_optimizer.pose_adjustment"]
        optimizer = CameraOptimizerConfig(mode=self.config.base_camera_optimizer).setup(
            num_cameras=adjustment.shape[0], device="cpu")
        optimizer.load_state_dict({"pose_adjustment": adjustment})
        return [optimizer.eval().requires_grad_(False)]

    def _freeze_base(self, **modules: torch.nn.Module) -> None:
        super()._freeze_base(**modules)
        if self.local_field is not None:  # the base's modules are the base: no gradient, no optimiser, not saved
            for module in modules.values():
                module.requires_grad_(False)
        if self.__dict__.get("_earlier") is not None:
            self.frozen_base = self._earlier_as_base(self.frozen_base)
        # Torch hash grids without a host copy per call, the edit's and the frozen base's (hash_grid.py).
        use_fast_hash_grids(self, *self.frozen_base.modules())

    @torch.no_grad()
    def base_content_near(self, low: np.ndarray, high: np.ndarray, points_per_side: int = 16) -> bool:
        """Opaque over one lattice step (opacity above a half) at any point of a lattice over the box."""
        device = self.edit_box_bounds.device
        steps = torch.linspace(0.0, 1.0, points_per_side, device=device)
        unit = torch.stack(torch.meshgrid(steps, steps, steps, indexing="ij"), dim=-1).reshape(-1, 3)
        low_t, high_t = (torch.as_tensor(v, dtype=torch.float32, device=device) for v in (low, high))
        density = self.base_field.density_fn(low_t + unit * (high_t - low_t))
        step = float(np.max(high - low)) / (points_per_side - 1)
        return bool((-torch.expm1(-density.float() * step)).max() > 0.5)

    @property
    def base_field(self):
        return self.frozen_base.field

    def _hash_grid_groups(self, **non_grid: torch.nn.Module) -> Dict[str, List[torch.nn.Parameter]]:
        """Hash grids get their own group: docs/method.md (Optimisation) trains them at 10x the MLPs' rate."""
        grids = {id(p) for module in self.modules() if isinstance(module, HashEncoding) for p in module.parameters()}
        trainable = lambda module: [p for p in module.parameters() if p.requires_grad]  # noqa: E731
        groups = {name: [p for p in trainable(module) if id(p) not in grids] for name, module in non_grid.items()}
        groups["hash_grids"] = [p for p in trainable(self) if id(p) in grids]
        if getattr(self, "colour_residual", None) is not None:
            # Its linear layer starts at zero, so the grid gets no gradient until it moves: train it at the grids' rate.
            groups["hash_grids"] += list(self.colour_residual.linear.parameters())
        if isinstance(self.local_field, LocalField):  # its MLPs are copies of the base's: the MLPs' rate, as a full copy's
            groups.setdefault("fields", []).extend(p for p in self.local_field.parameters() if id(p) not in grids)
        elif self.local_field is not None:  # the residual's head's last layer starts at zero too: the grids' rate
            groups["hash_grids"] += list(self.local_field.head.parameters())
        return {name: params for name, params in groups.items() if params}  # a local edit trains no base module

    # ---- model-specific hooks ------------------------------------------------------------
    def _render(self, ray_bundle: RayBundle) -> Tuple[Dict[str, Tensor], RaySamples, Dict]:
        """Render with the editable field: (outputs, samples, field outputs at the samples). The outputs hold the
        samples' weights as "_weights" (and "_ray_indices" for packed samples) for L_sil's editable opacity."""
        raise NotImplementedError

    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """The frozen base seen along `ray_bundle`."""
        raise NotImplementedError

    def _sampling_losses(self, rendered: Sequence[Dict[str, Tensor]]) -> Dict[str, Tensor]:
        """Losses of the sampler itself (nerfacto's interlevel loss), over all renders of a step."""
        return {}

    # ---- shared --------------------------------------------------------------------------
    def _collide(self, ray_bundle: RayBundle) -> RayBundle:
        # Model.forward applies the collider; SKED's own renders bypass forward.
        return self.collider(ray_bundle) if self.collider is not None else ray_bundle

    def _edit_colour(self, field_outputs: Dict, ray_samples: RaySamples, weight: Optional[Tensor]) -> Dict:
        """The editable field's colours with the colour residual (colour_residual.py) at samples of preservation
        weight `weight` (the render's, computed once); the base's are never moved."""
        if self.colour_residual is None:
            return field_outputs
        rgb = field_outputs[FieldHeadNames.RGB]
        return {**field_outputs, FieldHeadNames.RGB: self.colour_residual.apply(rgb, ray_samples.frustums.get_positions(),
                                                                             weight)}

    def _sample_weights(self, positions: Tensor) -> Optional[Tensor]:
        """The samples' preservation weights where a render needs them (the colour residual, the exact hold), once."""
        needed = self.colour_residual is not None or self.config.keep_threshold < 1
        return self.preservation_weight(positions) if needed else None

    def editable_accumulation(self, positions: Tensor, weights: Tensor, accumulation: Tensor,
                              ray_indices: Optional[Tensor] = None) -> Tensor:
        """Per ray: sum_i weight_i (1 - w(p_i)), the opacity of content the edit may change (differentiable in the
        weights; w is fixed). 1 - expected_preservation without the background term; shaped as `accumulation`."""
        return per_ray_sum(weights * (1.0 - self.preservation_weight(positions)), accumulation, ray_indices)

    def expected_preservation(self, positions: Tensor, weights: Tensor, accumulation: Tensor,
                              ray_indices: Optional[Tensor] = None) -> Tensor:
        """Per ray: sum_i weight_i w(p_i), plus the background (1 - accumulation), which is preserved.

        0 where a pixel shows content the edit may change, 1 where it shows only what must be kept.
        `ray_indices` for packed samples (occupancy grids), else samples are (rays, samples, 3).
        """
        preserved = per_ray_sum((weights * self.preservation_weight(positions)).detach(), accumulation, ray_indices)
        return (preserved + (1 - accumulation.detach()).clamp(0, 1)).clamp(0, 1)

    def in_chunks(self, function, *modules: torch.nn.Module):
        """`function` (a field's evaluation at samples or positions) in chunks of config.field_chunk samples, gradient-
        checkpointed while training (chunked.py); `modules`: the fields it evaluates."""
        return chunked(function, self.field_chunk, modules)

    def field_chunk(self) -> int:
        """config.field_chunk, or where the memory plan did not choose it (a model built outside ns-train sked) the
        checkpointed chunk: the safe side."""
        chunk = self.config.field_chunk
        return CHECKPOINTED_FIELD_CHUNK if chunk == AUTO_FIELD_CHUNK else chunk

    # ---- kept content held exactly (held_field.py) --------------------------------------------
    def _kept(self, positions: Tensor) -> Optional[Tensor]:
        """Which points are kept exactly as the base (w above keep_threshold); None when nothing is held."""
        return self._held(self.preservation_weight(positions)) if self.config.keep_threshold < 1 else None

    def _held(self, weight: Tensor) -> Optional[Tensor]:
        """`_kept` from the points' preservation weights (..., 1)."""
        return weight[..., 0] > self.config.keep_threshold if self.config.keep_threshold < 1 else None

    def _held_outputs(self, ray_samples: RaySamples, evaluate) -> Tuple[Dict, Dict]:
        """(edit's field outputs with kept samples the base's, base's field outputs); `evaluate(field, samples)`."""
        base_field, mode = self.base_field, self.base_field.training
        base_field.train(self.field.training)  # the same appearance (a photo's while anchoring) on both sides
        try:
            if self.local_field is not None:
                return self._local_outputs(ray_samples, lambda s: evaluate(base_field, s))
            weight = self._sample_weights(ray_samples.frustums.get_positions())
            edit = self.in_chunks(lambda s, w: self._edit_colour(evaluate(self.field, s), s, w), self.field)
            return held_field_outputs(lambda s: edit(s, weight), self.in_chunks(lambda s: evaluate(base_field, s), base_field),
                                      ray_samples, None if weight is None else self._held(weight))
        finally:
            base_field.train(mode)

    def held_density_fn(self, edit_fn, base_fn):
        """A density function that is the base's at kept points (samplers and occupancy grids follow what renders)."""
        def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
            value = edit_fn(positions, times)
            kept = self._kept(positions)
            if kept is None:
                return value
            with torch.no_grad():
                base = base_fn(positions, times)
            return torch.where(kept[..., None], base.to(value.dtype), value)

        return density

    @contextlib.contextmanager
    def _average_appearance(self):
        """Random and sketch views have no training image: use the evaluation appearance."""
        was_training = self.field.training
        self.field.train(False)
        try:
            yield
        finally:
            self.field.train(was_training)

    # ---- the base-photo anchor on rays ------------------------------------------------------
    def photo_anchor_acts(self) -> bool:
        # Its rays have w above photo_threshold everywhere: held exactly (and so without a gradient) unless
        # keep_threshold is higher.
        return super().photo_anchor_acts() and self.config.keep_threshold > self.config.photo_threshold

    def photo_rays_kept(self, rays: RayBundle) -> Tensor:
        """Which (collided) photo rays never come near the editable region."""
        count = len(rays)
        nears = rays.nears if rays.nears is not None else torch.zeros(count, 1, device=rays.origins.device)
        fars = rays.fars if rays.fars is not None else torch.full((count, 1), 1e10, device=rays.origins.device)
        return rays_away_from_edit(rays.origins, rays.directions, nears, fars, self.editable_box(),
                                   lambda p: self.preservation_weight(p)[..., 0], self.config.photo_threshold)

    def photo_anchor(self, rays: RayBundle, rgb: Tensor) -> Optional[Tuple[Tensor, Dict[str, Tensor], Tensor]]:
        """MSE to the base's photos at its safe rays, rendered as the base was trained (its image's appearance,
        its corrected pose). Returns (loss, outputs, fraction of rays kept), or None if no ray is safe."""
        rays = self._collide(rays)
        safe = self.photo_rays_kept(rays)
        if not safe.any():
            return None
        rays, rgb = anchor_rays(rays, rgb, safe)
        correct_poses(rays, self._base_cameras)
        outputs = self._render(rays)[0]
        predicted, truth = self.renderer_rgb.blend_background_for_loss_computation(
            pred_image=outputs["rgb"], pred_accumulation=outputs["accumulation"], gt_image=rgb.to(outputs["rgb"]))
        if not self.check_photos_once(predicted, truth):
            return None
        return torch.nn.functional.mse_loss(predicted.float(), truth.float()), outputs, safe.float().mean()

    @torch.no_grad()
    def _base_sketch_opacity(self, sketch_rays: RayBundle) -> Tensor:
        """The frozen base's L_sil opacity at the sketch rays: rendered once per beta (the base never changes; its
        editable opacity follows w, which the viewer's beta moves)."""
        key = (len(sketch_rays), self.config.beta)
        cached = getattr(self, "_base_sketch_opacity_cache", None)
        if cached is None or cached[0] != key:
            with self._average_appearance():
                base = self.render_base(self._collide(sketch_rays))
            opacity = (base["accumulation"] if self.config.silhouette_opacity == "any"
                       else 1.0 - base["preservation_weight"]).detach()
            cached = self._base_sketch_opacity_cache = (key, opacity)
        return cached[1]

    # ---- one iteration -----------------------------------------------------------------------
    def get_sked_loss_dict(self, data: Dict, step: int) -> tuple[Dict[str, Tensor], Dict[str, Tensor], Dict[str, Tensor]]:
        """All losses of one iteration from the datamanager's `next_sked` dict; returns (outputs, losses, metrics)."""
        config = self.config
        random_view, sketch_rays, sketch_masks = data["random_view"], data["sketch_rays"], data["sketch_masks"]
        # L_sil (and L_new's gate) read the sketch views only at the masks' pixels: render those rays alone and place
        # their opacity back among the views' pixels (zero elsewhere, where the masks weigh it by zero).
        pixels = data.get("sketch_pixels")
        if sketch_rays is not None and pixels is not None:
            sketch_rays = data["masked_sketch_rays"]

        def to_views(opacity: Tensor) -> Tensor:
            if pixels is None:
                return opacity
            return opacity.new_zeros(len(sketch_masks), *opacity.shape[1:]).index_copy(0, pixels, opacity)

        height, width = random_view.shape[:2]
        with self._average_appearance():
            view, samples, field_outputs = self._render(self._collide(random_view.flatten()))
            sketch, sketch_samples, _ = self._render(self._collide(sketch_rays)) if sketch_rays is not None else (None,) * 3

        # L_pres on the random view's samples.
        weight = self.preservation_weight(samples.frustums.get_positions())
        base_outputs = view.pop("_base_field_outputs")
        density_edit = field_outputs[FieldHeadNames.DENSITY]
        terms = StepTerms(preservation=preservation_loss(
            density_edit, field_outputs[FieldHeadNames.RGB], base_outputs[FieldHeadNames.DENSITY],
            base_outputs[FieldHeadNames.RGB], weight, config.occupancy_threshold, config.preservation_delta,
            config.lambda_colour, config.preservation_target,
        ), accumulation=view["accumulation"])
        carving = is_carving(config)
        if carving:
            # No prompt: empty the sketched region (occupancy -> 0 where w is small).
            _, log_empty = occupancy_log_probabilities(density_edit, config.preservation_delta)
            terms.carve = ((1 - weight) * -log_empty).mean()
        else:
            as_image = lambda rgb: rgb.reshape(1, height, width, 3).permute(0, 3, 1, 2)  # noqa: E731

            def base_image() -> Tensor:
                with self._average_appearance():
                    return as_image(self.render_base(self._collide(random_view.flatten()))["rgb"])

            terms.guidance = self.guidance_losses(as_image(view["rgb"]), data["random_camera"], base_image, step)
            if sketch is not None:
                opacity = sketch["accumulation"]
                if config.silhouette_opacity == "editable":
                    opacity = self.editable_accumulation(sketch_samples.frustums.get_positions(), sketch["_weights"],
                                                         opacity, sketch.get("_ray_indices"))
                opacity = to_views(opacity)
                terms.sketch = (opacity, sketch_masks)
            if config.lambda_new_mass > 0:
                # New mass on sketch rays the edit has already made opaque (or off the sketches) fades unless the
                # guidance holds it; the base's own opacity on a sketch ray (a table behind it) does not count.
                gate = (self.sketch_ray_opacity.gate(samples.frustums.get_positions(),
                                                     opacity.detach() - to_views(self._base_sketch_opacity(sketch_rays)),
                                                     sketch_masks)
                        if sketch is not None else None)
                terms.new_mass = new_mass_loss(density_edit, base_outputs[FieldHeadNames.DENSITY], weight,
                                               config.preservation_delta, gate)
        rendered = [view] + ([sketch] if sketch is not None else [])
        photo = data.get("photo")
        photo_metrics = {}
        if photo is not None and self.photo_anchor_acts():
            anchored = self.photo_anchor(*photo)
            if anchored is not None:
                terms.photo, photo_view, photo_metrics["photo_rays_kept"] = anchored
                rendered.append(photo_view)
        terms.representation = self._sampling_losses(rendered)
        losses, metrics = self.objective(terms, carving)
        metrics.update(photo_metrics)
        metrics["mean_preservation_weight"] = weight.mean().detach()
        metrics["edit_box_boost"] = torch.tensor(self.edit_box_boost())
        return view, losses, metrics
