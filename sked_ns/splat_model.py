"""SKED on a splatfacto base: the base's Gaussians, those far from the sketches kept exactly, the rest editable.

A Gaussian is a point with a preservation weight w, taken at its centre from the sketch distance
field (paper Eq. 4). The base's Gaussians are split once, at set-up:

- **kept** (w > keep_threshold): buffers, never optimised, never densified, pruned or reset, so they
  stay bit-identical to the base whatever the edit does (they are saved with the edit, which makes
  its checkpoint the whole scene: an edit is a base for the next one);
- **editable** (the rest, plus new seeds inside the sketches' visual hull): splatfacto's own
  `gauss_params`, optimised at the edit's Adam rates (edit_rates: splatfacto's are sized for 30,000
  steps) and refined by splatfacto's strategy (gsplat's DefaultStrategy), which never sees the kept
  ones. L_pres holds each editable base Gaussian to its base values (opacity, colour, position,
  scale, rotation) weighted by its w.

Both sets are rendered in one pass, kept first; the scene's `means`, `scales`, ... (what
`ns-export gaussian-splat` and the viewer read) are the two concatenated. The editable opacity
sum_i T_i alpha_i (1 - w_i) that L_sil fills is rendered as a fourth colour channel in the same pass.
The frozen base (all the base's Gaussians) is a plain attribute: never optimised or saved, moved by `.to()`.
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List, Optional, Tuple, Type

import torch
from gsplat.strategy import DefaultStrategy
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig, num_sh_bases
from nerfstudio.utils.colors import get_color
from torch import Tensor
from torch.nn import Parameter

from sked_ns.cameras import viewmat
from sked_ns.base_scene import read_model_state
from sked_ns.edit import SkedEdit
from sked_ns.errors import SkedUserError
from sked_ns.losses import sparsity_loss
from sked_ns.options import SkedOptions, is_carving
from sked_ns.photo_anchor import rays_away_from_edit
from sked_ns.preservation import check_beta
from sked_ns.splat_render import rasterize

GAUSSIAN_PARAMS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
"""splatfacto's per-Gaussian parameters, in its checkpoint as `gauss_params.<name>`."""
SH_C0 = 0.28209479177387814
"""The degree-0 SH basis: an SH coefficient difference times this is a colour difference."""
NEVER = 1 << 30
"""A step count no edit reaches (splatfacto's opacity reset switched off)."""


def area_downsample(image: Tensor, factor: int) -> Tensor:
    """An (H * factor, W * factor, C) image averaged over factor x factor blocks to (H, W, C)."""
    pooled = torch.nn.functional.avg_pool2d(image.permute(2, 0, 1)[None], factor)
    return pooled[0].permute(1, 2, 0)


@dataclass
class SkedSplatModelConfig(SplatfactoModelConfig, SkedOptions):
    """SKED on a splatfacto scene. Architecture fields (SH degree, rasterize mode, background, refinement
    thresholds) are copied from the base (base_scene.copy_base_architecture); the schedules and the fields below are
    the edit's (base_scene.EDIT_OWNED_FIELDS)."""

    _target: Type = field(default_factory=lambda: SkedSplatModel)
    # keep_threshold, num_seeds, seed_opacity, seed_size: SkedOptions (typeable on `ns-train sked` for any base).
    reset_alpha_every: int = 0
    """splatfacto's opacity reset every this many refinements; 0 = never (an edit starts from a trained base:
    a reset would fade every editable base Gaussian at once)."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Edits keep the base's cameras."""


SPLATFACTO_RATES = {"means": 1.6e-4, "scales": 0.005, "quats": 0.001, "features_dc": 0.0025,
                    "features_rest": 0.0025 / 20, "opacities": 0.05}
"""splatfacto's Adam learning rates of the six Gaussian groups, sized for 30,000-step runs."""
FORMATION_SHARE = 1.0 / 3.0
"""Under the edit's rates a seed can cross each of its ranges (seed_ranges) in this share of the edit's iterations."""
MIN_FORMATION_STEPS = 30
"""... but in no fewer steps than this: wider steps are noisier (hat, 100 iterations: 3.5x these rates 8.6 dB in
the changed region vs 12.2) and jolt the editable base Gaussians (a 6-iteration edit at a floor of 10 steps: PSNR
outside the sketches 20.5 dB)."""
OPAQUE = 0.99
"""The opacity a seed of the new part must be able to reach."""


def seed_ranges(seed_opacity: float) -> Dict[str, float]:
    """How far a seed's parameters must move to become part of the new content: its opacity logit from seed_opacity
    to opaque, its SH DC coefficient from grey to a saturated colour (0.5 / SH_C0), its log size by a factor of 4."""
    logit = lambda p: math.log(p / (1.0 - p))  # noqa: E731
    return {"opacities": max(logit(OPAQUE) - logit(seed_opacity), 0.0), "features_dc": 0.5 / SH_C0,
            "scales": math.log(4.0)}


def edit_rates(iterations: int, seed_opacity: float) -> Dict[str, float]:
    """The edit's Adam learning rates. Adam moves a parameter by about its rate a step, so splatfacto's rates, sized
    for 30,000 steps, leave a 500-step edit's seeds a faint grey haze (a seed's opacity logit moves 0.05 a step,
    its colour 0.0025 / 0.28 of grey a step). Each rate lets a seed cross its range in FORMATION_SHARE of the edit,
    never under splatfacto's (a long edit gets splatfacto's); the other groups keep splatfacto's."""
    steps = max(FORMATION_SHARE * max(int(iterations), 0), MIN_FORMATION_STEPS)
    ranges = seed_ranges(seed_opacity)
    return {name: max(rate, ranges.get(name, 0.0) / steps) for name, rate in SPLATFACTO_RATES.items()}


def splat_optimizers(iterations: int, options: Optional[SkedOptions] = None) -> Dict[str, Dict]:
    """The optimisers of the six Gaussian groups: Adam at the edit's rates (edit_rates), or at splatfacto's with
    `--pipeline.model.splat-learning-rates splatfacto` (or no options); the means' rate decays 100x over the edit,
    as over a splatfacto run."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    if options is None or options.splat_learning_rates == "splatfacto":
        rates = dict(SPLATFACTO_RATES)
    else:
        rates = edit_rates(iterations, options.seed_opacity)
    return {name: {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
                   "scheduler": (ExponentialDecaySchedulerConfig(lr_final=lr / 100, max_steps=iterations)
                                 if name == "means" else None)}
            for name, lr in rates.items()}


class GaussianSet(torch.nn.Module):
    """Per-Gaussian tensors held as buffers: saved with the model and moved by `.to()`, never optimised."""

    def __init__(self, tensors: Dict[str, Tensor]):
        super().__init__()
        for name, value in tensors.items():
            self.register_buffer(name, value)

    def __getitem__(self, name: str) -> Tensor:
        return getattr(self, name)

    def tensors(self) -> Dict[str, Tensor]:
        return dict(self.named_buffers())

    def assign(self, tensors: Dict[str, Tensor]) -> None:
        for name, value in tensors.items():
            setattr(self, name, value)  # a registered buffer's name: replaces the buffer


def base_gaussians(state: Dict[str, Tensor], checkpoint: Path, sh_degree: int) -> Dict[str, Tensor]:
    """The base scene's Gaussians from a model state: a splatfacto run's `gauss_params`, or an earlier SKED splat
    edit's kept and editable sets together (progressive editing)."""
    missing = [name for name in GAUSSIAN_PARAMS if f"gauss_params.{name}" not in state]
    if missing:
        raise SkedUserError(f"{checkpoint}: holds no splatfacto Gaussians (no gauss_params.{missing[0]}). "
                            "Point --load-dir at a splatfacto run.")
    gaussians = {name: state[f"gauss_params.{name}"].float() for name in GAUSSIAN_PARAMS}
    if "kept.means" in state:  # an earlier edit: its kept Gaussians are part of the scene
        gaussians = {name: torch.cat([state[f"kept.{name}"].float(), gaussians[name]]) for name in GAUSSIAN_PARAMS}
    count = len(gaussians["means"])
    rest = num_sh_bases(sh_degree) - 1
    shapes = {"means": (count, 3), "scales": (count, 3), "quats": (count, 4), "features_dc": (count, 3),
              "features_rest": (count, rest, 3), "opacities": (count, 1)}
    wrong = [f"{name} {tuple(value.shape)} (expected {shapes[name]})" for name, value in gaussians.items()
             if tuple(value.shape) != shapes[name]]
    if wrong:
        raise SkedUserError(f"{checkpoint}: the base's Gaussians do not fit its config (SH degree {sh_degree}): "
                            f"{', '.join(wrong)}.")
    return gaussians


def gaussian_colours(gaussians: Dict[str, Tensor], camera_centre: Tensor, sh_degree: int) -> Tensor:
    """(N, 3) colours towards one camera: splatfacto's SH (gsplat's, clamp_min(rgb + 0.5, 0)) or sigmoid colours."""
    if sh_degree == 0:
        return torch.sigmoid(gaussians["features_dc"])
    from gsplat.cuda._torch_impl import _spherical_harmonics  # the torch twin of gsplat's kernel: any device

    coefficients = torch.cat([gaussians["features_dc"][:, None], gaussians["features_rest"]], dim=1)
    rgb = _spherical_harmonics(sh_degree, gaussians["means"] - camera_centre, coefficients)
    return torch.clamp_min(rgb + 0.5, 0.0)


def splat_preservation_loss(params: Dict[str, Tensor], reference: Dict[str, Tensor], weight: Tensor,
                            lambda_colour: float, sh_degree: int) -> Tensor:
    """L_pres for Gaussians: mean_i w_i [ (o_i - o_i^base)^2 + lambda_c ||c_i - c_i^base||^2 + |mu_i - mu_i^base|^2 /
    s_i^base^2 + ||log s_i - log s_i^base||^2 + 1 - <q_i, q_i^base>^2 ] over the Gaussians with a base value
    (weight 0 elsewhere). Opacity and colour as rendered (activated), position in units of the base Gaussian's size."""
    f = lambda name: params[name].float()  # noqa: E731
    r = lambda name: reference[name].float()  # noqa: E731
    opacity = (torch.sigmoid(f("opacities")) - torch.sigmoid(r("opacities"))).pow(2).sum(dim=-1)
    if sh_degree == 0:
        colour = (torch.sigmoid(f("features_dc")) - torch.sigmoid(r("features_dc"))).pow(2).sum(dim=-1)
    else:
        colour = SH_C0**2 * ((f("features_dc") - r("features_dc")).pow(2).sum(dim=-1)
                             + (f("features_rest") - r("features_rest")).pow(2).sum(dim=(-2, -1)))
    size = torch.exp(r("scales")).mean(dim=-1).clamp_min(1e-4)  # a degenerate base Gaussian must not blow it up
    position = (f("means") - r("means")).pow(2).sum(dim=-1) / size.pow(2)
    scale = (f("scales") - r("scales")).pow(2).sum(dim=-1)
    alignment = (torch.nn.functional.normalize(f("quats"), dim=-1, eps=1e-12)
                 * torch.nn.functional.normalize(r("quats"), dim=-1, eps=1e-12)).sum(dim=-1)
    rotation = (1.0 - alignment.pow(2)).clamp_min(0.0)  # rounding must not make it negative
    per_gaussian = weight.float() * (opacity + lambda_colour * colour + position + scale + rotation)
    count = (weight > 0).sum().clamp_min(1)
    return per_gaussian.sum() / count


class SkedSplatModel(SkedEdit, SplatfactoModel):
    """Kept Gaussians (buffers) + editable Gaussians (splatfacto's parameters) + frozen base + sketches + guidance."""

    config: SkedSplatModelConfig
    PHOTOS_AS_IMAGES = True
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
        seeds = self._seed_gaussians(base)
        editable = {name: torch.cat([base[name][~kept], seeds[name]]) for name in GAUSSIAN_PARAMS}
        self.kept = GaussianSet({name: base[name][kept].clone() for name in GAUSSIAN_PARAMS})
        self.gauss_params = torch.nn.ParameterDict({name: Parameter(value.clone()) for name, value in editable.items()})
        from_base = torch.cat([torch.ones(int((~kept).sum()), dtype=torch.bool),
                               torch.zeros(len(seeds["means"]), dtype=torch.bool)])
        # L_pres's targets, one per editable Gaussian; follow it through densification (_follow_densification).
        self.reference = GaussianSet({**{name: value.clone() for name, value in editable.items()}, "from_base": from_base})
        # Plain attribute: never optimised or saved. Kept first, as the edit renders them, so that an unchanged edit
        # renders bit-identically to it (the compositor's sums depend on the order of equal-depth Gaussians' blocks).
        self.frozen_gaussians: Dict[str, Tensor] = {name: torch.cat([base[name][kept], base[name][~kept]])
                                                    for name in GAUSSIAN_PARAMS}
        self.strategy = self._strategy()
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        self._step_infos: List[Dict] = []
        self._photo_pixels: Dict[Tuple, Tensor] = {}

    def _read_base(self) -> Dict[str, Tensor]:
        checkpoint = self.config.base_checkpoint
        if checkpoint is None:
            raise ValueError("No base checkpoint: run `ns-train sked --load-dir <splatfacto run>`.")
        return base_gaussians(read_model_state(Path(checkpoint)), Path(checkpoint), self.config.sh_degree)

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

    @torch.no_grad()
    def _seed_gaussians(self, base: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Grey, nearly transparent, isotropic Gaussians spread uniformly over the sketches' visual hull (where every
        view's mask agrees), sized to their spacing. None when carving (nothing new is made)."""
        count = 0 if is_carving(self.config) else max(int(self.config.num_seeds), 0)
        low = torch.as_tensor(self.edit_box.min, dtype=torch.float32)
        high = torch.as_tensor(self.edit_box.max, dtype=torch.float32)
        generator = torch.Generator().manual_seed(0)  # the same seeds for every load of the edit
        found, drawn, hits = [], 0, 0
        while count > 0 and hits < count and drawn < 64 * count:
            points = low + torch.rand((4 * count, 3), generator=generator) * (high - low)
            inside = points[self.in_sketch_hull(points)]
            found.append(inside)
            drawn, hits = drawn + len(points), hits + len(inside)
        points = torch.cat(found)[:count] if found else torch.zeros((0, 3))
        if count > 0 and len(points) == 0:
            warnings.warn("The sketches' visual hull is empty at the sampled points: no Gaussians are seeded for new "
                          "content, so the edit can only reshape the base's Gaussians near the sketches.", stacklevel=2)
        n = len(points)
        hull_volume = float(torch.prod(high - low)) * hits / max(drawn, 1)
        spacing = (hull_volume / max(n, 1)) ** (1.0 / 3.0)
        size = max(spacing * self.config.seed_size, 1e-6)
        return {
            "means": points,
            "scales": torch.full((n, 3), math.log(size)),
            "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
            "features_dc": torch.zeros((n, 3)),  # grey: SH 0 -> 0.5, and sigmoid(0) = 0.5 without SH
            "features_rest": torch.zeros((n, base["features_rest"].shape[1], 3)),
            "opacities": torch.full((n, 1), math.log(self.config.seed_opacity / (1 - self.config.seed_opacity))),
        }

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
                width, height, render_mode="RGB+ED" if depth else "RGB", absgrad=self.strategy.absgrad,
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

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """SKED's step, and splatfacto's two: the step and optimizers before, densification after each iteration."""
        return [
            self.sked_step_callback(),
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb,
                             args=[training_callback_attributes.optimizers]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.step_post_backward),
        ]

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

    def load_state_dict(self, state_dict, strict: bool = True, **kwargs):  # type: ignore[override]
        """A saved edit's Gaussian counts differ from a fresh one's (densification): resize, then load. Parameters
        are resized in place, so the optimisers (set up before a resumed run loads) keep holding them."""
        for name, parameter in self.gauss_params.items():
            key = f"gauss_params.{name}"
            if key in state_dict:
                parameter.data = torch.zeros_like(state_dict[key], dtype=parameter.dtype, device=parameter.device)
        for prefix, holder in (("kept.", self.kept), ("reference.", self.reference)):
            holder.assign({name: torch.zeros_like(state_dict[prefix + name], device=value.device)
                           for name, value in holder.tensors().items() if prefix + name in state_dict})
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        self._step_infos = []
        return torch.nn.Module.load_state_dict(self, state_dict, strict=strict, **kwargs)

    # ---- one iteration --------------------------------------------------------------------
    def get_sked_loss_dict(self, data: Dict, step: int) -> Tuple[Dict[str, Tensor], Dict[str, Tensor], Dict[str, Tensor]]:
        """All losses of one iteration from the datamanager's `next_sked` dict; returns (outputs, losses, metrics)."""
        config = self.config
        losses: Dict[str, Tensor] = {}
        metrics: Dict[str, Tensor] = {}
        self._step_infos = []
        background = self._get_background_color()  # one per step: the edit and the base on the same one
        camera = data["random_view_camera"]
        view = self._render_supersampled(camera, background, channel="editable")

        reference = self.reference.tensors()
        weight = self.preservation_weight(reference["means"])[:, 0] * reference["from_base"].float()
        losses["preservation_loss"] = config.effective_lambda_pres * splat_preservation_loss(
            dict(self.gauss_params), reference, weight, config.lambda_colour, config.sh_degree)
        losses["sparsity_loss"] = config.lambda_sp * sparsity_loss(view["accumulation"])
        if is_carving(config):
            # No prompt: empty the sketched region (each editable Gaussian's opacity -> 0 where w is small).
            free = 1.0 - self.preservation_weight(self.gauss_params["means"])[:, 0]
            log_empty = -torch.nn.functional.softplus(self.gauss_params["opacities"].float()[:, 0])  # log(1 - o)
            losses["carve_loss"] = config.lambda_carve * (free * -log_empty).mean() if len(free) else free.sum()
        else:
            image = view["rgb"].permute(2, 0, 1)[None]
            base_image = lambda: self._render_supersampled(  # noqa: E731
                camera, background, base=True)["rgb"].permute(2, 0, 1)[None]
            losses.update(self.guidance_losses(image, data["random_camera"], base_image, step,
                                               samples_per_side=max(int(config.splat_supersampling), 1)))
            if config.effective_lambda_sil > 0 and data.get("sketch_views"):
                opacities, masks = [], []
                for sketch_camera, mask in data["sketch_views"]:
                    sketch = self._render_edit(sketch_camera, background, channel="editable")
                    opacity = sketch["extra"] if config.silhouette_opacity == "editable" else sketch["accumulation"]
                    opacities.append(opacity.reshape(-1))
                    masks.append(mask.reshape(-1).to(opacity))
                sil_losses, sil_metrics = self.silhouette_losses(torch.cat(opacities), torch.cat(masks))
                losses.update(sil_losses)
                metrics.update(sil_metrics)
            else:
                losses["silhouette_loss"] = torch.zeros((), device=self.device)
        photo = data.get("photo_view")
        if photo is not None and config.effective_lambda_photo > 0:
            self._photo_anchor(photo, background, losses, metrics)
        metrics["mean_preservation_weight"] = weight.sum() / reference["from_base"].sum().clamp_min(1)
        metrics["editable_gaussians"] = torch.tensor(float(len(self.gauss_params["means"])))
        metrics["kept_gaussians"] = torch.tensor(float(len(self.kept["means"])))
        self.finite_check(losses, metrics)
        return view, losses, metrics

    def _photo_anchor(self, photo: Dict, background: Tensor, losses: Dict[str, Tensor],
                      metrics: Dict[str, Tensor]) -> None:
        """MSE to one of the base's training photos at its pixels whose ray never comes near the editable region."""
        if not self._photos_checked:
            # Judged at the photo's own resolution, the base's: far below it a render point-samples Gaussians the
            # downscaled photo averages over, and the base's own photos would score as another scene's.
            with torch.no_grad():
                native = self._anchored_pixels(photo["native"]() if "native" in photo else photo, None, background)
            if native is None or not self.check_photos_once(*native[:2]):
                return
        anchored = self._anchored_pixels(photo, photo.get("index"), background)
        if anchored is not None:
            predicted, truth, safe = anchored
            losses["photo_loss"] = self.config.effective_lambda_photo * torch.nn.functional.mse_loss(
                predicted.float(), truth.float())
            metrics["photo_rays_kept"] = safe.float().mean()

    def _anchored_pixels(self, photo: Dict, index: Optional[int],
                      background: Tensor) -> Optional[Tuple[Tensor, Tensor, Tensor]]:
        """(the edit's render, the photo) at the photo's pixels whose ray keeps away from the editable region, and
        which pixels those are; None if there is none. `index` caches the pixels per photo."""
        camera, image = photo["camera"], photo["image"].to(self.device)
        safe = self._photo_pixels_kept(camera, index)
        if not safe.any():
            return None
        outputs = self._render_edit(camera, background)
        if image.dtype == torch.uint8:
            image = image.float() / 255.0
        truth = self.composite_with_background(image.float(), background)
        return outputs["rgb"][safe], truth[safe], safe

    @torch.no_grad()
    def _photo_pixels_kept(self, camera: Cameras, index: Optional[int]) -> Tensor:
        """(H, W) which pixels' rays keep away from the editable region; cached per photo while beta stays."""
        key = (index, self.config.beta, self.config.photo_threshold, int(camera.width.reshape(-1)[0]))
        if index is None or key not in self._photo_pixels:
            rays = camera.generate_rays(camera_indices=0, keep_shape=True).to(self.device)
            origins, directions = rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3)
            nears = torch.zeros(len(origins), 1, device=self.device)
            fars = torch.full((len(origins), 1), 1e10, device=self.device)
            safe = rays_away_from_edit(origins, directions, nears, fars, self.editable_box(),
                                       lambda p: self.preservation_weight(p)[..., 0], self.config.photo_threshold)
            self._photo_pixels[key] = safe.reshape(rays.origins.shape[:-1])
        return self._photo_pixels[key]

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

    def get_image_metrics_and_images(self, outputs, batch):
        """splatfacto's evaluation images and PSNR/SSIM, without LPIPS."""
        background = outputs["background"]
        background = background[0, 0] if background.dim() == 3 else background
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), background)
        predicted = outputs["rgb"]
        gt_chw, predicted_chw = gt.permute(2, 0, 1)[None], predicted.permute(2, 0, 1)[None]
        metrics = {"psnr": float(self.psnr(gt_chw, predicted_chw).item()),
                   "ssim": float(self.ssim(gt_chw, predicted_chw)), "gaussian_count": float(self.num_points)}
        images = {"img": torch.cat([gt, predicted], dim=1), "accumulation": outputs["accumulation"]}
        if "preservation_weight" in outputs:
            images["preservation_weight"] = outputs["preservation_weight"]
        return metrics, images
