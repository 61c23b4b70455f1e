"""The memory an edit will need, planned before training: printed, and checked against the device.

A model of what benchmarks/memory.py measures (docs/benchmarks.md, Memory), part by part:

- resident: the editable copy of the base, the frozen base and Adam's two moments (about 4x the
  base's weights as its checkpoint holds them), and their gradients during the step (1x more); a local NeRF
  edit (local_field.py) trains its residual alone, beside the base's modules held frozen (as loaded, and the
  frozen base: benchmarks/edit_size.py measures them), and only the residual's gradients come in the step;
- the NeRF side of a step: what each ray rendered with gradients keeps for the backward pass (the
  random view, the sketch views at their L_sil size, photo rays), plus one gradient-checkpointed chunk's
  activations, or every sample's activations when chunking is off; a splat edit's side per rendered pixel;
- Stable Diffusion: the UNet's and VAE encoder's weights, counted from the checkpoint's files at the
  dtype they run in (fp16 on CUDA), and its step (VAE encode with its backward, the UNet with classifier-
  free guidance), which grows with the image side squared.

The step's peak is the larger of the NeRF side's own peak and what it holds when the guidance runs
plus the guidance's step. The coefficients below are benchmarks/memory.py's measurements (fp32, CPU,
torch hash grids) divided out, a local NeRF edit's step from its own run where measured;
tests/engine/test_memory_plan.py checks the plan against their results files.
The plan also says roughly how long a step will take there (engine/step_time.py), from the same work.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from sked_ns.engine.step_time import StepTime, slow_step_warning, step_time
from sked_ns.engine.trained_weights import is_local, trained_bytes
from sked_ns.engine.weight_bytes import checkpoint_weight_bytes
from sked_ns.errors import SkedUserError, warn
from sked_ns.guide import guide
from sked_ns.models.registry import representation_named, representation_of

GB = 2**30


@dataclass(frozen=True)
class StepModel:
    """Bytes of one representation's side of a step, per unit of work."""

    kept_per_ray: float
    """Kept for the backward pass per random-view ray (nerfacto: at its default samples per ray), fields
    checkpointed; splats: per rendered pixel."""
    activation_per_ray: float
    """Per ray without checkpointing (every field activation, at the step's peak); splats: what the backward pass
    adds per rendered pixel."""
    activation_per_sample: float
    """One field sample's activations: what a checkpointed chunk re-creates in the backward pass."""
    samples_per_ray: float
    """The samples per ray the per-ray figures were measured at (nerfacto: its proposals' and field's)."""
    resident_per_weight_byte: float = 4.0
    """The edit's resident tensors per byte of the base's weights: the editable copy, the frozen base, Adam's two
    moments, and what the edit adds (nerfacto's colour residual grid)."""
    local_resident_per_weight_byte: float = 0.0
    """A local NeRF edit's resident tensors per byte of the base's weights, its residual apart: the base's modules as
    loaded and frozen, neither trained (benchmarks/edit_size.py's `resident_bytes`)."""
    kept_per_sketch_ray: Optional[float] = None
    """Per sketch-view (or photo) ray when it differs from a random-view ray's: instant-ngp samples only occupied
    cells, and random views frame the edit while sketch views show the whole scene. None: as a random-view ray."""
    activation_per_sketch_ray: Optional[float] = None
    """Without checkpointing, per sketch-view ray where it differs (instant-ngp, as above)."""
    kept_per_weight_byte: float = 0.0
    step_per_weight_byte: float = 0.0
    """Splats: held at the guidance, and added by the rest of the step, per byte of the base's Gaussians (the
    rasterizer's per-Gaussian work)."""


STEP_MODELS: Dict[str, StepModel] = {
    "nerfacto": StepModel(kept_per_ray=21443, activation_per_ray=471768, activation_per_sample=8087, samples_per_ray=400,
                          resident_per_weight_byte=4.502, local_resident_per_weight_byte=1.811),
    # instant-ngp's samples per ray follow its occupancy grid (the scene); 16 or more fill a chunk at any step's rays.
    "instant-ngp": StepModel(kept_per_ray=5115, activation_per_ray=46529, activation_per_sample=7300, samples_per_ray=16,
                             kept_per_sketch_ray=16266, activation_per_sketch_ray=393534,
                             resident_per_weight_byte=4.251, local_resident_per_weight_byte=2.721),
    "splatfacto": StepModel(kept_per_ray=76.02, activation_per_ray=19.13, activation_per_sample=0.0, samples_per_ray=1,
                            kept_per_weight_byte=6.274, step_per_weight_byte=379.5, resident_per_weight_byte=5.498),
}

LOCAL_STEP_MODELS: Dict[str, StepModel] = {
    # A local field's chunk re-creates its own small grid's and MLPs' activations in the backward pass, not a whole
    # copy's (memory_{nerfacto,ngp}_local_field.json); unchunked (not measured) as the whole copy's: above.
    "nerfacto": replace(STEP_MODELS["nerfacto"], kept_per_ray=20506, activation_per_sample=5115),
    "instant-ngp": replace(STEP_MODELS["instant-ngp"], kept_per_ray=5468, kept_per_sketch_ray=10462,
                           activation_per_sample=5053),
}
"""Where a local NeRF edit's step differs from a whole copy's (the plan falls back to STEP_MODELS)."""

SEED_BYTES = 59 * 4 * 3
"""A splat edit's new Gaussian: 59 floats (position, scale, rotation, opacity, 16 SH colours), with Adam's moments."""
SD_STEP_BYTES_AT_512 = 3.449e9
"""Stable Diffusion v1.x's guidance step (VAE encode with backward, UNet batch 2) at a 512 px input, fp32."""
VAE_CHECKPOINTING_SHARE = 0.7083
"""The guidance step with the VAE encoder's gradient checkpointing, as a share of it without."""


@dataclass
class MemoryPlan:
    """Expected bytes of an edit on its device, by part."""

    device: str
    resident: float
    nerf_step: float
    held_at_guidance: float
    sd_weights: float = 0.0
    sd_step: float = 0.0
    sd_device: Optional[str] = None
    """Where Stable Diffusion runs when not on `device` (--pipeline.model.guidance.device)."""
    step_time: Optional[StepTime] = None
    """How long a step is expected to take, where a step was measured on this device kind."""

    @property
    def peak(self) -> float:
        """The training device's peak."""
        if self.sd_device is not None:
            return self.resident + self.nerf_step
        return self.resident + self.sd_weights + max(self.nerf_step, self.held_at_guidance + self.sd_step)

    def line(self) -> str:
        parts = f"the edit's model {self.resident / GB:.1f} GB, its step {self.nerf_step / GB:.1f} GB"
        if self.sd_weights:
            where = f" on {self.sd_device}" if self.sd_device else ""
            parts += (f"; Stable Diffusion{where} {self.sd_weights / GB:.1f} GB and its step {self.sd_step / GB:.1f} GB, "
                      "while the edit's render waits for it")
        return f"Expected peak memory on {self.device}: {self.peak / GB:.1f} GB ({parts})"


@dataclass(frozen=True)
class StepWork:
    """What one step renders with gradients."""

    rays: float
    """Rays of the random view (a splat edit: pixels of every render of the step)."""
    sketch_rays: float = 0.0
    """Rays of the sketch views under the masks at their L_sil size, and of the photo anchor (NeRF edits)."""
    sample_scale: float = 1.0
    """Samples per ray relative to those its StepModel was measured at."""
    chunk: int = 0
    """Field samples per checkpointed chunk (0: none)."""


def step_work(options, datamanager, representation: str) -> StepWork:
    from sked_ns.sketches.sketch_set import load_sketch_set, sketch_view_at, sketch_view_size

    row = representation_named(representation)
    random_view = float(options.guidance_resolution ** 2)
    views = load_sketch_set(options.sketches).views
    if row.renders == "cameras":  # the supersampled random view, the sketch views, a photo at the view's size
        sketch = float(sum(math.prod(sketch_view_size(view, options.silhouette_resolution)) for view in views))
        photo = random_view if options.effective_lambda_photo > 0 else 0.0
        return StepWork(random_view * max(int(options.splat_supersampling), 1) ** 2 + sketch + photo)
    photos = options.lambda_photo > 0 and options.keep_threshold > options.photo_threshold
    scale = float(options.samples_per_ray_scale)
    if row.samples_from_proposals:
        samples = options.num_nerf_samples_per_ray + sum(options.num_proposal_samples_per_ray)
        scale *= samples / STEP_MODELS[representation].samples_per_ray
    # A NeRF renders the sketch views only at the masks' pixels (L_sil counts nothing else).
    masked = float(sum(int(sketch_view_at(view, options.silhouette_resolution)[1].sum()) for view in views))
    return StepWork(random_view, masked + (datamanager.train_num_rays_per_batch if photos else 0), scale,
                    max(int(options.field_chunk), 0))


def field_samples(representation: str, work: StepWork) -> Optional[float]:
    """The NeRF field samples a step renders with gradients; None for a representation that renders cameras."""
    if representation_named(representation).renders == "cameras":
        return None
    return (work.rays + work.sketch_rays) * STEP_MODELS[representation].samples_per_ray * work.sample_scale


def nerf_side(representation: str, work: StepWork, base_bytes: float, trained: Optional[float] = None,
              local: bool = False) -> Tuple[float, float]:
    """(the side's own step peak, what it holds when the guidance runs), in bytes; the gradients of the trained
    weights (`trained`, `trained_bytes`; None: the base's, a whole copy) come in the backward pass. LOCAL: the edit
    trains a local field (trained_weights.is_local)."""
    model = LOCAL_STEP_MODELS.get(representation, STEP_MODELS[representation]) if local else STEP_MODELS[representation]
    trained = base_bytes if trained is None else trained
    if representation_named(representation).renders == "cameras":  # per pixel and per Gaussian: kept, and added
        held = work.rays * model.kept_per_ray + base_bytes * model.kept_per_weight_byte
        return held + work.rays * model.activation_per_ray + base_bytes * (model.step_per_weight_byte + 1), held
    rays = work.rays + work.sketch_rays
    if work.chunk <= 0:  # every activation kept: counted as held from the render on
        sketch = model.activation_per_ray if model.activation_per_sketch_ray is None else model.activation_per_sketch_ray
        held = (work.rays * model.activation_per_ray + work.sketch_rays * sketch) * work.sample_scale
        return held + trained, held
    sketch = model.kept_per_ray if model.kept_per_sketch_ray is None else model.kept_per_sketch_ray
    held = (work.rays * model.kept_per_ray + work.sketch_rays * sketch) * work.sample_scale
    transient = min(work.chunk, rays * model.samples_per_ray * work.sample_scale) * model.activation_per_sample
    return held + transient + trained, held


def _safetensors_parameters(path: Path, prefixes: Tuple[str, ...] = ()) -> Optional[int]:
    """Parameters in a safetensors file (those whose names start with PREFIXES), from its header alone."""
    try:
        with open(path, "rb") as handle:
            (length,) = struct.unpack("<Q", handle.read(8))
            header = json.loads(handle.read(length))
    except (OSError, ValueError, struct.error):
        return None
    return sum(math.prod(entry["shape"]) for name, entry in header.items()
               if name != "__metadata__" and (not prefixes or name.startswith(prefixes)))


def _weights_file(folder: Path) -> Optional[Path]:
    from sked_ns.guidance.stable_diffusion import DIFFUSERS_WEIGHTS

    for name in DIFFUSERS_WEIGHTS[:2]:  # one file each (a sharded checkpoint's index is counted as fp32 below: none)
        if (folder / name).is_file():
            return folder / name
    return None


def sd_bytes(guidance, device_type: str) -> Tuple[float, float]:
    """(Stable Diffusion's weights on its device, its guidance step), in bytes; (0, 0) when the weights are not
    local (they are checked before this runs) or the guidance is another kind."""
    from sked_ns.guidance.stable_diffusion import StableDiffusionGuidanceConfig, checkpoint_folder

    if not isinstance(guidance, StableDiffusionGuidanceConfig):
        return 0.0, 0.0
    try:
        folder = checkpoint_folder(guidance.model)
    except SkedUserError:
        return 0.0, 0.0
    if folder is None:
        return 0.0, 0.0
    half = (guidance.device or device_type).startswith("cuda") and guidance.half_precision
    size = 2 if half else 4
    parameters = 0.0
    for part, prefixes in (("unet", ()), ("vae", ("encoder.", "quant_conv."))):
        path = _weights_file(folder / part)
        if path is None:
            continue
        count = _safetensors_parameters(path, prefixes) if path.suffix == ".safetensors" else None
        parameters += count if count is not None else path.stat().st_size / 4  # a .bin: fp32 as saved, decoder too
    step = SD_STEP_BYTES_AT_512 * (guidance.image_size / 512) ** 2 * size / 4
    if guidance.vae_checkpointing:
        step *= VAE_CHECKPOINTING_SHARE
    return parameters * size, step


def resident_bytes(representation: str, base_bytes: float, options) -> float:
    """What the edit holds between steps: its model and optimiser state (splats: the seeds too); a local NeRF edit,
    its base's modules frozen, and its residual with Adam's two moments of it."""
    from sked_ns.method.options import is_carving
    if is_local(representation, options):
        frozen = STEP_MODELS[representation].local_resident_per_weight_byte * base_bytes
        return frozen + 3.0 * trained_bytes(representation, base_bytes, options)
    seeds_new = representation_named(representation).seeds_new_gaussians and not is_carving(options)
    seeds = options.num_seeds * SEED_BYTES if seeds_new else 0.0
    return STEP_MODELS[representation].resident_per_weight_byte * base_bytes + seeds


def plan_edit(config) -> MemoryPlan:
    """The plan of an edit's config, after resolve_edit filled it in from the base."""
    from sked_ns.guidance.stable_diffusion import StableDiffusionGuidanceConfig
    from sked_ns.method.frozen_base import base_weights
    from sked_ns.method.options import is_carving

    options, machine = config.pipeline.model, config.machine
    representation = representation_of(options).name  # resolve_edit refused any other kind of base
    device = machine.device_type if machine.device_type != "cuda" else "cuda:0"
    weights = checkpoint_weight_bytes(base_weights(options))
    work = step_work(options, config.pipeline.datamanager, representation)
    step, held = nerf_side(representation, work, weights, trained_bytes(representation, weights, options),
                           is_local(representation, options))
    plan = MemoryPlan(device=device, resident=resident_bytes(representation, weights, options), nerf_step=step,
                      held_at_guidance=held)
    sd_size = sd_device_type = None
    if not is_carving(options):
        plan.sd_weights, plan.sd_step = sd_bytes(options.guidance, machine.device_type)
        sd_device = getattr(options.guidance, "device", None)
        if sd_device and sd_device != device and not (sd_device == "cuda" and device == "cuda:0"):
            plan.sd_device = sd_device
        if isinstance(options.guidance, StableDiffusionGuidanceConfig):
            sd_size, sd_device_type = options.guidance.image_size, (sd_device or machine.device_type).split(":")[0]
    plan.step_time = step_time(machine.device_type, field_samples(representation, work), sd_size, sd_device_type)
    return plan


_PRINTED: set = set()


def _free_bytes(device: str) -> Optional[float]:
    """Free memory of a CUDA device now, or what the kernel says a new process could use without swapping on the
    CPU; None where it cannot tell."""
    import torch

    if device == "cpu":
        return _available_host_bytes()
    if not device.startswith("cuda") or not torch.cuda.is_available():
        return None
    return float(torch.cuda.mem_get_info(torch.device(device))[0])


def options_that_fit(config, free: float) -> List[str]:
    """The flags, each on its own, under which the plan fits in FREE bytes, with their expected peaks."""
    import copy

    import torch

    from sked_ns.method.options import SkedOptions

    tries = []
    if torch.cuda.is_available() and torch.cuda.device_count() > 1 and hasattr(config.pipeline.model.guidance, "device"):
        tries.append(("--pipeline.model.guidance.device cuda:1", lambda c: setattr(c.pipeline.model.guidance, "device", "cuda:1")))
    default_seeds = SkedOptions.num_seeds
    if representation_of(config.pipeline.model).seeds_new_gaussians and config.pipeline.model.num_seeds > default_seeds:
        tries.append((f"--pipeline.model.num-seeds {default_seeds}",
                      lambda c: setattr(c.pipeline.model, "num_seeds", default_seeds)))
    tries += [
        ("--pipeline.model.guidance-resolution 64 --pipeline.model.silhouette-resolution 64 (or ns-train sked-fast)",
         lambda c: (setattr(c.pipeline.model, "guidance_resolution", 64), setattr(c.pipeline.model, "silhouette_resolution", 64))),
        ("--pipeline.model.field-chunk 16384", lambda c: setattr(c.pipeline.model, "field_chunk", 16384)),
        ("--pipeline.model.guidance.vae-checkpointing True",
         lambda c: setattr(c.pipeline.model.guidance, "vae_checkpointing", True)),
    ]
    fitting = []
    for flags, change in tries:
        trial = copy.deepcopy(config)
        try:
            change(trial)
        except AttributeError:
            continue
        peak = plan_edit(trial).peak
        if peak <= free:
            fitting.append(f"{flags} (about {peak / GB:.1f} GB)")
    return fitting


def _available_host_bytes() -> Optional[float]:
    """Memory the kernel says a new process could use without swapping (Linux); None elsewhere."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _free_swap_bytes() -> float:
    """Free swap (Linux; 0 elsewhere): a CPU edit may spill there, slowly, before it fails."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("SwapFree:"):
                    return float(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


UNCHUNKED_SHARE = 0.8
"""An unchunked step is chosen where the whole plan takes at most this share of the free memory."""


def choose_field_chunk(config, free: Optional[float]) -> int:
    """The field chunk of an edit whose config leaves it to the plan (-1): none (0) where the whole step fits in
    UNCHUNKED_SHARE of FREE bytes (one call per field, no re-run in the backward pass) or FREE is unknown, else the
    checkpointed chunk."""
    import copy

    from sked_ns.method.options import CHECKPOINTED_FIELD_CHUNK

    trial = copy.deepcopy(config)
    trial.pipeline.model.field_chunk = 0
    if free is None or plan_edit(trial).peak <= UNCHUNKED_SHARE * free:
        return 0
    return CHECKPOINTED_FIELD_CHUNK


def check_memory(config) -> MemoryPlan:
    """Choose the field chunk where the config leaves it to the plan; print the plan (and the step's expected time)
    once; refuse, before anything is written, an edit that cannot fit in the CUDA device's free memory (a CPU edit:
    available memory and swap), naming the options that would; warn a CPU edit that would swap, and a step expected to
    take minutes."""
    from sked_ns.method.options import AUTO_FIELD_CHUNK

    options = config.pipeline.model
    if getattr(options, "field_chunk", 0) == AUTO_FIELD_CHUNK:
        device = config.machine.device_type
        free = _free_bytes("cuda:0" if device == "cuda" else device)
        options.field_chunk = chosen = choose_field_chunk(config, free)
    else:
        chosen = None
    plan = plan_edit(config)
    line = plan.line()
    if chosen is not None:
        line += ("; fields unchunked (the step fits)" if chosen == 0 else
                 f"; fields in checkpointed chunks of {chosen} samples (an unchunked step would not fit)")
    line += f" (model: {guide('benchmarks.md')}, Memory)"
    if plan.step_time is not None:
        line += "\n" + plan.step_time.line(plan.device, config.max_num_iterations)
    if line not in _PRINTED:
        _PRINTED.add(line)
        print(line, flush=True)
    free = _free_bytes(plan.device)
    on_cpu = plan.device == "cpu"
    limit = free + _free_swap_bytes() if free is not None and on_cpu else free
    if limit is not None and plan.peak > limit:
        fitting = options_that_fit(config, limit)
        where = "this machine, which has" if on_cpu else f"{plan.device}, which has"
        available = "available (memory and swap)" if on_cpu else "free"
        raise SkedUserError(
            f"this edit needs about {plan.peak / GB:.1f} GB on {where} {limit / GB:.1f} GB {available}. "
            + (f"Options that fit: {'; '.join(fitting)}." if fitting else
               "None of the memory options fits alone: lower the settings that grow it (render sizes, seeds), or "
               "use a machine with more memory.")
            + f" ({guide('troubleshooting.md')}, Out of memory)")
    if on_cpu and free is not None and plan.peak > free:
        warn(f"this edit needs about {plan.peak / GB:.1f} GB, more than the {free / GB:.1f} GB of memory available "
             "now: it will swap, and run many times slower.")
    slow = plan.step_time and slow_step_warning(plan.step_time, config.machine.device_type)
    if slow:
        warn(slow)
    return plan
