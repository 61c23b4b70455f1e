"""What SKED adds to any representation of a scene (a NeRF field, Gaussian splats).

Per iteration (paper Eq. 6): L = L_guidance + lambda_pres L_pres + lambda_sil L_sil
+ lambda_sp L_sp. This class holds everything of it that does not depend on how the scene is
represented: the sketch set and its distance field (the preservation weight w of any point),
the edit box, the guidance call on a rendered image, L_sil on a per-pixel editable opacity,
SKED's step (warm-ups, resume), the frozen base's plumbing, the base-photo check and the
viewer controls.

A representation (`models.nerf.field_edit.SkedMixin` for NeRF fields, the splat model) mixes `SkedEdit` into a
nerfstudio `Model` and supplies:

- `populate_modules`: the parent's modules, then `_setup_sked()`, the base's weights, then
  `_freeze_base(**modules)` with copies of the modules the base is made of;
- `render_base(...)`: the frozen base seen from a view, as the model's outputs ("rgb",
  "accumulation", "depth"), for the guidance's base image and the viewer's show-the-base;
- `get_sked_loss_dict(data, step)`: one iteration's (outputs, losses, metrics) from the
  datamanager's `next_sked` dict: it renders and measures the unweighted terms (`StepTerms`: L_pres from
  `preservation_weight`, the random view's opacity, `guidance_losses`, the sketch views' opacity, the photo
  anchor through `check_photos_once`) and hands them to `objective`, the one place they are weighted and summed;
- evaluation outputs passed through `steer_outputs`, with "preservation_weight" per pixel
  where the representation can give it.

The model needs a `scene_box` (nerfstudio's `Model` has one) and, for
`get_image_metrics_and_images`, `renderer_rgb`, `psnr` and `ssim`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Dict, Optional, Tuple, Union

import numpy as np
import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from torch import Tensor

from sked_ns.errors import warn
from sked_ns.guidance import Guidance, RenderedView
from sked_ns.method.edit_box import EditBox, compute_edit_box, content_bounds, in_box
from sked_ns.method.frozen_base import FrozenBase
from sked_ns.method.losses import silhouette_loss, sparsity_loss
from sked_ns.method.options import SkedOptions, warn_degenerate_settings
from sked_ns.method.photo_anchor import check_base_explains_photos, editable_box, search_box
from sked_ns.method.preservation import SketchDistanceField, check_beta
from sked_ns.sketches.data_frame import model_frame_sketches

TINT = (1.0, 0.2, 0.2)
"""The viewer's tint where the edit may act."""
SKETCH_REACH = 0.5
"""How far around the edit box the base's content is looked for (warn_if_off_base: a share of its longest side), and
the editable region past the scene box (editable_search_box: a share of its size along each axis)."""


@dataclasses.dataclass
class StepTerms:
    """One iteration's terms as a representation measured them, before SKED's weights (paper Eq. 6 and ours)."""

    preservation: Tensor
    """L_pres (Eq. 5), a mean over the representation's samples (or Gaussians)."""
    accumulation: Tensor
    """The random view's opacity, for L_sp."""
    guidance: Dict[str, Tensor] = dataclasses.field(default_factory=dict)
    """The guidance's losses (weighted by the guidance's own `weight`); none when carving."""
    carve: Optional[Tensor] = None
    """Carving (no prompt): -log P(empty) where the sketches allow change."""
    sketch: Optional[Tuple[Tensor, Tensor]] = None
    """(opacity of the sketch views' pixels, their masks), for L_sil; None: no sketch view this step."""
    new_mass: Optional[Tensor] = None
    photo: Optional[Tensor] = None
    """The photo anchor's MSE at the base's photos' pixels far from the edit."""
    representation: Dict[str, Tensor] = dataclasses.field(default_factory=dict)
    """The representation's own losses, already weighted as its nerfstudio model weights them."""


class SkedEdit:
    """Sketch geometry, guidance, L_sil, SKED's step, the frozen base's plumbing and viewer controls."""

    config: SkedOptions

    # ---- set-up ---------------------------------------------------------------------------
    def _scaled_config(self):
        """A private copy of the config, so per-model adjustments never reach the saved config.yml."""
        if self.config.samples_per_ray_scale <= 0 or not math.isfinite(self.config.samples_per_ray_scale):
            raise ValueError(f"samples_per_ray_scale = {self.config.samples_per_ray_scale}: must be a positive number.")
        return dataclasses.replace(self.config)

    def _setup_sked(self) -> None:
        """Call after the parent's populate_modules: the sketch set in the model's frame and what follows from it."""
        self.lpips = None
        self.sketch_set = sketch_set = model_frame_sketches(self.config.sketches, self.kwargs.get("metadata") or {})
        # Quiet: the edit's inputs were checked and warned of before anything was written (engine/edit_inputs.py).
        self.content_box, self.content_bounded = content_bounds(self.config, self.scene_box.aabb.numpy())
        self.edit_box: EditBox = compute_edit_box(sketch_set.views, self.content_box, self.content_bounded, quiet=True)
        # The box as a device buffer (moved with the model, never saved): a host-built tensor per call would be a sync.
        self.register_buffer("edit_box_bounds", torch.as_tensor(np.stack([self.edit_box.min, self.edit_box.max]),
                                                                dtype=torch.float32), persistent=False)
        self.sketch_field = SketchDistanceField(
            sketch_set.views, compile=self.config.compile_lookup and torch.cuda.is_available()
        )
        warn_degenerate_settings(self.config, sketch_set)
        self.guidance: Optional[Guidance] = None  # plain attribute: never in a checkpoint
        self._add_viewer_controls()

    def warn_if_off_base(self) -> None:
        """Sketches drawn on another scene, or posed in another frame, meet in empty space: the edit would add content
        in the air and every check of the sketches alone passes. Warned when neither the edit box nor the space around
        it (SKETCH_REACH of its longest side each side) holds any of the base's content."""
        # One length on every axis: a box the views bound tightly along one axis is no less near the content there.
        reach = SKETCH_REACH * float(np.max(self.edit_box.max - self.edit_box.min))
        low, high = self.edit_box.min - reach, self.edit_box.max + reach
        if not self.base_content_near(low, high):
            warn(f"{self.config.sketches}: the sketches meet in empty space, with none of the base's content in or "
                 f"near their region (x, y, z from {np.round(self.edit_box.min, 3).tolist()} to "
                 f"{np.round(self.edit_box.max, 3).tolist()}). Were they drawn on another scene, are their poses in "
                 "another frame, or is the base barely trained there? Look at them in the viewer (the edit box is "
                 "shown) before a long edit.")

    def base_content_near(self, low: np.ndarray, high: np.ndarray) -> bool:
        """Whether the frozen base holds opaque content in the box [low, high] (model frame)."""
        raise NotImplementedError

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

    def steer_outputs(self, outputs: Dict[str, Tensor],
                      render_base: Callable[[], Dict[str, Tensor]]) -> Dict[str, Tensor]:
        """Evaluation outputs as the viewer controls ask: the base (`render_base()`, the same view) instead of the
        edit, tinted by 1 - w where the outputs hold a per-pixel "preservation_weight"."""
        if self.viewer_show_base.value:
            base = render_base()
            outputs = {**outputs, "rgb": base["rgb"], "accumulation": base["accumulation"], "depth": base["depth"]}
        if self.viewer_tint.value and "preservation_weight" in outputs:
            editable = (1.0 - outputs["preservation_weight"]).clamp(0, 1)
            tint = torch.tensor(TINT, device=editable.device)
            outputs = {**outputs, "rgb": outputs["rgb"] * (1 - 0.6 * editable) + 0.6 * editable * tint}
        return outputs

    # ---- the frozen base --------------------------------------------------------------------
    def _freeze_base(self, **modules: torch.nn.Module) -> None:
        # A dataclass (not a module) hides the frozen base from the module tree, so from optimisers and checkpoints.
        self.frozen_base = FrozenBase.copy_of(**modules)

    def _apply(self, fn, *args, **kwargs):
        # `.to()`, `.cuda()`, `.half()` reach the hidden base too.
        super()._apply(fn, *args, **kwargs)
        frozen = self.frozen_base.modules() if getattr(self, "frozen_base", None) is not None else []
        for module in frozen + getattr(self, "_base_cameras", []):
            module._apply(fn, *args, **kwargs)
        return self

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

    # ---- the sketches' geometry ---------------------------------------------------------------
    def preservation_weight(self, positions: Tensor) -> Tensor:
        """w for positions (..., 3) -> (..., 1): samples on rays, or Gaussians' centres."""
        return self.sketch_field.preservation_weight(positions.detach(), self.config.beta)[..., None]

    @torch.no_grad()
    def in_sketch_hull(self, positions: Tensor, tolerance: Optional[float] = None) -> Tensor:
        """Whether points (..., 3) project inside every sketch, to `tolerance` image widths (default a
        pixel): where new mass may appear."""
        flat = positions.reshape(-1, 3)
        if tolerance is None:
            tolerance = 1.0 / min(view.width for view in self.sketch_set.views)
        # Every point, no mask: a step never waits to learn how many points are in the box.
        inside = in_box(flat, self.edit_box_bounds.to(flat.dtype)) & (self.sketch_field.hull_distance(flat) <= tolerance)
        return inside.reshape(positions.shape[:-1])

    # ---- the losses on images ----------------------------------------------------------------
    def guidance_losses(self, image: Tensor, random_camera: Dict,
                        base_image: Union[None, Tensor, Callable[[], Tensor]], step: int,
                        samples_per_side: int = 1) -> Dict[str, Tensor]:
        """The guidance's losses on the random view's image (1, 3, H, W). `base_image`: the base's render of the
        same view, or a function rendering it, called only when the guidance needs it; `samples_per_side`: how the
        image was sampled (RenderedView)."""
        assert self.guidance is not None, "guidance is prepared by the pipeline before training"
        if callable(base_image):
            base_image = base_image() if self.guidance.needs_base_render else None
        rendered = RenderedView(image=image, camera_to_world=random_camera["camera_to_world"],
                                focal=random_camera["focal"], direction=random_camera["direction"],
                                base_image=base_image, samples_per_side=samples_per_side)
        return self.guidance(rendered, step)

    def objective(self, terms: StepTerms, carving: bool) -> Tuple[Dict[str, Tensor], Dict[str, Tensor]]:
        """The iteration's weighted losses (nerfstudio sums the dict: L = L_guidance + lambda_pres L_pres +
        lambda_sil L_sil + lambda_sp L_sp, paper Eq. 6, plus carving, new-mass and photo-anchor terms) and metrics."""
        config = self.config
        losses = {"preservation_loss": config.effective_lambda_pres * terms.preservation,
                  "sparsity_loss": config.lambda_sp * sparsity_loss(terms.accumulation)}
        metrics: Dict[str, Tensor] = {}
        if carving:
            losses["carve_loss"] = config.lambda_carve * terms.carve
        else:
            losses.update(terms.guidance)
            if terms.sketch is not None:
                sil_losses, metrics = self.silhouette_losses(*terms.sketch)
                losses.update(sil_losses)
            else:
                losses["silhouette_loss"] = torch.zeros((), device=terms.accumulation.device)
            if terms.new_mass is not None:
                losses["new_mass_loss"] = config.lambda_new_mass * terms.new_mass
        if terms.photo is not None:
            losses["photo_loss"] = config.effective_lambda_photo * terms.photo
        losses.update(terms.representation)
        self.finite_check(losses, metrics)
        return losses, metrics

    def silhouette_losses(self, editable_opacity: Tensor,
                          sketch_masks: Tensor) -> Tuple[Dict[str, Tensor], Dict[str, Tensor]]:
        """L_sil: the sketch views' opacity (of editable content, or all of it: config.silhouette_opacity decides
        what the representation passes) against the masks, any shape holding as many pixels as the masks."""
        opacity = editable_opacity.reshape(sketch_masks.shape)
        losses = {"silhouette_loss": self.config.effective_lambda_sil * silhouette_loss(
            opacity, sketch_masks, self.config.silhouette_normalisation)}
        covered = (opacity.detach() > 0.5).float().mul(sketch_masks).sum() / sketch_masks.sum().clamp_min(1)
        return losses, {"sketch_coverage": covered}

    @staticmethod
    def finite_check(losses: Dict[str, Tensor], metrics: Dict[str, Tensor]) -> None:
        """Counts the losses that are not finite (metrics["nonfinite_losses"], 0 when all are): safe_step skips such a
        step. Counted on the device: the host reads it only when it logs."""
        if losses:
            flags = torch.stack([~torch.isfinite(value.detach()).all() for value in losses.values()])
            metrics["nonfinite_losses"] = flags.sum().float()

    # ---- the base-photo anchor --------------------------------------------------------------
    def photo_anchor_acts(self) -> bool:
        """Whether a step needs the base's photos (the datamanager loads them only then)."""
        return self.config.effective_lambda_photo > 0

    _photos_checked: bool = False
    base_photo_psnr: Optional[float] = None
    """The base's PSNR at the first batch of anchored photo pixels (check_base_explains_photos)."""

    def editable_search_box(self) -> Tensor:
        """(2, 3) where the editable region is looked for: the scene box, and the edit box with SKETCH_REACH of its
        size each side where it reaches past it (within the space the base holds)."""
        return search_box(self.scene_box.aabb, self.edit_box.min, self.edit_box.max, SKETCH_REACH,
                          self.content_box if self.content_bounded else None)

    def editable_box(self) -> Optional[Tensor]:
        """The box holding every point with w <= photo_threshold (follows beta, which the viewer may change)."""
        key = (self.config.beta, self.config.photo_threshold)
        if getattr(self, "_editable_box_key", None) != key:
            self._editable_box = editable_box(lambda p: self.preservation_weight(p)[..., 0], self.editable_search_box(),
                                              self.config.photo_threshold)
            self._editable_box_key = key
        return self._editable_box

    def check_photos_once(self, predicted: Tensor, truth: Tensor) -> bool:
        """Whether the photo anchor may use this batch: once, on the first batch (the edit is still the base
        there, or holds it at these pixels when resumed), the base must explain its photos, else the anchor is
        switched off for the run."""
        if self._photos_checked:
            return True
        self._photos_checked = True
        self.base_photo_psnr, explained = check_base_explains_photos(predicted, truth)
        if not explained:
            self.config.lambda_photo = 0.0  # this model's copy of the config: config.yml keeps what was typed
        return explained

    # ---- evaluation -------------------------------------------------------------------------
    def eval_ground_truth(self, outputs, batch) -> Tensor:
        """The photo as the model renders one: on its background."""
        return self.renderer_rgb.blend_background(batch["image"].to(self.device))

    def eval_counts(self) -> Dict[str, float]:
        """The model's size at evaluation, logged beside PSNR (a NeRF's does not change)."""
        return {}

    def get_image_metrics_and_images(self, outputs, batch):
        """nerfstudio's evaluation images and PSNR/SSIM, without LPIPS."""
        gt = self.eval_ground_truth(outputs, batch)
        predicted = outputs["rgb"]
        gt_chw, predicted_chw = gt.permute(2, 0, 1)[None], predicted.permute(2, 0, 1)[None]
        metrics = {"psnr": float(self.psnr(gt_chw, predicted_chw).item()), "ssim": float(self.ssim(gt_chw, predicted_chw)),
                   **self.eval_counts()}
        images = {"img": torch.cat([gt, predicted], dim=1), "accumulation": outputs["accumulation"]}
        if "preservation_weight" in outputs:
            images["preservation_weight"] = outputs["preservation_weight"]
        return metrics, images
