"""What SKED adds to any NeRF model, whatever its sampler (nerfacto's proposals, NGP's grid).

Per iteration (paper Eq. 6): L = L_guidance + lambda_pres L_pres + lambda_sil L_sil
+ lambda_sp L_sp. L_pres and L_sp come from one random view aimed at the edit box, L_sil
from the fixed sketch views at reduced resolution. The frozen base is kept out of the
module tree: it is never optimised, never saved, and follows `.to()`.

A model using `SkedMixin` supplies four things: `_render(ray_bundle)` (outputs plus the
samples and field outputs behind them), `render_base`, `_sampling_losses` and the list of
weight prefixes its base checkpoint must provide.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import torch
import torchmetrics.image.lpip as lpip_module
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from torch import Tensor

from sked_ns.base_scene import read_model_state, uses_tcnn
from sked_ns.colour_residual import ColourResidual
from sked_ns.edit_box import EditBox, compute_edit_box
from sked_ns.frozen_base import FrozenBase
from sked_ns.guidance import Guidance, GuidanceChoice, RenderedView, StableDiffusionGuidanceConfig
from sked_ns.losses import occupancy_log_probabilities, preservation_loss, silhouette_loss, sparsity_loss
from sked_ns.photo_anchor import (anchor_rays, check_base_explains_photos, correct_poses, editable_box,
                                  rays_away_from_edit)
from sked_ns.preservation import SketchDistanceField, check_beta
from sked_ns.sketches import SketchSet
from sked_ns.validation import check_sketch_pixels


def per_ray_sum(values: Tensor, accumulation: Tensor, ray_indices: Optional[Tensor] = None) -> Tensor:
    """Sum per-sample values (..., samples, 1) over each ray, shaped as `accumulation`; `ray_indices` for packed
    samples (occupancy grids)."""
    if ray_indices is None:
        return values.sum(dim=-2)
    return torch.zeros_like(accumulation).index_add(0, ray_indices, values)


@dataclass
class SkedOptions:
    """SKED's settings, shared by the nerfacto and instant-ngp edit models."""

    sketches: Optional[Path] = None
    """Sketch-set folder (sketches.json + PNG masks); `ns-train sked --sketches` sets it."""
    prompt: Optional[str] = None
    """What should be in the sketched region; none with Stable Diffusion guidance = carve it away."""
    base_checkpoint: Optional[Path] = None
    """The base's step-*.ckpt; filled in from --load-dir."""
    guidance: GuidanceChoice = field(default_factory=StableDiffusionGuidanceConfig)
    """What pulls the sketched region: a subcommand, `pipeline.model.guidance:stable-diffusion` (default) or
    another installed guidance (`pipeline.model.guidance:reference`: renders of a known target scene)."""
    beta: float = 0.025
    """Falloff of the preservation weight, in image widths (paper Eq. 4)."""
    lambda_pres: float = 5.0
    """Weight of L_pres (a mean over samples; the authors' 5e-6 multiplied a sum)."""
    lambda_colour: float = 5.0
    """Weight of the colour term inside L_pres."""
    preservation_target: Literal["occupancy", "density"] = "density"
    """What L_pres holds the edit to: the base's own density (a soft base stays soft) or, as the paper, its occupancy
    thresholded at occupancy_threshold (sharpens a soft base: -1.2 vs -0.2 dB kept; docs/method.md, L_pres)."""
    lambda_sil: float = 1.0
    """Weight of L_sil."""
    silhouette_normalisation: Literal["image", "sketch"] = "image"
    """L_sil per image pixel (paper) or per sketch pixel ("sketch": scaled so a sketch covering 5% of its frame
    weighs the same; a sketch covering less pulls harder than under the paper's)."""
    colour_residual: bool = True
    """Give new content its own colour capacity near the sketches (colour_residual.py): a colour the base never shows
    is reached without moving the colour MLP everything kept shares. False: the paper's model."""
    silhouette_opacity: Literal["editable", "any"] = "editable"
    """What L_sil asks to be opaque along a sketch ray: content near the sketches (opacity weighted by 1 - w), so a
    wall or table behind the sketch does not fill it before anything is made; "any" is the paper's (all opacity,
    right for a base with an empty background)."""
    lambda_sp: float = 5e-4
    """Weight of the sparsity (accumulation entropy) loss."""
    lambda_carve: float = 5.0
    """Weight of the carving loss (empty the sketched region) when there is no prompt."""
    occupancy_threshold: float = 5.0
    """Base density above which a sample counts as occupied."""
    preservation_delta: float = 0.07
    """Fixed step length turning density into occupancy in L_pres."""
    guidance_resolution: int = 128
    """Side of the random view rendered for guidance (authors: 128, upsampled for SD)."""
    silhouette_resolution: int = 128
    """Longer side of the sketch views rendered for L_sil (authors: 128)."""
    edit_box_warmup: int = 1000
    """Iterations during which the empty edit box is kept sampled."""
    compile_lookup: bool = True
    """torch.compile the sketch-distance lookup on CUDA."""
    samples_per_ray_scale: float = 1.0
    """Samples per ray relative to the base's (nerfacto: sample counts; instant-ngp: 1 / step size)."""
    lambda_photo: float = 1.0
    """Weight of the base-photo anchor (photo_anchor.py): the base's training photos, at rays that never come
    near the editable region, keep the edit as the base was trained. 0: the paper's losses only."""
    photo_threshold: float = 0.99
    """A photo ray anchors the edit only if every point on it has a preservation weight above this."""
    base_camera_optimizer: Literal["off", "SO3xR3", "SE3"] = "off"
    """The base's camera optimisation (copied from it): its learnt pose corrections are applied to photo rays."""
    ablation: Literal["none", "no-preserve", "no-silhouette", "text-only"] = "none"
    """The paper's ablations: drop L_pres, drop L_sil, or both (text only: the sketches only aim the views)."""

    @property
    def effective_lambda_pres(self) -> float:
        return 0.0 if self.ablation in ("no-preserve", "text-only") else self.lambda_pres

    @property
    def effective_lambda_photo(self) -> float:
        # The photo anchor preserves too: the no-preserve ablations drop it with L_pres.
        return 0.0 if self.ablation in ("no-preserve", "text-only") else self.lambda_photo

    @property
    def effective_lambda_sil(self) -> float:
        return 0.0 if self.ablation in ("no-silhouette", "text-only") else self.lambda_sil


@contextlib.contextmanager
def without_lpips():
    """nerfstudio models build LPIPS (an AlexNet download) in populate_modules; SKED needs none."""
    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: None
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


class SkedMixin:
    """Sketch geometry, the frozen base, the losses and evaluation images, for any sampler."""

    config: SkedOptions
    BASE_PREFIXES: Tuple[str, ...] = ("field.",)
    """Checkpoint keys the base must provide and the edit starts from."""

    # ---- set-up ---------------------------------------------------------------------------
    def _scaled_config(self):
        """A private copy of the config, so per-model adjustments never reach the saved config.yml."""
        if self.config.samples_per_ray_scale <= 0 or not math.isfinite(self.config.samples_per_ray_scale):
            raise ValueError(f"samples_per_ray_scale = {self.config.samples_per_ray_scale}: must be a positive number.")
        return dataclasses.replace(self.config)

    def _setup_sked(self) -> None:
        """Call after the parent's populate_modules."""
        self.lpips = None
        from sked_ns.datamanager import model_frame_sketches

        self.sketch_set = sketch_set = model_frame_sketches(self.config.sketches, self.kwargs.get("metadata") or {})
        self.edit_box: EditBox = compute_edit_box(sketch_set.views, scene_box=self.scene_box.aabb.numpy())
        self.sketch_field = SketchDistanceField(
            sketch_set.views, compile=self.config.compile_lookup and torch.cuda.is_available()
        )
        # The appearance of random views is the average embedding: keep it as trained.
        if getattr(self.field, "embedding_appearance", None) is not None:
            self.field.embedding_appearance.requires_grad_(False)
        warn_degenerate_settings(self.config, sketch_set)
        check_sketch_pixels(sketch_set, self.config.silhouette_resolution)
        self.colour_residual = (ColourResidual(self.edit_box.min, self.edit_box.max)
                                if self.config.colour_residual else None)
        self.guidance: Optional[Guidance] = None  # plain attribute: never in a checkpoint
        self._add_viewer_controls()

    # ---- steering in the viewer ----------------------------------------------------------------
    def _add_viewer_controls(self) -> None:
        """Controls nerfstudio's viewer lists under the model (attributes, found by type)."""
        from nerfstudio.viewer.viewer_elements import ViewerCheckbox, ViewerSlider

        self.viewer_beta = ViewerSlider(
            "SKED beta (preservation falloff)", default_value=float(self.config.beta), min_value=1e-3,
            max_value=1.0, step=1e-3, cb_hook=self._on_beta,
            hint="Image widths over which preservation fades around the sketches; applies to training too.",
        )
        self.viewer_show_base = ViewerCheckbox("SKED show the base (not the edit)", default_value=False)
        self.viewer_tint = ViewerCheckbox("SKED tint where the edit may act", default_value=False)

    def _on_beta(self, element) -> None:
        check_beta(float(element.value))
        self.config.beta = float(element.value)

    def _steer(self, ray_bundle: RayBundle, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Evaluation outputs as the viewer controls ask: base instead of edit, tinted by 1 - w."""
        if self.viewer_show_base.value:
            base = self.render_base(ray_bundle)
            outputs = {**outputs, "rgb": base["rgb"], "accumulation": base["accumulation"], "depth": base["depth"]}
        if self.viewer_tint.value and "preservation_weight" in outputs:
            editable = (1.0 - outputs["preservation_weight"]).clamp(0, 1)
            tint = torch.tensor([1.0, 0.2, 0.2], device=editable.device)
            outputs = {**outputs, "rgb": outputs["rgb"] * (1 - 0.6 * editable) + 0.6 * editable * tint}
        return outputs

    def _load_base_weights(self) -> None:
        """The editable modules <- the base's weights, after checking they fit."""
        checkpoint = self.config.base_checkpoint
        if checkpoint is None:
            raise ValueError("No base checkpoint: run `ns-train sked --load-dir <base run or its nerfstudio_models>`.")
        state = read_model_state(Path(checkpoint))
        ours = self.state_dict()
        if uses_tcnn(state) != uses_tcnn(ours):
            trained, here = ("tiny-cuda-nn", "torch") if uses_tcnn(state) else ("torch", "tiny-cuda-nn")
            raise ValueError(
                f"{checkpoint}: the base was trained with the {trained} implementation, but this edit builds "
                f"{here} modules, whose weights are laid out differently. "
                + ("Install tinycudann here, or edit on the machine that trained the base."
                   if uses_tcnn(state) else "Pass --pipeline.model.implementation torch.")
            )
        embedding = state.get("field.embedding_appearance.embedding.weight")
        if embedding is not None and embedding.shape[0] != self.num_train_data:
            raise ValueError(
                f"{checkpoint}: the base was trained on {embedding.shape[0]} images but --data has "
                f"{self.num_train_data}. Pass the base's own data and dataparser settings."
            )
        wanted = [key for key in ours if key.startswith(self.BASE_PREFIXES)]
        missing = [key for key in wanted if key not in state]
        mismatched = [key for key in wanted if key in state and state[key].shape != ours[key].shape]
        if missing or mismatched:
            raise ValueError(
                f"{checkpoint}: the base's weights do not fit this model (missing {missing[:3]}, "
                f"shape mismatch {mismatched[:3]}). Is --data the base's data, and the base a supported method?"
            )
        self.load_state_dict({key: state[key] for key in wanted}, strict=False)
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
        # A dataclass (not a module) hides the frozen base from the module tree, so from optimisers and checkpoints.
        self.frozen_base = FrozenBase.copy_of(**modules)

    @property
    def base_field(self):
        return self.frozen_base.field

    def _apply(self, fn, *args, **kwargs):
        # `.to()`, `.cuda()`, `.half()` reach the hidden base too.
        super()._apply(fn, *args, **kwargs)
        frozen = self.frozen_base.modules() if getattr(self, "frozen_base", None) is not None else []
        for module in frozen + getattr(self, "_base_cameras", []):
            module._apply(fn, *args, **kwargs)
        return self

    def _hash_grid_groups(self, **non_grid: torch.nn.Module) -> Dict[str, List[torch.nn.Parameter]]:
        """Hash grids get their own group: docs/method.md (Optimisation) trains them at 10x the MLPs' rate."""
        grids = {id(p) for module in self.modules() if isinstance(module, HashEncoding) for p in module.parameters()}
        trainable = lambda module: [p for p in module.parameters() if p.requires_grad]  # noqa: E731
        groups = {name: [p for p in trainable(module) if id(p) not in grids] for name, module in non_grid.items()}
        groups["hash_grids"] = [p for p in trainable(self) if id(p) in grids]
        if getattr(self, "colour_residual", None) is not None:
            # Its linear layer starts at zero, so the grid gets no gradient until it moves: train it at the grids' rate.
            groups["hash_grids"] += list(self.colour_residual.linear.parameters())
        return groups

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

    # ---- SKED's own step: the warm-up follows it in training, in a resumed run and in a loaded edit ----
    sked_step: int = 0

    def update_to_step(self, step: int) -> None:
        """nerfstudio calls this when it loads a checkpoint (resume, viewer, ns-render, ns-export)."""
        self.sked_step = int(step)

    def sked_step_callback(self) -> TrainingCallback:
        return TrainingCallback(where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                                update_every_num_iters=1, func=self.update_to_step)

    def get_extra_state(self) -> Dict[str, int]:
        # Saved in every checkpoint: a loaded edit samples as training ended, whoever loads it.
        return {"sked_step": self.sked_step}

    def set_extra_state(self, state: Dict[str, int]) -> None:
        self.sked_step = int(state.get("sked_step", self.sked_step))

    def edit_box_boost(self) -> float:
        """How strongly the edit box is still forced into the sampling (1 at step 0, 0 after warm-up)."""
        return max(0.0, 1.0 - self.sked_step / max(self.config.edit_box_warmup, 1))

    # ---- shared --------------------------------------------------------------------------
    def _collide(self, ray_bundle: RayBundle) -> RayBundle:
        # Model.forward applies the collider; SKED's own renders bypass forward.
        return self.collider(ray_bundle) if self.collider is not None else ray_bundle

    def preservation_weight(self, positions: Tensor) -> Tensor:
        """w for sample positions (..., 3) -> (..., 1)."""
        return self.sketch_field.preservation_weight(positions.detach(), self.config.beta)[..., None]

    @torch.no_grad()
    def in_sketch_hull(self, positions: Tensor, tolerance: Optional[float] = None) -> Tensor:
        """Whether points (..., 3) project inside every sketch, to `tolerance` image widths (default a
        pixel): where new mass may appear."""
        flat = positions.reshape(-1, 3)
        inside = self.edit_box.contains(flat)  # cheap first: the box holds the hull
        if inside.any():
            if tolerance is None:
                tolerance = 1.0 / min(view.width for view in self.sketch_set.views)
            inside[inside.clone()] = self.sketch_field.hull_distance(flat[inside]) <= tolerance
        return inside.reshape(positions.shape[:-1])

    def _edit_colour(self, field_outputs: Dict, ray_samples: RaySamples) -> Dict:
        """The editable field's colours with the colour residual (colour_residual.py); the base's are never moved."""
        if self.colour_residual is None:
            return field_outputs
        positions = ray_samples.frustums.get_positions()
        rgb = field_outputs[FieldHeadNames.RGB]
        return {**field_outputs, FieldHeadNames.RGB: self.colour_residual.apply(rgb, positions,
                                                                             self.preservation_weight(positions))}

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

    @contextlib.contextmanager
    def _average_appearance(self):
        """Random and sketch views have no training image: use the evaluation appearance."""
        was_training = self.field.training
        self.field.train(False)
        try:
            yield
        finally:
            self.field.train(was_training)

    # ---- the base-photo anchor --------------------------------------------------------------
    _photos_checked: bool = False
    base_photo_psnr: Optional[float] = None
    """The base's PSNR at the first batch of anchored photo rays (check_base_explains_photos)."""

    def editable_box(self) -> Optional[Tensor]:
        """The box holding every point with w <= photo_threshold (follows beta, which the viewer may change)."""
        key = (self.config.beta, self.config.photo_threshold)
        if getattr(self, "_editable_box_key", None) != key:
            self._editable_box = editable_box(lambda p: self.preservation_weight(p)[..., 0], self.scene_box.aabb,
                                              self.config.photo_threshold)
            self._editable_box_key = key
        return self._editable_box

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
        if not self._photos_checked:
            # Once, on the first batch (the edit is still the base there, or holds it at these rays when resumed).
            self._photos_checked = True
            self.base_photo_psnr, explained = check_base_explains_photos(predicted, truth)
            if not explained:
                self.config.lambda_photo = 0.0  # this model's copy of the config: config.yml keeps what was typed
                return None
        return torch.nn.functional.mse_loss(predicted.float(), truth.float()), outputs, safe.float().mean()

    def get_sked_loss_dict(
        self,
        random_view: RayBundle,
        random_camera: Dict,
        sketch_rays: Optional[RayBundle],
        sketch_masks: Tensor,
        step: int,
        photo: Optional[Tuple[RayBundle, Tensor]] = None,
    ) -> tuple[Dict[str, Tensor], Dict[str, Tensor], Dict[str, Tensor]]:
        """All losses of one iteration; returns (outputs, losses, metrics)."""
        config = self.config
        losses: Dict[str, Tensor] = {}
        metrics: Dict[str, Tensor] = {}
        height, width = random_view.shape[:2]
        with self._average_appearance():
            view, samples, field_outputs = self._render(self._collide(random_view.flatten()))
            sketch, sketch_samples, _ = self._render(self._collide(sketch_rays)) if sketch_rays is not None else (None,) * 3

        # L_pres on the random view's samples.
        weight = self.preservation_weight(samples.frustums.get_positions())
        with torch.no_grad():
            base_outputs = self.base_field(samples)
        density_edit = field_outputs[FieldHeadNames.DENSITY]
        losses["preservation_loss"] = config.effective_lambda_pres * preservation_loss(
            density_edit, field_outputs[FieldHeadNames.RGB], base_outputs[FieldHeadNames.DENSITY],
            base_outputs[FieldHeadNames.RGB], weight, config.occupancy_threshold, config.preservation_delta,
            config.lambda_colour, config.preservation_target,
        )
        losses["sparsity_loss"] = config.lambda_sp * sparsity_loss(view["accumulation"])
        if is_carving(config):
            # No prompt: empty the sketched region (occupancy -> 0 where w is small).
            _, log_empty = occupancy_log_probabilities(density_edit, config.preservation_delta)
            losses["carve_loss"] = config.lambda_carve * ((1 - weight) * -log_empty).mean()
        else:
            assert self.guidance is not None, "guidance is prepared by the pipeline before training"
            as_image = lambda rgb: rgb.reshape(1, height, width, 3).permute(0, 3, 1, 2)  # noqa: E731
            base_image = None
            if self.guidance.needs_base_render:
                with self._average_appearance():
                    base_image = as_image(self.render_base(self._collide(random_view.flatten()))["rgb"])
            rendered = RenderedView(image=as_image(view["rgb"]), camera_to_world=random_camera["camera_to_world"],
                                    focal=random_camera["focal"], direction=random_camera["direction"],
                                    base_image=base_image)
            losses.update(self.guidance(rendered, step))
            if sketch is not None:
                accumulation = sketch["accumulation"]
                if config.silhouette_opacity == "editable":
                    accumulation = self.editable_accumulation(sketch_samples.frustums.get_positions(), sketch["_weights"],
                                                              accumulation, sketch.get("_ray_indices"))
                accumulation = accumulation.reshape(sketch_masks.shape)
                losses["silhouette_loss"] = config.effective_lambda_sil * silhouette_loss(
                    accumulation, sketch_masks, config.silhouette_normalisation)
                metrics["sketch_coverage"] = (accumulation.detach() > 0.5).float().mul(sketch_masks).sum() / sketch_masks.sum().clamp_min(1)
        rendered = [view] + ([sketch] if sketch is not None else [])
        if photo is not None and config.effective_lambda_photo > 0:
            anchored = self.photo_anchor(*photo)
            if anchored is not None:
                loss, photo_view, kept = anchored
                losses["photo_loss"] = config.effective_lambda_photo * loss
                metrics["photo_rays_kept"] = kept
                rendered.append(photo_view)
        losses.update(self._sampling_losses(rendered))
        metrics["mean_preservation_weight"] = weight.mean().detach()
        metrics["edit_box_boost"] = torch.tensor(self.edit_box_boost())
        bad = [name for name, value in losses.items() if not torch.isfinite(value).all()]
        if bad:
            metrics["nonfinite_losses"] = torch.tensor(float(len(bad)))
        return view, losses, metrics

    def get_image_metrics_and_images(self, outputs, batch):
        """nerfstudio's evaluation images and PSNR/SSIM, without LPIPS."""
        gt = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        predicted = outputs["rgb"]
        gt_chw, predicted_chw = gt.permute(2, 0, 1)[None], predicted.permute(2, 0, 1)[None]
        metrics = {"psnr": float(self.psnr(gt_chw, predicted_chw).item()), "ssim": float(self.ssim(gt_chw, predicted_chw))}
        images = {"img": torch.cat([gt, predicted], dim=1), "accumulation": outputs["accumulation"]}
        if "preservation_weight" in outputs:
            images["preservation_weight"] = outputs["preservation_weight"]
        return metrics, images


def is_carving(config: SkedOptions) -> bool:
    """A prompt-driven guidance (Stable Diffusion) without a prompt removes what is in the sketches."""
    return config.guidance.uses_prompt and not (config.prompt and config.prompt.strip())


def warn_degenerate_settings(config: SkedOptions, sketch_set: SketchSet) -> List[str]:
    """Settings that run without error but cannot give a sensible edit get a clear warning."""
    messages = []
    if config.beta < 1e-3:
        messages.append(f"beta = {config.beta:g} image widths is under a pixel at usual sizes: only the exact "
                        "sketch rays may change and the edit cannot blend in (paper range 0.005-1).")
    if config.beta > 1.0:
        messages.append(f"beta = {config.beta:g} image widths: preservation weights are near 0 around the whole "
                        "object, so the edit may change everything (paper range 0.005-1).")
    if config.lambda_pres == 0:
        messages.append("lambda_pres = 0: nothing preserves the base (the paper's no-preserve ablation).")
    if config.lambda_sil == 0 and config.prompt:
        messages.append("lambda_sil = 0: nothing makes the edit fill the sketches (the paper's no-silhouette ablation).")
    for view in sketch_set.views:
        covered = float(view.mask.mean())
        if covered > 0.9:
            messages.append(f"{view.name or 'a sketch view'}: the mask covers {covered:.0%} of the image, so almost "
                            "nothing in that view is preserved.")
    for message in messages:
        warnings.warn(message, SkedSettingsWarning, stacklevel=2)
    return messages


class SkedSettingsWarning(UserWarning):
    """A setting that runs but defeats the method."""

