"""Step census: what one edit step dispatches, phase by phase, counted on the CPU (device-independent).

    python benchmarks/step_census.py                          # nerfacto, instant-ngp, splatfacto at 128 px
    python benchmarks/step_census.py --bases nerfacto --label before --out /tmp/census.json

A GPU step is bound by dispatch long before work: every kernel launch costs microseconds and every host-device sync
drains the stream. This benchmark sets up a real `ns-train sked` edit of the demo scene (the bases fitted with their
method's own architecture, torch hash grids), replaces the guidance by a stand-in that hands the render an image
gradient (Stable Diffusion's own step is measured apart: benchmarks/sds_iteration.py), and counts one training
iteration with benchmarks/dispatch_census.py: the compute ops (about one GPU kernel each), the would-be syncs with
the source line of each, and the samples through each network, per phase: random-view render, sketch-view render,
frozen base, preservation (the sketch-distance lookups), losses, backward, optimiser (the trainer's own bookkeeping
is "trainer").

The counts of ops and syncs do not depend on how many rays a call carries, only on how many calls: the step is run
at a small random-view size (--measure-resolution) with the sketch views and the chunk size scaled by the same area
ratio, so that every chunked call is made as often as at the reported size (--resolution); the samples are scaled
by the ratio of rays. The chunk size is what the edit would choose on a device with --device-memory-gb free (the memory
plan: no chunks where the step fits), or --field-chunk.

Writes benchmarks/results/step_census.json (keys "nerfacto@128", "nerfacto@128-no-proposal-update",
"instant-ngp@128", "splatfacto@128"; each with compute_ops, syncs, chunked_calls, base_proposal_samples and the
phases) and prints a table.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Callable, Dict, List, Optional

import torch

BENCHMARKS = Path(__file__).resolve().parent
RESULTS = BENCHMARKS / "results"
sys.path.insert(0, str(BENCHMARKS))
from dispatch_census import DispatchCensus, module_tensors  # noqa: E402
from sole_writer import claim  # noqa: E402

PHASES = ["random_view_render", "sketch_view_render", "frozen_base", "preservation", "losses", "backward", "optimiser",
          "trainer"]


class ImageGradient:
    """Guidance stand-in: a fixed random gradient on the rendered image, as score distillation hands the render."""

    needs_base_render = False

    def __init__(self) -> None:
        self.gradients: Dict = {}

    def __call__(self, view, step: int) -> Dict[str, torch.Tensor]:
        # Made once per image shape, on the device: SD's own step is measured apart, not its inputs' copies.
        key = tuple(view.image.shape)
        if key not in self.gradients:
            self.gradients[key] = torch.randn(key, generator=torch.Generator().manual_seed(0)).to(view.image)
        return {"image_gradient": (view.image * self.gradients[key]).sum() * 1e-3}


class Counters:
    """Samples through each network and chunked calls, counted by wrapping them."""

    def __init__(self) -> None:
        self.samples: Dict[str, int] = collections.Counter()
        self.calls: Dict[str, int] = collections.Counter()

    def reset(self) -> None:
        self.samples.clear()
        self.calls.clear()


def _numel_rows(batch) -> int:
    """Samples in a network's input: positions (..., 3) or RaySamples."""
    return math.prod(batch.shape[:-1] if isinstance(batch, torch.Tensor) else batch.shape)


def wrap(owner, attribute: str, phase: Callable, name: Optional[str] = None, counters: Optional[Counters] = None,
         samples: Optional[str] = None) -> None:
    """owner.attribute counted under the phase `name` (if given), its first argument's samples under `samples`."""
    original = getattr(owner, attribute)

    def wrapped(*args, **kwargs):
        if counters is not None and samples is not None and args:
            counters.samples[samples] += _numel_rows(args[0])
            counters.calls[samples] += 1
        with (phase(name) if name is not None else contextlib.nullcontext()):
            return original(*args, **kwargs)

    setattr(owner, attribute, wrapped)


def instrument(trainer, state: Dict, counters: Counters) -> None:
    """Name the step's phases (memory.py's markers, with census phases for its memory parts) and count samples
    through the networks."""
    from memory import _marked, mark_backward

    def phase(name: str):
        census = state.get("census")
        return census.phase(name) if census is not None else contextlib.nullcontext()

    model = trainer.pipeline.model
    if hasattr(model, "_render"):  # NeRF: the random view, the sketch rays, the photo rays
        state["reset_renders"] = _marked(model, "_render", ["random_view_render", "sketch_view_render",
                                                             "photo_anchor_render"], phase)
    else:
        wrap(model, "_render_supersampled", phase, "random_view_render")
        wrap(model, "_render_edit", phase, "sketch_view_render")
    wrap(model, "render_base", phase, "frozen_base")
    # Every network evaluation goes through its get_density (a field's forward too): one call per chunk.
    base = getattr(model, "frozen_base", None)  # splats keep their base as reference Gaussians
    if base is not None:
        wrap(base.field, "get_density", phase, "frozen_base", counters, "base_field_samples")
        for network in getattr(base, "proposal_networks", None) or []:
            wrap(network, "get_density", phase, "frozen_base", counters, "base_proposal_samples")
        wrap(model.field, "get_density", phase, None, counters, "edit_field_samples")
        for network in getattr(model, "proposal_networks", None) or []:
            wrap(network, "get_density", phase, None, counters, "edit_proposal_samples")
    if hasattr(model, "sketch_field"):
        wrap(model.sketch_field, "preservation_weight", phase, "preservation")
        wrap(model.sketch_field, "hull_distance", phase, "preservation")
    wrap(model, "objective", phase, "losses")
    if hasattr(model, "_sampling_losses"):
        wrap(model, "_sampling_losses", phase, "losses")
    wrap(trainer.optimizers, "optimizer_scaler_step_some", phase, "optimiser")
    mark_backward(trainer.grad_scaler, phase)


def device_tensors(trainer) -> List[torch.Tensor]:
    """What lives on the device before a step: the model (and frozen base), optimiser state, the datamanager's."""
    model = trainer.pipeline.model
    tensors = module_tensors(model, trainer.pipeline.datamanager)
    base = getattr(model, "frozen_base", None)
    if base is not None:
        tensors += module_tensors(*base.modules())
    for optimizer in trainer.optimizers.optimizers.values():
        for values in optimizer.state.values():
            # Adam's step counts stay on the host unless it is capturable or fused (torch.optim.adam)
            tensors += [v for k, v in values.items() if isinstance(v, torch.Tensor) and k != "step"]
    datamanager = trainer.pipeline.datamanager
    for name in ("sketch_masks", "sketch_pixels"):
        value = getattr(datamanager, name, None)
        if isinstance(value, torch.Tensor):
            tensors.append(value)
    for name in ("sketch_rays", "masked_sketch_rays"):  # made once at set-up, on the device
        rays = getattr(datamanager, name, None)
        if rays is not None:
            tensors += [getattr(rays, f) for f in ("origins", "directions", "pixel_area", "camera_indices", "nears",
                                                   "fars") if isinstance(getattr(rays, f, None), torch.Tensor)]
    for camera, mask in getattr(datamanager, "sketch_cameras", []):
        tensors += [mask] + [v for v in vars(camera).values() if isinstance(v, torch.Tensor)]
    for value in vars(model).values():  # plain attributes moved by the model's own code (caches, grids)
        if isinstance(value, torch.Tensor):
            tensors.append(value)
        elif isinstance(value, dict):
            tensors += module_tensors(*[v for v in value.values() if isinstance(v, torch.nn.Module)])
    return tensors


def count_step(trainer, step: int, state: Dict, counters: Counters) -> Dict:
    counters.reset()
    if "reset_renders" in state:
        state["reset_renders"]()
    mode = DispatchCensus(device_tensors(trainer))
    state["census"] = mode
    with mode, mode.phase("trainer"):
        trainer.train_iteration(step)
    state["census"] = None
    result = mode.census.as_dict()
    # chunked calls: network evaluations (one per chunk, a checkpointed chunk's re-run in backward included)
    result["chunked_calls"] = int(sum(counters.calls.values()))
    result["samples"] = dict(counters.samples)
    result["network_calls"] = dict(counters.calls)
    return result


def ns_train_sked(arguments: List[str]):
    from gpu_check import ns_train_sked as parse

    return parse(arguments)


def setup_edit(work: Path, method: str, base: Path, args, resolution: int, sketch_resolution: int, chunk: Optional[int]):
    arguments = [
        "--load-dir", str(base), "--sketches", str(work / "sketches"), "--max-num-iterations", "100",
        "--output-dir", str(work / "edits"), "--experiment-name", f"{method}-{resolution}", "--vis", "tensorboard",
        "--machine.device-type", "cpu", "--steps-per-save", str(10**9), "--prompt", "a red chef hat",
        "--pipeline.model.guidance-resolution", str(resolution),
        "--pipeline.model.silhouette-resolution", str(sketch_resolution),
        *(["--pipeline.model.field-chunk", str(chunk)] if chunk is not None else []),
        *args.extra,
        "pipeline.model.guidance:reference", "nerfstudio-data", "--data", str(work / "data"),
    ]
    config = ns_train_sked(arguments)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.pipeline.prepare_guidance()
    trainer.pipeline.model.guidance = ImageGradient()
    return trainer


def make_bases(work: Path, methods: List[str], args) -> Dict[str, Path]:
    from sked_ns.demo.base import build_demo_base
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.demo.splat_base import SplatFit, fit_demo_splat_base
    from sked_ns.sketches.sketch_set import save_sketch_set

    if not (work / "data").exists():
        demo_scene.write_demo_dataset(work / "data")
        save_sketch_set(demo_scene.demo_sketch_set(), work / "sketches", overwrite=True)
    bases = {}
    for method in methods:
        built = sorted((work / "bases").glob(f"*/{method}/*/config.yml"))
        if built:
            bases[method] = built[-1].parent
        elif method == "splatfacto":
            bases[method] = fit_demo_splat_base(work / "data", work / "bases", SplatFit(steps=args.base_steps))
        else:
            from memory import few_grid_passes

            with few_grid_passes(2 if method != "nerfacto" else None):  # instant-ngp's full-grid passes take minutes
                bases[method] = build_demo_base(work / "data", work / "bases", steps=args.base_steps, tiny=None,
                                                method=method)
    return bases


def census_of(work: Path, method: str, base: Path, args, proposal_update: bool = True) -> Dict:
    """One kind's step at --resolution, counted at --measure-resolution."""
    ratio = (args.resolution / args.measure_resolution) ** 2
    sketch = max(8, round(args.silhouette_resolution * args.measure_resolution / args.resolution))
    chunk = None if args.field_chunk is None else int(args.field_chunk / ratio)
    if chunk is None:  # the plan's choice at the reported size, on the named device
        chosen = planned_chunk(work, method, base, args)
        chunk = int(chosen / ratio) if chosen > 0 else 0
    trainer = setup_edit(work, method, base, args, args.measure_resolution, sketch, chunk)
    model = trainer.pipeline.model
    state: Dict = {}
    counters = Counters()
    instrument(trainer, state, counters)
    for optimizer in trainer.optimizers.optimizers.values():
        for group in optimizer.param_groups:
            group["foreach"] = True  # what torch chooses on a GPU (on a CPU it steps tensor by tensor)
    trainer.train_iteration(0)  # optimiser state exists from the first step on
    step = 1
    sampler = getattr(model, "proposal_sampler", None)
    if sampler is not None:
        # nerfstudio updates the proposals at every step before its 10th, then on a schedule
        sampler._step = 100
        sampler._steps_since_update = 100 if proposal_update else 0
    entry = count_step(trainer, step, state, counters)
    samples = {key: int(value * ratio) for key, value in entry.pop("samples").items()}
    entry["samples"] = samples
    entry["base_proposal_samples"] = samples.get("base_proposal_samples", 0)
    entry["settings"] = {
        "resolution": args.resolution, "measured_at": args.measure_resolution,
        "silhouette_resolution": args.silhouette_resolution, "measured_silhouette_resolution": sketch,
        "field_chunk": getattr(model.config, "field_chunk", None),
        "field_chunk_at_resolution": None if getattr(model.config, "field_chunk", None) is None
        else int(model.config.field_chunk * ratio),
        "proposal_update": proposal_update if sampler is not None else None,
        "model": type(model).__name__,
    }
    del trainer, model
    return entry


def planned_chunk(work: Path, method: str, base: Path, args) -> int:
    """The field chunk `ns-train sked` chooses for this edit at --resolution on a device with --device-memory-gb
    free (its memory plan), or its fixed default where it has no plan to choose with."""
    from sked_ns.engine import memory_plan

    free = args.device_memory_gb * memory_plan.GB
    patched = {"_free_bytes": lambda device: free, "_available_host_bytes": lambda: free}
    saved = {name: getattr(memory_plan, name) for name in patched if hasattr(memory_plan, name)}
    for name, value in patched.items():
        setattr(memory_plan, name, value)
    try:
        arguments = [
            "--load-dir", str(base), "--sketches", str(work / "sketches"), "--max-num-iterations", "100",
            "--output-dir", str(work / "plans"), "--experiment-name", f"{method}-{args.resolution}", "--vis",
            "tensorboard", "--machine.device-type", "cpu", "--prompt", "a red chef hat",
            "--pipeline.model.guidance-resolution", str(args.resolution),
            "--pipeline.model.silhouette-resolution", str(args.silhouette_resolution), *args.extra,
            "pipeline.model.guidance:reference", "nerfstudio-data", "--data", str(work / "data"),
        ]
        return int(getattr(ns_train_sked(arguments).pipeline.model, "field_chunk", 0))
    finally:
        for name, value in saved.items():
            setattr(memory_plan, name, value)


def table(results: Dict) -> str:
    lines = [f"{'step':34s} {'compute ops':>11s} {'syncs':>6s} {'chunked':>8s} {'base prop. samples':>19s}"]
    for key, entry in results.items():
        if not isinstance(entry, dict) or "compute_ops" not in entry:
            continue
        lines.append(f"{key:34s} {entry['compute_ops']:11,d} {entry['syncs']:6,d} {entry['chunked_calls']:8,d} "
                     f"{entry['base_proposal_samples']:19,d}")
        for phase in PHASES:
            counts = entry["phases"].get(phase)
            if counts:
                lines.append(f"  {phase:32s} {counts['compute_ops']:11,d} {counts['syncs']:6,d}")
    return "\n".join(lines)


def markdown(before: Dict, after: Dict) -> str:
    """The before/after table of docs/benchmarks.md (Step census)."""
    rows = ["| step | compute ops | syncs | chunked calls | frozen-base proposal samples |", "|---|---|---|---|---|"]
    for key in after:
        if not isinstance(after[key], dict) or "compute_ops" not in after[key]:
            continue
        old, new = before.get(key, {}), after[key]
        cells = [f"{old[name]:,} -> {new[name]:,}" if name in old else f"{new[name]:,}"
                 for name in ("compute_ops", "syncs", "chunked_calls", "base_proposal_samples")]
        rows.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bases", nargs="+", default=["nerfacto", "instant-ngp", "splatfacto"])
    parser.add_argument("--resolution", type=int, default=128, help="random-view size reported")
    parser.add_argument("--silhouette-resolution", type=int, default=128, help="sketch-view size reported")
    parser.add_argument("--measure-resolution", type=int, default=32, help="random-view size the step is run at")
    parser.add_argument("--field-chunk", type=int, default=None,
                        help="chunk size at --resolution (default: what the edit chooses)")
    parser.add_argument("--device-memory-gb", type=float, default=140.0,
                        help="free memory of the device the field chunk is chosen for (default: one H200)")
    parser.add_argument("--base-steps", type=int, default=60, help="fitting steps of the demo bases")
    parser.add_argument("--workdir", type=Path, default=None, help="reuse bases built there")
    parser.add_argument("--label", default=None, help="store the results under this label in the file")
    parser.add_argument("--out", type=Path, default=RESULTS / "step_census.json")
    parser.add_argument("--markdown", action="store_true", help="print the file's before/after table and stop")
    parser.add_argument("extra", nargs="*", help="more ns-train sked flags (before the dataparser)")
    args = parser.parse_args()
    if args.markdown:
        stored = json.loads(args.out.read_text())
        print(markdown(stored.get("before", {}), {k: v for k, v in stored.items() if k != "before"}))
        return
    claim("step_census.py", args.out, args.workdir)
    torch.manual_seed(0)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    with (contextlib.nullcontext(str(args.workdir)) if args.workdir else tempfile.TemporaryDirectory()) as folder:
        work = Path(folder)
        work.mkdir(parents=True, exist_ok=True)
        bases = make_bases(work, args.bases, args)
        results: Dict = {}
        for method in args.bases:
            key = f"{method}@{args.resolution}"
            results[key] = census_of(work, method, bases[method], args)
            if method == "nerfacto":
                results[f"{key}-no-proposal-update"] = census_of(work, method, bases[method], args,
                                                                 proposal_update=False)
            write(args, results)  # each kind as soon as it is counted
    print(table(results))
    print(f"wrote {args.out}")


def write(args, results: Dict) -> None:
    existing = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.label:
        existing.setdefault(args.label, {}).update(results)
    else:
        existing.update(results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(existing, indent=1) + "\n")


if __name__ == "__main__":
    main()
