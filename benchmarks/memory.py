"""Memory of one edit step, part by part, at the default settings: where the bytes go and what an 8 GB card needs.

    python benchmarks/memory.py                       # CPU: nerfacto, instant-ngp, splatfacto at 64 and 128 px
    python benchmarks/memory.py --device cuda         # on a GPU (gpu_check runs it): the same table
    python benchmarks/memory.py --sd tiny --bases nerfacto --resolutions 16   # a smoke run (a test runs it)

For each base kind (the demo scene fitted with the method's own architecture, torch hash grids)
and random-view size, a real `ns-train sked` edit is set up and one step measured with the
guidance replaced by a stand-in that hands the render an image gradient, as score distillation
does: the NeRF (or splat) side of the step. Its parts: the random-view render, the sketch-view
renders (L_sil), the frozen base, the photo anchor (forward passes), the backward pass and the
optimiser; each part's peak is above what was held when it started. The NeRF side is measured
with the gradient-checkpointed field chunks (the default) and without them (`--pipeline.model.
field-chunk 0`), with both steps' times. Stable Diffusion's side (SD v1.x's architecture, random
weights) is measured once, as it does not depend on the base: its weights on the device, the VAE
encode with its backward, the UNet with classifier-free guidance, and the guidance step together.

Measured: bytes torch allocates (`benchmarks/memory_meter.py`: torch.profiler's memory events on
the CPU, exact per allocation; `torch.cuda.max_memory_allocated` for the totals on CUDA), fp32 on
the CPU. The whole step is composed from the two sides: the edit's resident tensors + SD's weights
+ the larger of the NeRF side's step and what the NeRF side holds when the guidance runs plus the
guidance step. fp16 figures are PROJECTIONS: SD's weights and activations halved (fp16 under
autocast on a GPU), the NeRF side as measured in fp32 (tiny-cuda-nn's half-precision grids would
need less). Writes benchmarks/results/memory.json and prints a table.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import time
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Dict, List, Optional

import harness
import torch
from harness import ImageGradient, mark_backward, marked
from memory_meter import GB, live_tensor_bytes, metered, part

METHODS = {"nerfacto": "nerfacto", "instant-ngp": "instant-ngp", "splatfacto": "splatfacto"}


def mark_parts(trainer) -> Callable[[], None]:
    """Name the step's parts by the model's methods; returns a function to call before each step."""
    model = trainer.pipeline.model
    resets = []
    if hasattr(model, "_render"):  # NeRF: the random view, the sketch rays, the photo rays
        resets.append(marked(model, "_render", ["random_view_render", "sketch_view_render", "photo_anchor_render"],
                             part))
    else:  # splats: the supersampled random view, then one render per sketch view
        resets.append(marked(model, "_render_supersampled", ["random_view_render", "frozen_base_render"], part))
        resets.append(marked(model, "_render_edit", ["sketch_view_render"], part))
    resets.append(marked(model, "render_base", ["frozen_base_render"], part))
    # nerfstudio 1.1.5 steps "some"
    resets.append(marked(trainer.optimizers, "optimizer_scaler_step_some", ["optimiser"], part))
    mark_backward(trainer.grad_scaler, part)
    return lambda: [reset() for reset in resets]


def resident_bytes(trainer) -> Dict[str, int]:
    """Tensors a step starts with: the edit model (its frozen base too) and the optimiser state."""
    model = trainer.pipeline.model
    modules = [model] + (model.frozen_base.modules() if getattr(model, "frozen_base", None) is not None else [])
    weights = live_tensor_bytes(*modules)
    optimisers = list(trainer.optimizers.optimizers.values())
    everything = live_tensor_bytes(*modules, *optimisers)
    return {"edit_model": weights, "optimiser_state": everything - weights}


@contextmanager
def device_peak(device: str):
    """On CUDA the block's peak from torch.cuda.max_memory_allocated (above what it started with)."""
    result = {}
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        start = torch.cuda.memory_allocated()
    yield result
    if device == "cuda":
        torch.cuda.synchronize()
        result["cuda_peak"] = torch.cuda.max_memory_allocated() - start


def measure_step(trainer, step: int, device: str, reset: Callable[[], None]) -> Dict[str, float]:
    reset()
    with device_peak(device) as cuda, metered(device) as peaks:
        trainer.train_iteration(step)
    measured = {"step_peak_gb": peaks.peak_bytes / GB,
                **{f"{name}_gb": value / GB for name, value in peaks.parts.items()}}
    if "guidance" in peaks.parts_held_at_start:
        measured["held_at_guidance_gb"] = peaks.parts_held_at_start["guidance"] / GB
    if "cuda_peak" in cuda:
        measured["step_peak_gb"] = cuda["cuda_peak"] / GB  # the allocator's own count, as gpu_check reports
    return measured


def time_steps(trainer, first_step: int, count: int, device: str) -> float:
    """The median of COUNT steps' times."""
    times = harness.timed_steps(trainer, range(first_step, first_step + count), device)
    return float(sorted(times)[len(times) // 2])


def nerf_side(work: Path, method: str, base: Path, resolution: int, args, smaller: Optional[Dict] = None) -> Dict:
    """One base kind at one random-view size: the step with chunks (and without, for NeRF bases; SMALLER: its
    entry at a smaller size, to skip an unchunked step this machine cannot hold)."""
    arguments = [
        *harness.sked_flags(base, work, f"{method}-{resolution}", args.device, prompt=None),
        "--pipeline.model.guidance-resolution", str(resolution),
        "--pipeline.model.field-chunk", str(args.field_chunk),  # the chunked step (then none): not the plan's choice
        *(["--pipeline.model.silhouette-resolution", str(args.silhouette_resolution)] if args.silhouette_resolution else []),
        *(["--pipeline.model.nerf-edit-field", args.edit_field] if args.edit_field and method != "splatfacto" else []),
        *harness.reference_edit_tail(work),
    ]
    trainer = harness.set_up_edit(arguments, ImageGradient(part))
    model = trainer.pipeline.model
    nerf = hasattr(model.config, "field_chunk") and hasattr(model, "_render")
    settings = {"guidance_resolution": resolution, "silhouette_resolution": model.config.silhouette_resolution,
                "field_chunk": model.config.field_chunk if nerf else None, "model": type(model).__name__,
                "nerf_edit_field": getattr(model.config, "nerf_edit_field", None)}  # the plan follows it
    for key in ("num_nerf_samples_per_ray", "num_proposal_samples_per_ray", "render_step_size"):
        if hasattr(model.config, key):
            settings[key] = model.config.__dict__[key]
    datamanager = trainer.pipeline.datamanager
    photos = model.photo_anchor_acts()
    settings["rays"] = {"random_view": resolution ** 2,
                        "sketch_views": int(len(getattr(datamanager, "masked_sketch_rays", datamanager.sketch_rays))),
                        "photo": datamanager.config.train_num_rays_per_batch if photos and nerf else 0}
    settings["photo_anchor"] = bool(photos)
    reset = mark_parts(trainer)
    trainer.train_iteration(0)  # the optimiser's state exists from the first step on
    from sked_ns.engine.memory_plan import checkpoint_weight_bytes, step_work
    from sked_ns.models.registry import representation_of

    settings["base_weights_gb"] = checkpoint_weight_bytes(Path(model.config.base_checkpoint)) / GB
    settings["work"] = asdict(step_work(model.config, datamanager.config, representation_of(model.config).name))
    entry: Dict = {"settings": settings, "resident_gb": {k: v / GB for k, v in resident_bytes(trainer).items()}}
    entry["chunked"] = measure_step(trainer, 1, args.device, reset)
    entry["chunked"]["seconds_per_step"] = time_steps(trainer, 2, args.timed_steps, args.device)
    if nerf and not args.skip_unchunked:
        default_chunk = model.config.field_chunk
        model.config.field_chunk = 0
        needed = projected_unchunked_bytes(smaller, resolution)
        if needed is not None and needed > args.host_memory_gb * GB * 0.8:
            entry["unchunked"] = {"not_run": f"projected {needed / GB:.1f} GB from the smaller size's step, over 80% "
                                             f"of this machine's {args.host_memory_gb:.0f} GB"}
        else:
            entry["unchunked"] = measure_step(trainer, 3 + args.timed_steps, args.device, reset)
            entry["unchunked"]["seconds_per_step"] = time_steps(trainer, 4 + args.timed_steps, args.timed_steps,
                                                                args.device)
            entry["time_ratio_chunked_to_unchunked"] = (entry["chunked"]["seconds_per_step"]
                                                        / entry["unchunked"]["seconds_per_step"])
        model.config.field_chunk = default_chunk
    resident = sum(entry["resident_gb"].values())
    entry["nerf_side_peak_gb"] = resident + entry["chunked"]["step_peak_gb"]
    if isinstance(entry.get("unchunked"), dict) and "step_peak_gb" in entry["unchunked"]:
        entry["nerf_side_peak_unchunked_gb"] = resident + entry["unchunked"]["step_peak_gb"]
    del trainer, model
    gc.collect()
    return entry


def projected_unchunked_bytes(previous: Optional[Dict], resolution: int) -> Optional[float]:
    """An unchunked step at RESOLUTION from the same base's entry at a smaller size (its random view grown)."""
    if not previous or "step_peak_gb" not in previous.get("unchunked", {}):
        return None
    smaller = previous["settings"]["guidance_resolution"]
    random_view = previous["unchunked"].get("random_view_render_gb", 0.0) * GB
    return previous["unchunked"]["step_peak_gb"] * GB + random_view * ((resolution / smaller) ** 2 - 1)


def sd_side(work: Path, args) -> Dict:
    """SD's part of a step, on its own: weights, VAE encode + backward, UNet with CFG, the guidance step."""
    from sds_iteration import build_random_stable_diffusion

    from sked_ns.guidance.base import RenderedView
    from sked_ns.guidance.stable_diffusion import StableDiffusionGuidanceConfig

    folder = build_random_stable_diffusion(work / f"sd-{args.sd}", args.sd)
    config = StableDiffusionGuidanceConfig(model=str(folder))
    if args.sd == "tiny":
        config.image_size = 32
    guidance = config.setup()
    guidance.prepare(harness.PROMPT, args.device, {})
    gc.collect()
    entry: Dict = {"image_size": config.image_size, "architecture": f"SD v1.x ({args.sd}), random weights",
                   "dtype": str(guidance.dtype)}
    entry["weights_gb"] = {"unet": live_tensor_bytes(guidance.unet) / GB, "vae_encoder": live_tensor_bytes(guidance.vae) / GB,
                           "text_embeddings": live_tensor_bytes(guidance.embeddings) / GB}
    image = torch.rand(1, 3, 128, 128, device=args.device, requires_grad=True)
    with metered(args.device) as peaks:
        with part("vae_encode"):
            latents = guidance.encode(image)
        with part("vae_backward"):
            latents.sum().backward()
    entry["vae_encode_gb"] = peaks.parts["vae_encode"] / GB
    entry["vae_encode_and_backward_gb"] = peaks.peak_bytes / GB
    guidance.vae.enable_gradient_checkpointing()  # --pipeline.model.guidance.vae-checkpointing
    image.grad = None
    with metered(args.device) as peaks:
        guidance.encode(image).sum().backward()
    entry["vae_encode_and_backward_checkpointed_gb"] = peaks.peak_bytes / GB
    guidance.vae.disable_gradient_checkpointing()
    latents = latents.detach()
    context = torch.stack([guidance.embeddings[""], guidance.embeddings["front"]])
    with metered(args.device) as peaks, torch.no_grad():
        guidance._unet_forward(torch.cat([latents.to(guidance.dtype)] * 2), torch.full((2,), 500, device=args.device),
                               encoder_hidden_states=context)
    entry["unet_cfg_gb"] = peaks.peak_bytes / GB
    view = RenderedView(image=image, camera_to_world=torch.eye(4)[:3].numpy(), focal=100.0, direction="front")
    image.grad = None
    with device_peak(args.device) as cuda, metered(args.device) as peaks:
        loss = guidance(view, 0)["sds_loss"]
        loss.backward()
    entry["guidance_step_gb"] = (cuda.get("cuda_peak", peaks.peak_bytes)) / GB
    image.grad = None
    start = time.perf_counter()
    guidance(view, 1)["sds_loss"].backward()
    harness.sync(args.device)
    entry["guidance_step_seconds"] = time.perf_counter() - start
    del guidance
    gc.collect()
    return entry


def compose(entry: Dict, sd: Optional[Dict]) -> None:
    """The whole step from its two sides (see the module's docstring), measured and projected to fp16; and the
    chunks' cost in time on the whole step (the NeRF side's two times, each plus the guidance step's)."""
    if not sd:
        return
    seconds = sd.get("guidance_step_seconds")
    unchunked = entry.get("unchunked", {})
    if seconds and "seconds_per_step" in unchunked:
        entry["time_ratio_whole_step"] = ((entry["chunked"]["seconds_per_step"] + seconds)
                                          / (unchunked["seconds_per_step"] + seconds))
    resident = sum(entry["resident_gb"].values())
    step = entry["chunked"]
    held = step.get("held_at_guidance_gb", step["step_peak_gb"])
    weights = sum(sd["weights_gb"].values())
    entry["total_fp32_gb"] = resident + weights + max(step["step_peak_gb"], held + sd["guidance_step_gb"])
    entry["projected_fp16_total_gb"] = (resident + weights / 2 + max(step["step_peak_gb"], held + sd["guidance_step_gb"] / 2))


def plan_coefficients(result: Dict) -> Dict[str, Dict[str, float]]:
    """The memory plan's coefficients (sked_ns/engine/memory_plan.py, STEP_MODELS) from each base kind's smallest
    measured size; its larger sizes are then predictions the plan's test checks. Bytes per ray rendered with
    gradients (splats: per pixel) and per sample of a checkpointed chunk."""
    from sked_ns.models.nerf.local_field import LOCAL, LOCAL_RESIDUAL

    coefficients: Dict[str, Dict[str, float]] = {}
    by_size = sorted(result["steps"].items(), key=lambda item: item[1]["settings"]["guidance_resolution"])
    for key, entry in by_size:
        representation = key.split("@")[0]
        if representation == "splatfacto":
            sizes = [e for k, e in by_size if k.startswith("splatfacto@")]
            if len(sizes) >= 2 and representation not in coefficients:
                coefficients[representation] = {**splat_coefficients(sizes[0], sizes[-1]),
                                                "resident_per_weight_byte": resident_per_weight_byte(entry, True)}
            continue
        if representation in coefficients:
            continue
        work, weights = entry_work(entry), entry["settings"]["base_weights_gb"] * GB
        rays = (work["rays"] + work["sketch_rays"]) * work["sample_scale"]
        step, held = entry["chunked"]["step_peak_gb"] * GB, entry["chunked"]["held_at_guidance_gb"] * GB
        if entry["settings"].get("nerf_edit_field") in (LOCAL, LOCAL_RESIDUAL):  # its gradients: Adam's moments / 2
            weights = entry["resident_gb"]["optimiser_state"] * GB / 2
        model = {"kept_per_ray": held / rays, "activation_per_ray": 0.0,
                 "activation_per_sample": max(0.0, step - held - weights) / work["chunk"]}
        model["resident_per_weight_byte"] = resident_per_weight_byte(entry, False)
        unchunked = entry.get("unchunked", {})
        if "step_peak_gb" in unchunked:
            model["activation_per_ray"] = max(0.0, unchunked["step_peak_gb"] * GB - weights) / rays
        if representation == "instant-ngp":
            model.update(ngp_ray_coefficients([e for k, e in by_size if k.startswith("instant-ngp@")]))
        coefficients[representation] = model
    sd = result.get("stable_diffusion")
    if sd:
        step = sd["guidance_step_gb"]
        saved = sd["vae_encode_and_backward_gb"] - sd.get("vae_encode_and_backward_checkpointed_gb",
                                                          sd["vae_encode_and_backward_gb"])
        coefficients["stable_diffusion"] = {"step_bytes_at_512": step * GB * (512 / sd["image_size"]) ** 2,
                                            "vae_checkpointing_share": max(0.0, step - saved) / step}
    return coefficients


def resident_per_weight_byte(entry: Dict, seeds: bool) -> float:
    """The resident tensors per byte of the base's weights, the splat seeds' own bytes taken out."""
    from sked_ns.engine.memory_plan import SEED_BYTES
    from sked_ns.method.options import SkedOptions

    resident = sum(entry["resident_gb"].values()) * GB - (SkedOptions.num_seeds * SEED_BYTES if seeds else 0)
    return resident / (entry["settings"]["base_weights_gb"] * GB)


def entry_work(entry: Dict) -> Dict[str, float]:
    """An entry's StepWork (memory_plan.py): NeRF rays split into the random view's and the others' (sketch views,
    photo rays), read from the rays it counted; a splat edit's pixels as the plan counted them."""
    settings = entry["settings"]
    work = dict(settings["work"])
    if settings.get("field_chunk") is not None:
        rays = settings["rays"]
        work.update(rays=float(rays["random_view"]), sketch_rays=float(rays["sketch_views"] + rays["photo"]))
    else:
        work.setdefault("sketch_rays", 0.0)
    return work


def ngp_ray_coefficients(sizes: List[Dict]) -> Dict[str, float]:
    """instant-ngp samples only occupied cells: a random view (framing the edit) and a sketch view (the whole scene)
    cost differently per ray. From the smallest and largest sizes (random-view rays change, sketch rays do not); the
    sizes between are predictions."""
    small, large = sizes[0], sizes[-1]
    if len(sizes) < 2 or small is large:
        return {}
    held = [entry["chunked"]["held_at_guidance_gb"] * GB for entry in (small, large)]
    random_rays = [entry_work(entry)["rays"] for entry in (small, large)]
    sketch_rays = entry_work(small)["sketch_rays"]
    per_random = (held[1] - held[0]) / (random_rays[1] - random_rays[0])
    fit = {"kept_per_ray": per_random, "kept_per_sketch_ray": (held[0] - random_rays[0] * per_random) / sketch_rays}
    if all("step_peak_gb" in entry.get("unchunked", {}) for entry in (small, large)):  # every activation kept
        weights = small["settings"]["base_weights_gb"] * GB
        kept = [entry["unchunked"]["step_peak_gb"] * GB - weights for entry in (small, large)]
        per_random = (kept[1] - kept[0]) / (random_rays[1] - random_rays[0])
        fit.update(activation_per_ray=per_random,
                   activation_per_sketch_ray=max(0.0, kept[0] - random_rays[0] * per_random) / sketch_rays)
    return fit


def splat_coefficients(small: Dict, large: Dict) -> Dict[str, float]:
    """A splat step is nearly flat in pixels at the demo's Gaussian count (the rasterizer's work per Gaussian
    dominates): per pixel from the two sizes' difference, the rest per byte of the base's Gaussians. Two sizes, two
    unknowns: a fit, not a prediction (one Gaussian count measured)."""
    rays = [entry_work(entry)["rays"] for entry in (small, large)]
    held = [entry["chunked"]["held_at_guidance_gb"] * GB for entry in (small, large)]
    step = [entry["chunked"]["step_peak_gb"] * GB for entry in (small, large)]
    weights = small["settings"]["base_weights_gb"] * GB
    kept = (held[1] - held[0]) / (rays[1] - rays[0])
    added = ((step[1] - held[1]) - (step[0] - held[0])) / (rays[1] - rays[0])
    return {"kept_per_ray": kept, "activation_per_ray": added,
            "kept_per_weight_byte": (held[0] - rays[0] * kept) / weights,
            "step_per_weight_byte": (step[0] - held[0] - rays[0] * added - weights) / weights}


def make_bases(work: Path, methods: List[str], args) -> Dict[str, Path]:
    from sked_ns.demo.base import TinyNerfacto
    from sked_ns.demo.splat_base import SplatFit

    harness.demo_scene(work)
    tiny = args.sd == "tiny"
    return {method: harness.demo_base(work, method, args.base_steps, TinyNerfacto() if tiny else None, args.device,
                                      SplatFit(steps=40, num_gaussians=500) if tiny else SplatFit(steps=args.base_steps),
                                      grid_passes=None if tiny else 2)
            for method in methods}


def table(result: Dict) -> str:
    fmt = lambda value: "-" if value is None else f"{value:.2f}"  # noqa: E731
    rows = [[key, *map(fmt, [entry.get("nerf_side_peak_gb"), entry.get("nerf_side_peak_unchunked_gb"),
                             entry.get("time_ratio_chunked_to_unchunked"), entry["chunked"].get("random_view_render_gb"),
                             entry["chunked"].get("sketch_view_render_gb"), entry["chunked"].get("backward_gb"),
                             entry.get("total_fp32_gb"), entry.get("projected_fp16_total_gb")])]
            for key, entry in result["steps"].items()]
    lines = [harness.markdown_table(["base @ px", "NeRF/splat side GB", "unchunked GB", "chunked / unchunked time",
                                     "random view GB", "sketch views GB", "backward GB", "total fp32 GB",
                                     "projected fp16 GB"], rows)]
    sd = result.get("stable_diffusion")
    if sd:
        lines.append(f"SD ({sd['dtype']}): weights {sum(sd['weights_gb'].values()):.2f} GB, VAE encode + backward "
                     f"{sd['vae_encode_and_backward_gb']:.2f} GB, UNet CFG {sd['unet_cfg_gb']:.2f} GB, guidance step "
                     f"{sd['guidance_step_gb']:.2f} GB")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--bases", default=",".join(METHODS), help="comma-separated: nerfacto,instant-ngp,splatfacto")
    parser.add_argument("--resolutions", default="64,128", help="random-view sizes, smallest first")
    parser.add_argument("--sd", choices=("full", "tiny", "none"), default="full",
                        help="SD's architecture for its side (tiny: the tests' model and the bases' tiny fields)")
    parser.add_argument("--silhouette-resolution", type=int, default=None,
                        help="sketch views' size (default: the preset's 128)")
    parser.add_argument("--base-steps", type=int, default=30, help="fitting steps of each base")
    parser.add_argument("--timed-steps", type=int, default=1)
    parser.add_argument("--skip-unchunked", action="store_true")
    parser.add_argument("--edit-field", choices=("local", "full-copy"), default=None,
                        help="what a NeRF edit trains (default: the preset's); rows record it")
    parser.add_argument("--field-chunk", type=int, default=65536,
                        help="samples per checkpointed chunk of the chunked step (the plan's fallback)")
    parser.add_argument("--parts", default="steps,sd",
                        help="what to measure: steps (each base kind and size), sd (Stable Diffusion's side)")
    parser.add_argument("--keep", action="store_true",
                        help="keep --output's other entries (steps of other bases or sizes, SD's side when not measured)")
    parser.add_argument("--coefficients-only", action="store_true",
                        help="derive --output's plan_coefficients again from the steps it recorded; measure nothing")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "memory.json")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    harness.claim("memory.py", args.output, args.workdir)
    if args.coefficients_only:
        result = json.loads(args.output.read_text())
        result["plan_coefficients"] = plan_coefficients(result)
        harness.write_results(args.output, result)
        harness.report(table(result), args.output)
        return
    import psutil

    args.host_memory_gb = psutil.virtual_memory().total / GB
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    methods = [m for m in args.bases.split(",") if m]
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f"--bases: unknown {sorted(unknown)}; choose from {list(METHODS)}")
    resolutions = sorted(int(r) for r in args.resolutions.split(","))
    result: Dict = {
        "description": __doc__.split("\n\n")[0].strip(),
        "measured": "bytes torch allocates: torch.profiler memory events (CPU) / torch.cuda.max_memory_allocated "
                    "(CUDA); fp32 on the CPU, torch hash grids",
        "projected": "projected_fp16_total_gb: SD's weights and activations halved, the NeRF side as measured",
        "environment": harness.environment(args.device),
        "sd": args.sd, "base_steps": args.base_steps, "steps": {},
    }
    parts = set(args.parts.split(","))
    if args.keep and args.output.is_file():
        kept = json.loads(args.output.read_text())
        result["steps"] = kept.get("steps", {})
        if "sd" not in parts and "stable_diffusion" in kept:
            result["stable_diffusion"] = kept["stable_diffusion"]
    with harness.work_folder(args.workdir) as work:
        bases = make_bases(work, methods, args) if "steps" in parts else {}
        for method in methods if "steps" in parts else []:
            smaller = None
            for resolution in resolutions:
                key = f"{method}@{resolution}"
                print(f"[{key}] ...", flush=True)
                entry = smaller = nerf_side(work, method, bases[method], resolution, args, smaller)
                result["steps"][key] = entry
                harness.write_results(args.output, result)
        if args.sd != "none" and "sd" in parts:
            print("[stable diffusion] ...", flush=True)
            result["stable_diffusion"] = sd_side(work, args)
        for entry in result["steps"].values():
            compose(entry, result.get("stable_diffusion"))
        result["plan_coefficients"] = plan_coefficients(result)
        harness.write_results(args.output, result)
    harness.report(table(result), args.output)


if __name__ == "__main__":
    main()
