"""SKED on a splatfacto base: the base's Gaussians, those far from the sketches kept exactly, the rest editable.

A Gaussian is a point with a preservation weight w, taken at its centre from the sketch distance
field (paper Eq. 4). The base's Gaussians are split once, at set-up:

- **kept** (w > keep_threshold): buffers, never optimised, never densified, pruned or reset, so they
  stay bit-identical to the base whatever the edit does. They are not saved with the edit: it saves which
  of the base's Gaussians it keeps (`kept_in_base`), and they are read from its copy of the base whenever
  it is built, so its checkpoint holds what it changed. An edit is a base for the next one: read as a
  base, it is composed from its own base and its changes (gaussians.base_gaussians);
- **editable** (the rest, plus new seeds inside the sketches' visual hull): splatfacto's own
  `gauss_params`, optimised at the edit's Adam rates (edit_rates: splatfacto's are sized for 30,000
  steps) and refined by splatfacto's strategy (gsplat's DefaultStrategy), which never sees the kept
  ones. L_pres holds each editable base Gaussian to its base values (opacity, colour, position,
  scale, rotation) weighted by its w (its targets, too, are saved only once refinement moves them: saved.py).

Both sets are rendered in one pass, kept first; the scene's `means`, `scales`, ... (what
`ns-export gaussian-splat` and the viewer read) are the two concatenated. The editable opacity
sum_i T_i alpha_i (1 - w_i) that L_sil fills is rendered as a fourth colour channel in the same pass.
The frozen base (all the base's Gaussians) is a plain attribute: never optimised or saved, moved by `.to()`.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
import torch
from gsplat.strategy import DefaultStrategy
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.colors import get_color
from torch import Tensor
from torch.nn import Parameter

from sked_ns.errors import SkedUserError
from sked_ns.method.edit import SkedEdit, StepTerms
from sked_ns.method.edit_box import in_box
from sked_ns.method.frozen_base import base_weights, read_model_state
from sked_ns.method.options import SkedOptions, is_carving, taken_from_the_base
from sked_ns.method.photo_anchor import rays_away_from_edit
from sked_ns.method.preservation import check_beta
from sked_ns.models.splat.densify import EditableRefinement
from sked_ns.models.splat.gaussians import (
    GAUSSIAN_PARAMS,
    KEPT_IN_BASE,
    GaussianSet,
    base_gaussians,
    gaussian_colours,
    kept_gaussians,
    splat_preservation_loss,
)
from sked_ns.models.splat.photo_anchor import SplatPhotoAnchor
from sked_ns.models.splat.rasterize import rasterize
from sked_ns.models.splat.saved import TARGETS, base_in_its_order, targets_are_the_bases, targets_from_the_base
from sked_ns.models.splat.seeds import hull_seeds
from sked_ns.sketches.cameras import viewmat

NEVER = 1 << 30
"""A step count no edit reaches (splatfacto's opacity reset switched off)."""


def area_downsample(image: Tensor, factor: int) -> Tensor:
    """An (H * factor, W * factor, C) image averaged over factor x factor blocks to (H, W, C)."""
    pooled = torch.nn.functional.avg_pool2d(image.permute(2, 0, 1)[None], factor)
    return pooled[0].permute(1, 2, 0)


@dataclass
class SkedSplatModelConfig(SplatfactoModelConfig, SkedOptions):
    """SKED on a splatfacto scene. Architecture fields (SH degree, rasterize mode, background, refinement
    thresholds) are copied from the base (options.copy_base_architecture); the schedules and the fields below are
    the edit's (EDIT_OWNED)."""

    # The edit's seeds and kept set, and schedules of training from scratch (an edit starts from a trained base,
    # at full resolution and SH degree, without opacity resets).
    EDIT_OWNED = SkedOptions.EDIT_OWNED | {
        "keep_threshold", "num_seeds", "seed_opacity", "seed_size", "reset_alpha_every", "warmup_length",
        "refine_every", "stop_split_at", "stop_screen_size_at", "sh_degree_interval", "resolution_schedule",
        "num_downscales", "random_init", "num_random", "random_scale",
    }
    _target: Type = field(default_factory=lambda: SkedSplatModel)
    # keep_threshold, num_seeds, seed_opacity, seed_size: SkedOptions (typeable on `ns-train sked` for any base).
    reset_alpha_every: int = 0
    """splatfacto's opacity reset every this many refinements; 0 = never (an edit starts from a trained base:
    a reset would fade every editable base Gaussian at once)."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Edits keep the base's cameras."""



taken_from_the_base(SkedSplatModelConfig, SplatfactoModelConfig)  # the base's architecture: not typeable

class SkedSplatModel(SkedEdit, SplatfactoModel):
    """Kept Gaussians (buffers) + editable Gaussians (splatfacto's parameters) + frozen base + sketches + guidance."""

    config: SkedSplatModelConfig
    """The base-photo anchor takes whole training images (the datamanager's `photo_view`), not ray batches."""

    # ---- set-up ---------------------------------------------------------------------------
    def populate_modules(self) -> None:
        """splatfacto's modules without its random initialisation or LPIPS; the Gaussians come from the base."""
        from pytorch_msssim import SSIM
        from torchmetrics.image import PeakSignalNoiseRatio

        check_beta(self.config.beta)
        self.config = self._scaled_config()
        if not 0.0 < self.config.seed_opacity < 1.0:
            raise SkedUserError(f"--pipeline.model.seed-opacity {self.config.seed_opacity}: must be in (0, 1).")
        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self.step = 0
        self.crop_box = None
        self.background_color = (torch.tensor([0.1490, 0.1647, 0.2157]) if self.config.background_color == "random"
                                 else get_color(self.config.background_color))
        self.camera_optimizer = self.config.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        self._setup_sked()

        base = self._read_base()
        kept = self.preservation_weight(base["means"])[:, 0] > self.config.keep_threshold
        count = 0 if is_carving(self.config) else max(int(self.config.num_seeds), 0)  # carving makes nothing
        seeds = hull_seeds(count, self.edit_box, self.in_sketch_hull, self.config.seed_opacity,
                           self.config.seed_size, base["features_rest"].shape[1])
        editable = {name: torch.cat([base[name][~kept], seeds[name]]) for name in GAUSSIAN_PARAMS}
        self._hold_kept(base, kept)
        self.gauss_params = torch.nn.ParameterDict({name: Parameter(value.clone()) for name, value in editable.items()})
        from_base = torch.cat([torch.ones(int((~kept).sum()), dtype=torch.bool),
                               torch.zeros(len(seeds["means"]), dtype=torch.bool)])
        # L_pres's targets, one per editable Gaussian; follow it through densification (densify.follow_densification).
        self.reference = GaussianSet({**{name: value.clone() for name, value in editable.items()}, "from_base": from_base})
        self.refinement = EditableRefinement(self._strategy())
        self._step_infos: List[Dict] = []  # the step's training renders, for the refinement after the backward
        self.photo_anchor = SplatPhotoAnchor(self._render_edit, self.composite_with_background, self._rays_away_from_edit,
                                             self.check_photos_once, lambda: self._photos_checked)

    def _hold_kept(self, base: Dict[str, Tensor], kept: Tensor) -> None:
        """The base's Gaussians split by `kept` (N_base bools): the kept set (read from the base, not saved) and
        which rows it is (saved), and the frozen base, kept rows first."""
        self.kept = GaussianSet(kept_gaussians(base, kept, base_weights(self.config)), saved=False)
        self.register_buffer(KEPT_IN_BASE, kept.clone())
        # Plain attribute: never optimised or saved. Kept first, as the edit renders them, so that an unchanged edit
        # renders bit-identically to it (the compositor's sums depend on the order of equal-depth Gaussians' blocks).
        self.frozen_gaussians: Dict[str, Tensor] = {name: torch.cat([value[kept], value[~kept]])
                                                    for name, value in base.items()}
        self.__dict__.pop("_fixed_weights", None)  # w of other Gaussians

    def _base_in_its_order(self) -> Dict[str, Tensor]:
        return base_in_its_order(self.frozen_gaussians, getattr(self, KEPT_IN_BASE))

    @torch.no_grad()
    def base_content_near(self, low: np.ndarray, high: np.ndarray) -> bool:
        """A base Gaussian more opaque than a half, or faint ones holding as much opacity as one fully opaque, have
        their centres in the box (a briefly fitted base is all faint Gaussians: splatfacto starts them at 0.1)."""
        means = self.frozen_gaussians["means"]
        inside = in_box(means, torch.as_tensor(np.stack([low, high]), dtype=means.dtype, device=means.device))
        opacity = torch.sigmoid(self.frozen_gaussians["opacities"]).reshape(-1) * inside
        return bool(opacity.numel()) and bool((opacity.max() > 0.5) | (opacity.sum() >= 1.0))

    def _read_base(self) -> Dict[str, Tensor]:
        if self.config.base_checkpoint is None:
            raise ValueError("No base checkpoint: run `ns-train sked --load-dir <splatfacto run>`.")
        checkpoint = base_weights(self.config)
        return base_gaussians(read_model_state(checkpoint), checkpoint, self.config.sh_degree)

    def _strategy(self) -> DefaultStrategy:
        """splatfacto's strategy and settings (its populate_modules), the opacity reset as the edit sets it."""
        config = self.config
        reset_every = config.reset_alpha_every * config.refine_every if config.reset_alpha_every > 0 else NEVER
        return DefaultStrategy(
            prune_opa=config.cull_alpha_thresh, grow_grad2d=config.densify_grad_thresh,
            grow_scale3d=config.densify_size_thresh, grow_scale2d=config.split_screen_size,
            prune_scale3d=config.cull_scale_thresh, prune_scale2d=config.cull_screen_size,
            refine_scale2d_stop_iter=config.stop_screen_size_at, refine_start_iter=config.warmup_length,
            refine_stop_iter=config.stop_split_at, reset_every=reset_every, refine_every=config.refine_every,
            pause_refine_after_reset=self.num_train_data + config.refine_every if reset_every != NEVER else 0,
            absgrad=config.use_absgrad, revised_opacity=False, verbose=False,
        )

    def _apply(self, fn, *args, **kwargs):
        # `.to()`, `.cuda()`, `.half()` reach the frozen base too.
        super()._apply(fn, *args, **kwargs)
        if getattr(self, "frozen_gaussians", None) is not None:
            self.frozen_gaussians = {name: fn(value) for name, value in self.frozen_gaussians.items()}
        return self

    # ---- the scene: kept + editable (what the viewer and ns-export gaussian-splat read) ----------------
    def _scene(self, name: str) -> Tensor:
        return torch.cat([self.kept[name], self.gauss_params[name]])

    @property
    def means(self):
        return self._scene("means")

    @property
    def scales(self):
        return self._scene("scales")

    @property
    def quats(self):
        return self._scene("quats")

    @property
    def features_dc(self):
        return self._scene("features_dc")

    @property
    def features_rest(self):
        return self._scene("features_rest")

    @property
    def opacities(self):
        return self._scene("opacities")

    @property
    def num_points(self):
        return len(self.kept["means"]) + len(self.gauss_params["means"])

    def scene_gaussians(self) -> Dict[str, Tensor]:
        return {name: self._scene(name) for name in GAUSSIAN_PARAMS}

    # ---- preservation weights per Gaussian ----------------------------------------------------
    def _fixed_weight(self, name: str, means: Tensor) -> Tensor:
        """w of Gaussians that never move (the kept ones, the frozen base): once per beta, not every render."""
        key = (self.config.beta, len(means), means.device)
        cache = self.__dict__.setdefault("_fixed_weights", {})
        if name not in cache or cache[name][0] != key:
            cache[name] = (key, self.preservation_weight(means))
        return cache[name][1]

    def _scene_weight(self) -> Tensor:
        """(N, 1) w at every Gaussian's centre, kept first (editable ones where they are now)."""
        return torch.cat([self._fixed_weight("kept", self.kept["means"]),
                          self.preservation_weight(self.gauss_params["means"])])

    # ---- rendering ------------------------------------------------------------------------
    def _rasterize(self, gaussians: Dict[str, Tensor], camera: Cameras, background: Tensor,
                   extra: Optional[Tensor] = None, depth: bool = False) -> Tuple[Dict[str, Tensor], Dict]:
        """One camera's image: "rgb" on `background`, "accumulation", `extra` per-Gaussian channels composited as
        "extra" (sum_i T_i alpha_i x_i), "depth" (expected) if asked, and the rasterizer's info."""
        camera_to_world = camera.camera_to_worlds.reshape(-1, 3, 4)[:1].to(self.device, torch.float32)
        intrinsics = camera.get_intrinsics_matrices().reshape(-1, 3, 3)[:1].to(self.device, torch.float32)
        width, height = int(camera.width.reshape(-1)[0]), int(camera.height.reshape(-1)[0])
        # gsplat's kernels take float32: a mixed-precision iteration (autocast) must not hand them half floats.
        with torch.autocast(device_type=self.device.type, enabled=False):
            gaussians = {name: value.float() for name, value in gaussians.items()}
            colours = gaussian_colours(gaussians, camera_to_world[0, :, 3], self.config.sh_degree)
            if extra is not None:
                colours = torch.cat([colours, extra.float()], dim=-1)
            render, alpha, info = rasterize(
                gaussians["means"], gaussians["quats"], torch.exp(gaussians["scales"]),
                torch.sigmoid(gaussians["opacities"]).squeeze(-1), colours, viewmat(camera_to_world), intrinsics,
                width, height, render_mode="RGB+ED" if depth else "RGB", absgrad=self.refinement.strategy.absgrad,
                rasterize_mode=self.config.rasterize_mode,
            )
        render, alpha = render[0], alpha[0]
        outputs = {"rgb": torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0), "accumulation": alpha,
                   "background": background}
        if extra is not None:
            outputs["extra"] = render[..., 3:3 + extra.shape[-1]]
        if depth:
            depth_image = render[..., -1:]
            outputs["depth"] = torch.where(alpha > 0, depth_image, depth_image.detach().max())
        return outputs, info

    def _render_edit(self, camera: Cameras, background: Tensor, channel: Optional[str] = None,
                     depth: bool = False) -> Dict[str, Tensor]:
        """The edited scene; channel "editable" adds sum_i T_i alpha_i (1 - w_i) (L_sil's editable opacity),
        "preserved" adds sum_i T_i alpha_i w_i. Training renders feed splatfacto's densification."""
        gaussians = self.scene_gaussians()
        extra = None
        if channel is not None:
            weight = self._scene_weight()
            extra = (1.0 - weight) if channel == "editable" else weight
        if self.crop_box is not None and not self.training:
            inside = self.crop_box.within(gaussians["means"]).reshape(-1)
            gaussians = {name: value[inside] for name, value in gaussians.items()}
            extra = extra[inside] if extra is not None else None
        outputs, info = self._rasterize(gaussians, camera, background, extra, depth)
        if self.training and torch.is_grad_enabled() and info["means2d"].requires_grad:
            info["means2d"].retain_grad()  # the strategy reads its gradient after the backward
            self._step_infos.append(info)
        return outputs

    def _render_supersampled(self, camera: Cameras, background: Tensor, channel: Optional[str] = None,
                             base: bool = False) -> Dict[str, Tensor]:
        """The edit (or with `base`, the frozen base: the guidance's reference outside the change is the base's render,
        which must be sampled as the edit is) at splat_supersampling times the camera's resolution, each image
        averaged back down to it."""
        render = (lambda view: self.render_base(view, background)) if base else (
            lambda view: self._render_edit(view, background, channel))
        factor = int(self.config.splat_supersampling)
        if factor <= 1:
            return render(camera)
        fine = copy.deepcopy(camera)
        fine.rescale_output_resolution(float(factor))
        outputs = render(fine)
        return {name: area_downsample(value, factor) if value.dim() == 3 else value for name, value in outputs.items()}

    @torch.no_grad()
    def render_base(self, camera: Cameras, background: Optional[Tensor] = None) -> Dict[str, Tensor]:
        """The frozen base seen from `camera`: "rgb", "accumulation", "depth", "preservation_weight" (rendered as the
        edit is, the same channels in the same order: an unchanged edit renders bit-identically)."""
        background = self._get_background_color() if background is None else background
        base = self.frozen_gaussians
        outputs = self._rasterize(base, camera, background, self._fixed_weight("base", base["means"]), depth=True)[0]
        outputs["preservation_weight"] = (outputs.pop("extra") + (1 - outputs["accumulation"])).clamp(0, 1)
        return outputs

    # ---- nerfstudio's hooks ----------------------------------------------------------------
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """The editable Gaussians only (splatfacto's six groups); the kept ones are buffers."""
        return {name: [self.gauss_params[name]] for name in GAUSSIAN_PARAMS}

    def _rays_away_from_edit(self, origins: Tensor, directions: Tensor, nears: Tensor, fars: Tensor) -> Tensor:
        """Which rays never come near the editable region (the photo anchor's pixels)."""
        rays = [value.to(self.device) for value in (origins, directions, nears, fars)]
        return rays_away_from_edit(*rays, self.editable_box(), lambda p: self.preservation_weight(p)[..., 0],
                                   self.config.photo_threshold)

    def step_post_backward(self, step: int) -> None:
        """splatfacto's densification on the editable Gaussians, from this step's training renders."""
        infos, self._step_infos = self._step_infos, []
        self.refinement.step_post_backward(step, self.gauss_params, self.optimizers, infos, len(self.kept["means"]),
                                           self.reference)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """SKED's step, and splatfacto's two: the step and optimizers before, densification after each iteration."""
        return [
            self.sked_step_callback(),
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb,
                             args=[training_callback_attributes.optimizers]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.step_post_backward),
        ]

    def load_state_dict(self, state_dict, strict: bool = True, **kwargs):  # type: ignore[override]
        """A saved edit's Gaussian counts differ from a fresh one's (densification): resize, then load. Parameters
        are resized in place, so the optimisers (set up before a resumed run loads) keep holding them. Its kept
        Gaussians are the base's rows it saved as kept, and L_pres's targets the base's values where it saved none
        (saved.py); an edit saved whole (by earlier versions) holds both itself, loaded as saved and saved again."""
        state_dict = dict(state_dict)
        whole = "kept.means" in state_dict
        if whole:
            state_dict.setdefault(KEPT_IN_BASE, getattr(self, KEPT_IN_BASE))
        elif KEPT_IN_BASE in state_dict:
            saved = state_dict[KEPT_IN_BASE].to(self.kept_in_base.device)
            set_up = self.reference.tensors()
            if not torch.equal(saved, self.kept_in_base):  # w rounded across keep_threshold on another device
                self._hold_kept(self._base_in_its_order(), saved)
            if f"{TARGETS}means" not in state_dict and "gauss_params.means" in state_dict:
                editable = {name: state_dict[f"gauss_params.{name}"] for name in GAUSSIAN_PARAMS}
                state_dict.update(targets_from_the_base(self._base_in_its_order(), saved, set_up, editable))
        self.kept.save_with_model(whole)
        for name, parameter in self.gauss_params.items():
            key = f"gauss_params.{name}"
            if key in state_dict:
                parameter.data = torch.zeros_like(state_dict[key], dtype=parameter.dtype, device=parameter.device)
        for prefix, holder in (("kept.", self.kept), ("reference.", self.reference)):
            holder.assign({name: torch.zeros_like(state_dict[prefix + name], device=value.device)
                           for name, value in holder.tensors().items() if prefix + name in state_dict})
        self.refinement.reset()
        self._step_infos = []
        return torch.nn.Module.load_state_dict(self, state_dict, strict=strict, **kwargs)

    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """The model's state, without L_pres's targets while they are the base's values (saved.py)."""
        state = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        if f"{prefix}kept.means" in state:
            return state  # an edit saved whole by earlier versions, saved as it was
        kept, targets = getattr(self, KEPT_IN_BASE), self.reference.tensors()
        if targets_are_the_bases(targets, len(self.gauss_params["means"]), self._base_in_its_order(), kept):
            for name in targets:
                state.pop(f"{prefix}{TARGETS}{name}")
        return state

    # ---- one iteration --------------------------------------------------------------------
    def get_sked_loss_dict(self, data: Dict, step: int) -> Tuple[Dict[str, Tensor], Dict[str, Tensor], Dict[str, Tensor]]:
        """All losses of one iteration from the datamanager's `next_sked` dict; returns (outputs, losses, metrics)."""
        config = self.config
        self._step_infos = []
        background = self._get_background_color()  # one per step: the edit and the base on the same one
        camera = data["random_view_camera"]
        view = self._render_supersampled(camera, background, channel="editable")

        reference = self.reference.tensors()
        weight = self.preservation_weight(reference["means"])[:, 0] * reference["from_base"].float()
        terms = StepTerms(preservation=splat_preservation_loss(dict(self.gauss_params), reference, weight,
                                                               config.lambda_colour, config.sh_degree),
                          accumulation=view["accumulation"])
        carving = is_carving(config)
        if carving:
            # No prompt: empty the sketched region (each editable Gaussian's opacity -> 0 where w is small).
            free = 1.0 - self.preservation_weight(self.gauss_params["means"])[:, 0]
            log_empty = -torch.nn.functional.softplus(self.gauss_params["opacities"].float()[:, 0])  # log(1 - o)
            terms.carve = (free * -log_empty).mean() if len(free) else free.sum()
        else:
            image = view["rgb"].permute(2, 0, 1)[None]
            base_image = lambda: self._render_supersampled(  # noqa: E731
                camera, background, base=True)["rgb"].permute(2, 0, 1)[None]
            terms.guidance = self.guidance_losses(image, data["random_camera"], base_image, step,
                                                  samples_per_side=max(int(config.splat_supersampling), 1))
            if config.effective_lambda_sil > 0 and data.get("sketch_views"):
                opacities, masks = [], []
                for sketch_camera, mask in data["sketch_views"]:
                    sketch = self._render_edit(sketch_camera, background, channel="editable")
                    opacity = sketch["extra"] if config.silhouette_opacity == "editable" else sketch["accumulation"]
                    opacities.append(opacity.reshape(-1))
                    masks.append(mask.reshape(-1).to(opacity))
                terms.sketch = (torch.cat(opacities), torch.cat(masks))
        photo = data.get("photo_view")
        photo_metrics: Dict[str, Tensor] = {}
        if photo is not None and config.effective_lambda_photo > 0:
            terms.photo = self.photo_anchor.loss(photo, background, photo_metrics,
                                                 (config.beta, config.photo_threshold))
        losses, metrics = self.objective(terms, carving)
        metrics.update(photo_metrics)
        metrics["mean_preservation_weight"] = weight.sum() / reference["from_base"].sum().clamp_min(1)
        metrics["editable_gaussians"] = torch.tensor(float(len(self.gauss_params["means"])))
        metrics["kept_gaussians"] = torch.tensor(float(len(self.kept["means"])))
        return view, losses, metrics

    # ---- evaluation ------------------------------------------------------------------------
    def get_outputs(self, camera: Cameras) -> Dict[str, Tensor]:
        """splatfacto's outputs (rgb, depth, accumulation, background) and the expected preservation weight
        sum_i T_i alpha_i w_i + (1 - accumulation) (0 where a pixel shows what the edit may change); the viewer's
        show-the-base and tint controls applied."""
        if not isinstance(camera, Cameras):
            return {}
        background = self._get_background_color()
        outputs = self._render_edit(camera, background, channel="preserved", depth=True)
        outputs["preservation_weight"] = (outputs.pop("extra") + (1 - outputs["accumulation"])).clamp(0, 1)
        if not self.training:
            height, width = outputs["rgb"].shape[:2]
            outputs["background"] = background.expand(height, width, 3)
        return self.steer_outputs(outputs, lambda: self.render_base(camera, background))

    def eval_ground_truth(self, outputs, batch) -> Tensor:
        """The photo on the background the evaluation render used (splatfacto's)."""
        background = outputs["background"]
        background = background[0, 0] if background.dim() == 3 else background
        return self.composite_with_background(self.get_gt_img(batch["image"]), background)

    def eval_counts(self) -> Dict[str, float]:
        return {"gaussian_count": float(self.num_points)}
