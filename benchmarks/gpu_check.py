"""The whole CUDA path in one command: bases, SDS edits (nerfacto, instant-ngp and splatfacto), the bare SD
step, the CUDA marcher against the torch one, gsplat against the CPU splat compositor, and the CUDA-only tests.

    python benchmarks/gpu_check.py                            # on a GPU: full-size SD v1.x, paper's settings
    python benchmarks/gpu_check.py --device cpu --size tiny   # a smoke run anywhere (a test runs it)

a. Fits a nerfacto and an instant-ngp base of the demo scene on the device (the methods' own
   architectures at --size full, the tests' tiny ones at --size tiny).
b. Writes SD v1.x's architecture with RANDOM weights to a local folder (honest timings,
   meaningless images) and runs a real `ns-train sked --prompt ...` edit of each base, parsed
   by nerfstudio's own command line, with the paper's settings (128 px renders upsampled to
   512, CFG 100, fp16 and compiled UNet / VAE encoder on CUDA). The instant-ngp edit marches
   nerfacc's CUDA occupancy grid.
c. First (correctness, a minute or two): gsplat's rasterization against sked_ns.models.splat.rasterize's
   CPU compositor (images and gradients) and the tests that only run on CUDA.
d. In the first edit's process, times the bare compiled SD step (VAE encode forward + backward and the
   batch-2 UNet) that every SDS iteration must pay: the floor an edit step is compared with. Checks
   nerfacc's CUDA marcher against the torch marcher on the instant-ngp edit's own grid, edits a
   splatfacto base of the demo scene (fitted with the torch rasterizer; gsplat renders the edit on
   CUDA), and runs benchmarks/memory.py on the GPU with the time left (each part of a step's memory
   from the CUDA allocator: memory_cuda.json, beside the output).
e. Writes benchmarks/results/gpu_check.json: per edit the setup, compile and per-iteration
   times (steady iterations, the end-of-training save left out), the 10,000-iteration extrapolation
   (compile, each checkpoint once and evaluation images included), the ratio to the SD floor, the
   peak GPU memory and the process's peak RSS; and a torch-profiler table
   of the nerfacto edit's most expensive operations beside it (gpu_check_profile.txt).

Every phase is timed and guarded: a failing phase is recorded with its error and the rest run.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import shlex
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Callable, Dict, List, Optional

import harness
import numpy as np
import torch
from harness import BENCHMARKS, PROMPT, StageTimer, ns_train_sked, peak_rss_gb, sync

PAPER_ITERATIONS = 10_000
EDIT_BASES = {"nerfacto": "nerfacto", "ngp": "instant-ngp", "splat": "splatfacto"}  # each edit and the method of its base


class Check:
    """The results dict, written after every phase, and the phases' timing and guarding."""

    def __init__(self, output: Path, budget_s: float) -> None:
        self.output, self.deadline, self.result = output, time.perf_counter() + budget_s, {"phases": {}}
        output.parent.mkdir(parents=True, exist_ok=True)

    def left(self) -> float:
        return self.deadline - time.perf_counter()

    def phase(self, name: str, function: Callable[[], Optional[dict]], needs_s: float = 0.0):
        if self.left() < needs_s:
            self.result["phases"][name] = {"status": f"skipped: under {needs_s:.0f} s of the time budget left"}
            print(f"[{name}] skipped (time budget)", flush=True)
            self.write()
            return None
        print(f"[{name}] ...", flush=True)
        start = time.perf_counter()
        try:
            value = function()
            status = "ok"
        except Exception as error:  # recorded, so one broken phase does not hide the others
            value, status = None, f"failed: {type(error).__name__}: {error}"
            traceback.print_exc()
            self.result["phases"].setdefault(name, {})["traceback"] = traceback.format_exc()[-4000:]
        self.result["phases"].setdefault(name, {}).update(status=status, seconds=round(time.perf_counter() - start, 2))
        print(f"[{name}] {status} ({time.perf_counter() - start:.1f} s)", flush=True)
        self.write()
        return value

    def write(self) -> None:
        harness.write_results(self.output, self.result)


def reset_peak(device: str) -> None:
    if device == "cuda":
        gc.collect()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


def peak_gb(device: str) -> Optional[float]:
    return torch.cuda.max_memory_allocated() / 2**30 if device == "cuda" else None


def iteration_seconds(starts: List[float], saves: List[float], end: float) -> np.ndarray:
    """Each iteration from its start to the next iteration's start, the next checkpoint save's or the end,
    whichever comes first: saves (the one at the end of training too) are costed once, on their own."""
    bounds = np.sort(np.array([*starts[1:], *saves, end]))
    return np.array([bounds[np.searchsorted(bounds, start, side="right")] - start for start in starts])


def steps_due(iterations: int, every: int) -> int:
    """How many of an edit's steps nerfstudio's loop saves or evaluates at (its own step_check)."""
    from nerfstudio.utils.misc import step_check

    return sum(step_check(step, every) for step in range(iterations))


def checkpoint_saves(iterations: int, steps_per_save: int) -> int:
    """Checkpoints an edit of ITERATIONS steps writes: nerfstudio's in-loop ones and the one after the loop."""
    return steps_due(iterations, steps_per_save) + 1


def extrapolated_seconds(entry: Dict, iterations: int, steps_per_save: int, steps_per_eval_image: int) -> float:
    """A whole edit's wall time from the timed run: setup, the first (compiling) iteration, the steady ones,
    and each checkpoint and evaluation image nerfstudio's loop would add, at the preset's cadence."""
    return (entry["setup_seconds"] + entry["load_diffusion_seconds"] + entry["first_iteration_seconds"]
            + (iterations - 1) * entry["ms_per_iteration"] / 1000
            + checkpoint_saves(iterations, steps_per_save) * entry["checkpoint_seconds"]
            + steps_due(iterations, steps_per_eval_image) * entry["eval_image_seconds"])


class StepClock:
    """Wall time of every training iteration, callbacks and logging included, checkpoint saves left out."""

    def __init__(self, trainer, device: str) -> None:
        self.trainer, self.device, self.entries, self.saves, self.end = trainer, device, [], [], float("nan")
        original_iteration, original_save = trainer.train_iteration, trainer.save_checkpoint

        def timed(step: int):
            sync(device)
            self.entries.append(time.perf_counter())
            return original_iteration(step)

        def save(step: int):
            sync(device)
            self.saves.append(time.perf_counter())
            return original_save(step)

        trainer.train_iteration, trainer.save_checkpoint = timed, save

    def close(self) -> None:
        sync(self.device)
        self.end = time.perf_counter()
        del self.trainer.train_iteration, self.trainer.save_checkpoint  # the class's own again

    @property
    def durations(self) -> np.ndarray:
        return iteration_seconds(self.entries, self.saves, self.end)


def edit_arguments(base: Path, work: Path, sd: Path, name: str, iterations: int, size: str, device: str,
                   render_resolution: Optional[int] = None, extra: str = "") -> List[str]:
    """The user's command line: the paper's settings from the preset; small renders only at --size tiny
    or where RENDER_RESOLUTION asks (the random and sketch views' size); EXTRA: more `ns-train sked` flags."""
    arguments = harness.sked_flags(base, work, name, device, iterations)
    guidance = ["pipeline.model.guidance:stable-diffusion", "--pipeline.model.guidance.model", str(sd)]
    if size == "tiny":
        render_resolution = render_resolution or 16
        guidance += ["--pipeline.model.guidance.image-size", "32"]
    if render_resolution:
        arguments += ["--pipeline.model.guidance-resolution", str(render_resolution),
                      "--pipeline.model.silhouette-resolution", str(render_resolution)]
    arguments += shlex.split(extra)
    return arguments + guidance + ["nerfstudio-data", "--data", str(work / "data")]


def run_edit(check: Check, key: str, base: Path, work: Path, sd: Path, args) -> Optional[object]:
    """One `ns-train sked` edit, timed; returns the trainer (for the SD floor and the marcher check)."""
    device = args.device
    entry: Dict = {}
    check.result[key] = entry
    reset_peak(device)
    config = ns_train_sked(edit_arguments(base, work, sd, key, args.iterations, args.size, device,
                                          args.render_resolution, args.edit_flags))
    start = time.perf_counter()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    sync(device)
    entry["setup_seconds"] = time.perf_counter() - start
    start = time.perf_counter()
    trainer.pipeline.prepare_guidance()  # loads SD from the folder, encodes the prompts
    sync(device)
    entry["load_diffusion_seconds"] = time.perf_counter() - start
    clock = StepClock(trainer, device)
    start = time.perf_counter()
    trainer.train()
    clock.close()
    entry["train_seconds"] = time.perf_counter() - start
    durations = clock.durations
    steady = durations[min(args.warmup, len(durations) - 1):]
    ms = 1000 * float(np.mean(steady))
    entry.update(
        iterations=len(durations),
        first_iteration_seconds=float(durations[0]),
        compile_seconds=max(0.0, float(durations[0]) - ms / 1000),
        ms_per_iteration=ms,
        ms_per_iteration_median=1000 * float(np.median(steady)),
        ms_per_iteration_p90=1000 * float(np.percentile(steady, 90)),
        steady_iterations=len(steady),
        final_save_seconds=float(clock.end - clock.saves[-1]) if clock.saves else None,
        peak_gpu_memory_gb=peak_gb(device),
        peak_gpu_memory_reserved_gb=torch.cuda.max_memory_reserved() / 2**30 if device == "cuda" else None,
    )
    model = trainer.pipeline.model
    entry["model"] = type(model).__name__
    entry["sketch_lookup_compiled"] = model.sketch_field._lookup is not getattr(
        sys.modules["sked_ns.method.preservation"], "_sketch_distance")
    entry["guidance_dtype"] = str(getattr(model.guidance, "dtype", None))

    # What a 10,000-iteration edit also pays: a checkpoint every steps_per_save, an eval image every
    # steps_per_eval_image, at the preset's cadence (the timed run saved none).
    sync(device)
    start = time.perf_counter()
    trainer.save_checkpoint(len(durations))
    sync(device)
    entry["checkpoint_seconds"] = time.perf_counter() - start
    start = time.perf_counter()
    trainer.pipeline.eval()
    with torch.no_grad():
        trainer.pipeline.get_eval_image_metrics_and_images(step=len(durations))
    trainer.pipeline.train()
    sync(device)
    entry["eval_image_seconds"] = time.perf_counter() - start
    entry["extrapolated_10k_seconds"] = extrapolated_seconds(
        entry, PAPER_ITERATIONS, sked_preset_cadence("steps_per_save"), sked_preset_cadence("steps_per_eval_image"))
    entry["peak_rss_gb"] = peak_rss_gb()
    return trainer


def sked_preset_cadence(name: str) -> int:
    from sked_ns.engine.presets import edit_preset

    return int(getattr(edit_preset(), name))


def sd_floor(check: Check, trainer, args, edit: str) -> dict:
    """The bare compiled SD step on a fixed input, as the edit calls it (same autocast, same shapes), in the
    process of EDIT (the first edit that ran)."""
    from sds_iteration import bare_sd_step

    device = args.device
    resolution = trainer.pipeline.model.config.guidance_resolution
    image = torch.rand(1, 3, resolution, resolution, device=device, requires_grad=True)
    warmup = min(max(args.warmup, 1), 3)  # compilation (and its recompiles on CUDA) out of the mean
    times = harness.timed_calls(lambda: bare_sd_step(trainer, image), args.floor_repeats, device, warmup)
    floor = 1000 * float(np.mean(times))
    check.result["sd_floor_ms"], check.result["sd_floor_edit"] = floor, edit
    ratios_to_sd_floor(check)
    return {"sd_floor_ms": floor}


def ratios_to_sd_floor(check: Check) -> None:
    """Each timed edit's iteration over the SD floor, once the floor is measured."""
    floor = check.result.get("sd_floor_ms")
    for key in EDIT_BASES:
        entry = check.result.get(key)
        if floor and isinstance(entry, dict) and "ms_per_iteration" in entry:
            entry["ratio_to_sd_floor"] = entry["ms_per_iteration"] / floor


def profile_steps(check: Check, trainer, args) -> dict:
    """Where an iteration's time goes: a synchronised split, then torch.profiler's top operations."""
    device = args.device
    model, guidance = trainer.pipeline.model, trainer.pipeline.model.guidance
    timer = StageTimer(device)
    undo = [timer.wrap(model, "_render", "nerf_render (random + sketch views)"),
            timer.wrap(model.base_field, "forward", "base_field (L_pres)"),
            timer.wrap(guidance, "_encode", "vae_encode"),
            timer.wrap(guidance, "_unet_forward", "unet")]
    steps = range(10**6, 10**6 + args.profile_steps)
    total = harness.timed_steps(trainer, steps, device)
    for restore in undo:
        restore()
    split = {name: 1000 * value / len(steps) for name, value in timer.totals.items()}
    split["rest (losses, backward, optimiser, overhead)"] = 1000 * float(np.mean(total)) - sum(split.values())
    check.result["split_ms (synchronised)"] = split

    activities = [torch.profiler.ProfilerActivity.CPU]
    if device == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as profiler:
        for step in range(2 * 10**6, 2 * 10**6 + args.profile_steps):
            trainer.train_iteration(step)
        sync(device)
    sort = "cuda_time_total" if device == "cuda" else "cpu_time_total"
    table = profiler.key_averages().table(sort_by=sort, row_limit=40)
    path = check.output.with_name(check.output.stem + "_profile.txt")
    path.write_text(f"{args.profile_steps} iterations of the nerfacto edit, sorted by {sort}\n{table}\n")
    check.result["profile_table"] = str(path)
    return split


def marcher_check(check: Check, trainer, args) -> dict:
    """nerfacc's CUDA marcher against the torch marcher on the edit's own occupancy grid and options
    (step, cone angle, near/far planes): the same samples, compared one by one, not only counted."""
    from sked_ns.models.nerf.occupancy import march_grid, marcher_rtol, sample_agreement

    model = trainer.pipeline.model
    grid, config = model.occupancy_grid, model.config
    step, cone_angle = config.render_step_size, config.cone_angle
    generator = torch.Generator().manual_seed(0)
    aabb = grid.aabbs[-1].cpu()
    centre, half = (aabb[:3] + aabb[3:]) / 2, (aabb[3:] - aabb[:3]) / 2
    targets = centre + (torch.rand(2048, 3, generator=generator) * 2 - 1) * half * 0.5
    origins = centre + torch.nn.functional.normalize(torch.randn(2048, 3, generator=generator), dim=-1) * half.norm() * 1.5
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far = float(config.near_plane), float(config.far_plane)
    nears, fars = torch.full((2048,), near), torch.full((2048,), far)
    reference = march_grid(grid.binaries.cpu(), grid.aabbs.cpu(), origins, directions, nears, fars, step, cone_angle)
    device = "cuda" if args.device == "cuda" else "cpu"
    fast = grid.sampling(origins.to(device), directions.to(device), render_step_size=step, near_plane=near,
                         far_plane=far, cone_angle=cone_angle)
    fast = [tensor.cpu() for tensor in fast]
    counts_ref = torch.bincount(reference[0], minlength=2048)
    counts_fast = torch.bincount(fast[0], minlength=2048)
    result = {
        "backend": "nerfacc CUDA" if args.device == "cuda" else "torch (no CUDA)",
        "render_step_size": step, "cone_angle": cone_angle, "near_plane": near, "far_plane": far,
        "samples_torch": int(len(reference[0])), "samples_nerfacc": int(len(fast[0])),
        "relative_difference": abs(len(fast[0]) - len(reference[0])) / max(len(reference[0]), 1),
        "rays_with_equal_counts": float((counts_ref == counts_fast).float().mean()),
        "rays_within_one_sample": float(((counts_ref - counts_fast).abs() <= 1).float().mean()),
        # Share of each marcher's samples (t_start, t_end per ray) the other has too, within the float32 drift of
        # the edit's steps (marcher_rtol), and within 1e-4 of t.
        "samples_rtol": marcher_rtol(cone_angle),
        **{f"samples_{key}": value for key, value in sample_agreement(reference, fast, marcher_rtol(cone_angle)).items()},
        **{f"samples_1e-4_{key}": value for key, value in sample_agreement(reference, fast, 1e-4).items()},
    }
    check.result["marcher_check"] = result
    if min(result["samples_matched_reference"], result["samples_matched_other"]) < 0.99:
        raise AssertionError(f"CUDA and torch marchers disagree: {result}")
    return result


def splat_raster_check(check: Check, device: str) -> dict:
    """gsplat's CUDA rasterization vs sked_ns.models.splat.rasterize's CPU compositor on one random scene: each image and
    gradient's largest difference, relative to gsplat's largest value."""
    from splat_agreement import compare_with_gsplat  # benchmarks/, beside this script

    differences = compare_with_gsplat(device)
    relative = {key: differences[key] / max(differences.get(f"{key}_scale", 0.0), 1e-12)
                for key in differences if not key.endswith("_scale")}
    check.result["splat_raster_check"] = {"max_abs": differences, "relative": relative,
                                          "worst_relative": max(relative.values())}
    return check.result["splat_raster_check"]


CUDA_TESTS = ["models/test_occupancy.py", "models/test_splat_render.py", "method/test_preservation.py",
              "guidance/test_guidance.py"]
"""The test files (under tests/) with tests that only run on CUDA; `-k cuda` picks those tests out of them."""


def cuda_tests(check: Check) -> dict:
    """The tests that only run on CUDA (skipped on the CPU CI)."""
    tests = BENCHMARKS.parent / "tests"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "cuda",
               *[str(tests / path) for path in CUDA_TESTS]]
    run = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=BENCHMARKS.parent)
    summary = (run.stdout.strip().splitlines() or [""])[-1]
    check.result["cuda_tests"] = {"returncode": run.returncode, "summary": summary, "tail": run.stdout[-3000:] + run.stderr[-2000:]}
    if run.returncode != 0:
        raise AssertionError(f"CUDA tests failed: {summary}")
    return check.result["cuda_tests"]


def memory_check(check: Check, args) -> dict:
    """benchmarks/memory.py on the GPU: each part of a step's peak, and the whole step's, from the CUDA allocator."""
    output = check.output.with_name("memory_cuda.json")
    command = [sys.executable, str(BENCHMARKS / "memory.py"), "--device", "cuda", "--output", str(output)]
    try:
        subprocess.run(command, check=True, timeout=max(60.0, check.left() - 30))
        error = None
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as failure:
        error = failure  # memory.py writes each step as it goes: what it measured is kept, then the phase fails
    steps = json.loads(output.read_text())["steps"] if output.is_file() else {}
    summary = {key: {name: entry.get(name) for name in ("nerf_side_peak_gb", "total_fp32_gb", "projected_fp16_total_gb")}
               for key, entry in steps.items()}
    check.result["memory"] = {"results": str(output), "steps": summary, "complete": error is None}
    if error is not None:
        raise error
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=("cuda", "cpu"))
    parser.add_argument("--size", choices=("full", "tiny"), default="full",
                        help="full: SD v1.x and the methods' own field sizes; tiny: a smoke run")
    parser.add_argument("--iterations", type=int, default=None, help="edit iterations timed (default 60 full, 3 tiny)")
    parser.add_argument("--warmup", type=int, default=None, help="iterations left out of the steady state")
    parser.add_argument("--base-steps", type=int, default=None, help="fitting steps of each base")
    parser.add_argument("--floor-repeats", type=int, default=None)
    parser.add_argument("--render-resolution", type=int, default=None,
                        help="random and sketch views' size (default: the preset's 128 at full, 16 at tiny); on the "
                             "CPU, 128 px renders of the full nerfacto take over 18 GB (torch hash grids, no tcnn)")
    parser.add_argument("--profile-steps", type=int, default=None)
    parser.add_argument("--edit-flags", default="",
                        help="more `ns-train sked` flags for both edits, e.g. \"--pipeline.model.lambda-photo 0\"")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="skip later phases past this much time (default: 540 s on CUDA, a lent GPU's slot; none on CPU)")
    parser.add_argument("--skip", default="", help="comma-separated: an edit and its base (nerfacto, ngp, splat), or "
                        "profile, splat_raster_check, tests, memory")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "gpu_check.json")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    full = args.size == "full"
    args.iterations = args.iterations or (60 if full else 3)
    args.warmup = args.warmup if args.warmup is not None else (10 if full else 1)
    args.base_steps = args.base_steps or (300 if full else 30)
    args.floor_repeats = args.floor_repeats or (20 if full else 2)
    args.profile_steps = args.profile_steps or (5 if full else 1)
    skip = set(filter(None, args.skip.split(",")))
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda, but torch sees no CUDA device here: pass --device cpu")

    harness.claim("gpu_check.py", args.output, args.workdir)
    budget = args.budget_s if args.budget_s is not None else (540.0 if args.device == "cuda" else float("inf"))
    check = Check(args.output, budget)
    check.result.update(
        description="benchmarks/gpu_check.py: real `ns-train sked --prompt` edits with SD v1.x's "
                    f"{'full' if full else 'tiny'} architecture and RANDOM weights (honest timings, meaningless images)",
        settings={"size": args.size, "edit_flags": args.edit_flags, "iterations_timed": args.iterations, "warmup": args.warmup,
                  "guidance_resolution": args.render_resolution or (128 if full else 16), "sd_image_size": 512 if full else 32,
                  "guidance_scale": 100, "precision": "fp16 autocast, compiled UNet and VAE encoder" if args.device == "cuda"
                  else "fp32, eager", "prompt": PROMPT},
        **harness.environment(args.device),
    )
    check.write()

    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never the hub: the diffusion model is built here, random weights
    from sds_iteration import build_random_stable_diffusion

    from sked_ns.demo.base import TinyNerfacto
    from sked_ns.demo.splat_base import SplatFit

    with harness.work_folder(args.workdir) as work:
        tiny = None if full else TinyNerfacto()
        bases: Dict[str, Path] = {}

        def make_bases():
            harness.demo_scene(work)
            timing = {}
            for method in [method for edit, method in EDIT_BASES.items() if edit not in skip]:  # none for a skipped edit
                start = time.perf_counter()
                # Splats are fitted with the torch rasterizer: the base is the same on any device.
                bases[method] = harness.demo_base(work, method, args.base_steps, tiny, args.device,
                                                  SplatFit() if full else SplatFit(steps=40, num_gaussians=500),
                                                  reuse=False)
                sync(args.device)
                timing[f"{method}_seconds"] = time.perf_counter() - start
            check.result["bases"] = {**timing, "steps": args.base_steps,
                                     "architecture": "the methods' defaults" if full else "tiny (tests)"}

        check.phase("bases", make_bases)
        # Correctness first (a minute or two): gsplat against the CPU compositor, and the CUDA-only tests.
        if args.device == "cuda" and "splat_raster_check" not in skip:
            check.phase("splat_raster_check", lambda: splat_raster_check(check, args.device))
        if args.device == "cuda" and "tests" not in skip:
            check.phase("cuda_tests", lambda: cuda_tests(check), needs_s=60)
        sd_folder = work / f"sd-{args.size}"
        check.phase("diffusion_model", lambda: {"folder": str(build_random_stable_diffusion(sd_folder, args.size))})

        trainer = None
        if "nerfacto" not in skip and "nerfacto" in bases:
            trainer = check.phase("nerfacto_edit", lambda: run_edit(check, "nerfacto", bases["nerfacto"], work, sd_folder, args))
        if trainer is not None:
            check.phase("sd_floor", lambda: sd_floor(check, trainer, args, "nerfacto"), needs_s=30)
            if "profile" not in skip:
                check.phase("profile", lambda: profile_steps(check, trainer, args), needs_s=60)
        del trainer
        gc.collect()
        if args.device == "cuda":
            torch._dynamo.reset()  # the second edit compiles anew (inductor's disk cache may help, as for a user)
        if "ngp" not in skip and "instant-ngp" in bases:
            trainer = check.phase("ngp_edit", lambda: run_edit(check, "ngp", bases["instant-ngp"], work, sd_folder, args),
                                  needs_s=90 if full else 0)
            if trainer is not None:
                if "sd_floor_ms" not in check.result:  # the nerfacto edit did not run: the floor in this process
                    check.phase("sd_floor", lambda: sd_floor(check, trainer, args, "ngp"), needs_s=30)
                check.phase("marcher_check", lambda: marcher_check(check, trainer, args))
            del trainer
        if "splat" not in skip and "splatfacto" in bases:
            trainer = check.phase("splat_edit", lambda: run_edit(check, "splat", bases["splatfacto"], work, sd_folder, args),
                                  needs_s=90 if full else 0)
            del trainer
        # The memory table takes what is left (it writes each step as it goes).
        if args.device == "cuda" and "memory" not in skip:
            check.phase("memory", lambda: memory_check(check, args), needs_s=120)

    ratios_to_sd_floor(check)
    # The headline figures (the nerfacto edit) at the top level, as the README quotes them.
    headline = check.result.get("nerfacto", {})
    for key in ("extrapolated_10k_seconds", "compile_seconds", "ms_per_iteration", "ratio_to_sd_floor", "peak_gpu_memory_gb"):
        if key in headline:
            check.result[key] = headline[key]
    check.result["peak_rss_gb"] = peak_rss_gb()
    check.result["failed_phases"] = [name for name, phase in check.result["phases"].items() if phase["status"] != "ok"
                                     and not phase["status"].startswith("skipped")]
    check.write()
    harness.report(summary_table(check.result), args.output)
    if check.result["failed_phases"]:
        sys.exit(1)


def summary_table(result: dict) -> str:
    rows = ["| edit | setup s | compile s | ms / iteration | x SD floor | peak GPU GB | 10k iterations, min |",
            "|---|---|---|---|---|---|---|"]
    for key in ("nerfacto", "ngp", "splat"):
        entry = result.get(key)
        if not isinstance(entry, dict) or "ms_per_iteration" not in entry:
            continue
        ratio = entry.get("ratio_to_sd_floor")
        peak = entry.get("peak_gpu_memory_gb")
        rows.append(f"| {key} | {entry['setup_seconds'] + entry['load_diffusion_seconds']:.1f} | {entry['compile_seconds']:.1f} "
                    f"| {entry['ms_per_iteration']:.1f} | {'-' if ratio is None else f'{ratio:.2f}'} "
                    f"| {'-' if peak is None else f'{peak:.2f}'} | {entry['extrapolated_10k_seconds'] / 60:.1f} |")
    floor = result.get("sd_floor_ms")
    head = f"{result.get('device')}; {result.get('description')}"
    lines = [head, *rows] + ([f"bare SD step (VAE encode fwd+bwd + UNet batch 2): {floor:.1f} ms"] if floor else [])
    return "\n".join(lines + ([f"peak RSS {result['peak_rss_gb']:.2f} GB"] if "peak_rss_gb" in result else []))


if __name__ == "__main__":
    main()
