"""SKED's settings, shared by every edit model (nerfacto, instant-ngp, splats), and their checks.

Imports no model code: the base-scene reader and the trainer need these settings before any
model is built.
"""

from __future__ import annotations

import contextlib
import copy
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Dict, FrozenSet, List, Literal, Optional

from sked_ns.errors import SkedWarning
from sked_ns.guidance import GuidanceChoice, StableDiffusionGuidanceConfig

if TYPE_CHECKING:
    from sked_ns.sketches.sketch_set import SketchSet


AUTO_FIELD_CHUNK = -1
"""`field_chunk` chosen by the memory plan (engine/memory_plan.choose_field_chunk)."""
CHECKPOINTED_FIELD_CHUNK = 65536
"""The chunk the plan falls back to where an unchunked step does not fit: a few hundred MB of activations."""


@dataclass
class SkedOptions:
    """SKED's settings, shared by every edit model."""

    EDIT_OWNED: ClassVar[FrozenSet[str]] = frozenset({
        "_target",  # the SKED model class
        "prompt",  # nerfstudio's ModelConfig has one too: the edit's prompt is SKED's
        "eval_num_rays_per_chunk",  # a rendering setting of this run
        "camera_optimizer",  # the edit keeps the base's cameras; the base's mode goes to base_camera_optimizer
    })
    """Fields of the model config the edit decides, not the base (each representation adds its own); every other
    field of the base's model config is its architecture, copied by `copy_base_architecture`."""

    sketches: Optional[Path] = None
    """Sketch-set folder (sketches.json + PNG masks); `ns-train sked --sketches` sets it."""
    prompt: Optional[str] = None
    """What should be in the sketched region; none with Stable Diffusion guidance = carve it away."""
    base_checkpoint: Optional[Path] = None
    """The base's step-*.ckpt; filled in from --load-dir."""
    base_kept: Optional[Path] = None
    """The edit's own copy of that checkpoint's weights (`<edit run>/base/`), which every load of the edit
    reads (no later write to the base run changes the edit); set when the edit starts."""
    base_digest: Optional[str] = None
    """The SHA-256 of that copy, checked whenever the edit loads; set with it."""
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
    thresholded at occupancy_threshold (which sharpens a soft base; docs/method.md, L_pres)."""
    lambda_sil: float = 1.0
    """Weight of L_sil."""
    silhouette_normalisation: Literal["image", "sketch"] = "image"
    """L_sil per image pixel (paper) or per sketch pixel ("sketch": scaled so a sketch covering 5% of its frame
    weighs the same; a sketch covering less pulls harder than under the paper's)."""
    colour_residual: bool = True
    """Give new content its own colour capacity near the sketches (colour_residual.py): a colour the base never shows
    is reached without moving the colour MLP everything kept shares. False: the paper's model. Ignored by a
    local-residual NeRF edit, whose residual moves colours itself."""
    silhouette_opacity: Literal["editable", "any"] = "editable"
    """What L_sil asks to be opaque along a sketch ray: content near the sketches (opacity weighted by 1 - w), so a
    wall or table behind the sketch does not fill it before anything is made; "any" is the paper's (all opacity,
    right for a base with an empty background)."""
    lambda_sp: float = 5e-4
    """Weight of the sparsity (accumulation entropy) loss."""
    lambda_new_mass: float = 0.0
    """Weight of L_new (losses.new_mass_loss; NeRF bases): the opacity the edit adds over the base near the sketches,
    counted only where every sketch ray through a point already holds more than 0.9 of new opacity (or off the
    sketches: hull_carving.SketchRayOpacity), so a two-view visual hull is carved once filled, not before the part
    forms. 0 (default): the paper's losses (docs/benchmarks.md, Edit quality, says where it was measured)."""
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
    field_chunk: int = -1
    """NeRF bases: field samples evaluated per gradient-checkpointed chunk while training (models/nerf/chunked.py):
    a chunk keeps only its inputs and outputs until the backward pass evaluates it again, which cuts the NeRF side
    of a step several times over, at one more forward pass of the fields and a call per chunk (docs/benchmarks.md).
    -1 (default): chosen before training by the memory plan, none where the step fits the device, else 65536.
    0: no checkpointing (fastest, most memory)."""
    lambda_photo: float = 1.0
    """Weight of the base-photo anchor (photo_anchor.py): the base's training photos, at rays that never come
    near the editable region, keep the edit as the base was trained. 0: the paper's losses only. NeRF bases hold
    such rays exactly already (keep_threshold), so there it acts only if keep_threshold is above photo_threshold."""
    photo_threshold: float = 0.99
    """A photo ray anchors the edit only if every point on it has a preservation weight above this."""
    base_camera_optimizer: Literal["off", "SO3xR3", "SE3"] = "off"
    """The base's camera optimisation (copied from it): its learnt pose corrections are applied to photo rays."""
    ablation: Literal["none", "no-preserve", "no-silhouette", "text-only"] = "none"
    """The paper's ablations: drop L_pres, drop L_sil, or both (text only: the sketches only aim the views)."""
    keep_threshold: float = 0.99
    """What is far from the sketches is kept exactly: NeRF samples with a preservation weight above this take the frozen
    base's density and colour (held_field.py; the editable field is trained only at the others), and splat bases'
    Gaussians whose centre's weight is above it are never optimised, densified, pruned or reset. The rest is held to
    the base by L_pres. 1 holds nothing exactly: the paper's soft L_pres alone."""
    nerf_edit_field: Literal["local", "local-residual", "full-copy"] = "local"
    """NeRF bases: what the edit trains. "local": the base's own networks over the box the edit may change, a grid of
    changes to its hash features and copies of its MLPs (models/nerf/local_field.py); its checkpoint holds those
    alone. "local-residual": a residual on the base's outputs over that box, which fills more slowly; an edit of a
    local edit is one (its base's outputs are all it has). "full-copy", and "local" on a base whose grid and MLP
    tiny-cuda-nn fuses: a trainable copy of the whole field and proposal networks (the paper's model). An edit
    resumes and loads as it was saved."""
    # Gaussian-splat bases only (models/splat/model.py); here so `ns-train sked` can parse them for any base.
    num_seeds: int = 3000
    """Splats: new Gaussians seeded inside the sketches' visual hull for new content (none when carving), each as wide
    as their spacing (seed_size). With supersampled training renders more seeds give a sharper part, at more memory
    and time (docs/benchmarks.md); densification adds more where the edit runs long enough."""
    seed_opacity: float = 0.005
    """Splats: opacity of the seeds at the start: nearly transparent, but above the rasterizer's 1/255 cut-off, under
    which a Gaussian is skipped and gets no gradient."""
    seed_size: float = 1.0
    """Splats: seed scale (standard deviation) relative to their mean spacing: at 1 neighbouring seeds overlap, so
    the hull starts as one continuous (transparent) medium."""
    splat_learning_rates: Literal["edit", "splatfacto"] = "edit"
    """Splats: the Gaussians' Adam rates. "edit": sized to the edit's length, so that a seed can turn opaque, take any
    colour and change its size 4x within a third of the iterations (models/splat/rates.py); "splatfacto":
    splatfacto's own, sized for 30,000-step runs (a 500-step edit's seeds stay a faint grey haze)."""
    splat_supersampling: int = 4
    """Splats: the random view (and the base render the guidance compares it with) is rendered at this many times its
    resolution and averaged down to it, so that a Gaussian's footprint between two pixel centres is fitted too (1: one
    sample a pixel, under which a seed fitted at a small render shows as a soft blob from other views; measured in
    docs/benchmarks.md). The sketch views keep one: L_sil averaged over a pixel would fill the sketch's edge pixels."""

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
    import torchmetrics.image.lpip as lpip_module  # here, not at import: every ns-* command imports this module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: None
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


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
    if getattr(config, "edit_box_density", None) == 0 and config.nerf_edit_field == "local" and config.prompt:
        messages.append("edit_box_density = 0 on a local edit: its proposals are the base's, so nothing new is ever "
                        "sampled or rendered; use --pipeline.model.nerf-edit-field full-copy to edit without it.")
    for view in sketch_set.views:
        covered = float(view.mask.mean())
        if covered > 0.9:
            messages.append(f"{view.name or 'a sketch view'}: the mask covers {covered:.0%} of the image, so almost "
                            "nothing in that view is preserved.")
    for message in messages:
        warnings.warn(message, SkedSettingsWarning, stacklevel=2)
    return messages


class SkedSettingsWarning(SkedWarning):
    """A setting that runs but defeats the method."""


def copy_base_architecture(target: SkedOptions, base_model_config) -> None:
    """Make the edit's model the base's shape: every field of the base's model config but the edit's own."""
    owned = type(target).EDIT_OWNED | {option.name for option in fields(SkedOptions)}
    ours = {f.name for f in fields(target)}
    for name in (f.name for f in fields(base_model_config)):
        if name in ours and name not in owned:
            setattr(target, name, copy.deepcopy(getattr(base_model_config, name)))
    cameras = getattr(base_model_config, "camera_optimizer", None)
    target.base_camera_optimizer = getattr(cameras, "mode", "off") if cameras is not None else "off"
    if getattr(base_model_config, "nerf_edit_field", None) in ("local", "local-residual"):  # a local edit as the base:
        target.nerf_edit_field = "local-residual"  # it saved its changes alone: no whole field or grid to copy


def taken_from_the_base(config_class: type, base_class: type) -> None:
    """Hide from `ns-train sked --help` and its parser the fields the edit copies from the base's config
    (`copy_base_architecture`): typed, they would be overwritten without a word. Marks them tyro.conf.Suppress in
    the class's annotations, which only the command line reads (config.yml and the dataclass stay as they are)."""
    from typing import Annotated, get_type_hints

    import tyro

    hints = get_type_hints(base_class, include_extras=True)
    owned = config_class.EDIT_OWNED | {option.name for option in fields(SkedOptions)}
    for base_field in fields(base_class):
        if base_field.name not in owned and not base_field.name.startswith("_") and base_field.name in hints:
            config_class.__annotations__[base_field.name] = Annotated[hints[base_field.name], tyro.conf.Suppress]
    # A field both define is SKED's (e.g. the prompt): its help is SKED's, not nerfstudio's first-found docstring.
    ours, helps = get_type_hints(SkedOptions, include_extras=True), field_helps(SkedOptions)
    for option in fields(SkedOptions):
        if option.name in hints and helps.get(option.name):
            config_class.__annotations__[option.name] = Annotated[ours[option.name],
                                                                  tyro.conf.arg(help=helps[option.name])]
    # The edit keeps the base's cameras (base_camera_optimizer): none to choose; the base's copy is made at the start.
    hidden = {"camera_optimizer": hints, "base_kept": ours, "base_digest": ours}
    for name, types in hidden.items():
        if name in types:
            config_class.__annotations__[name] = Annotated[types[name], tyro.conf.Suppress]


def field_helps(config_class: type) -> Dict[str, str]:
    """Each dataclass field's docstring in its class's source (what tyro shows as its help), as one line."""
    import ast
    import inspect
    import textwrap

    body = ast.parse(textwrap.dedent(inspect.getsource(config_class))).body[0].body
    return {statement.target.id: " ".join(str(following.value.value).split())
            for statement, following in zip(body, body[1:])
            if isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)
            and isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)}
