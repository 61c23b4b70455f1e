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
from pathlib import Path
from typing import Callable, Dict, List, Optional

import harness
import torch
from dispatch_census import DispatchCensus, module_tensors
from harness import ImageGradient, mark_backward, marked

PHASES = ["random_view_render", "sketch_view_render", "frozen_base", "preservation", "losses", "backward", "optimiser",
          "trainer"]


class Counters:
    """Samples through each network and chunked calls, counted by wrapping them."""

    def __init__(self) -> None:
        self.samples: Dict[str, int] = collections.Counter()
        self.calls: Dict[str, int] = collections.Counter()

    def reset(self) -> None:
        self.samples.clear()
        self.calls.clear()

    def count(self, samples: str) -> Callable:
        """What counts a call's first argument under `samples`."""

        def counted(*args) -> None:
            if args:
                batch = args[0]  # positions (..., 3) or RaySamples
                self.samples[samples] += math.prod(batch.shape[:-1] if isinstance(batch, torch.Tensor) else batch.shape)
                self.calls[samples] += 1

        return counted


def instrument(trainer, state: Dict, counters: Counters) -> None:
    """Name the step's phases (memory.py's parts, as census phases) and count samples through the networks."""

    def phase(name: Optional[str]):
        census = state.get("census")
        return census.phase(name) if census is not None and name is not None else contextlib.nullcontext()

    def wrap(owner, attribute: str, name: Optional[str], samples: Optional[str] = None) -> None:
        harness.wrap(owner, attribute, lambda: phase(name), counters.count(samples) if samples else None)

    model = trainer.pipeline.model
    if hasattr(model, "_render"):  # NeRF: the random view, the sketch rays, the photo rays
        state["reset_renders"] = marked(model, "_render", ["random_view_render", "sketch_view_render",
                                                           "photo_anchor_render"], phase)
    else:
        wrap(model, "_render_supersampled", "random_view_render")
        wrap(model, "_render_edit", "sketch_view_render")
    wrap(model, "render_base", "frozen_base")
    # Every network evaluation goes through its get_density (a field's forward too): one call per chunk.
    base = getattr(model, "frozen_base", None)  # splats keep their base as reference Gaussians
    if base is not None:
        wrap(base.field, "get_density", "frozen_base", "base_field_samples")
        for network in getattr(base, "proposal_networks", None) or []:
            wrap(network, "get_density", "frozen_base", "base_proposal_samples")
        wrap(model.field, "get_density", None, "edit_field_samples")
        for network in getattr(model, "proposal_networks", None) or []:
            wrap(network, "get_density", None, "edit_proposal_samples")
    if hasattr(model, "sketch_field"):
        wrap(model.sketch_field, "preservation_weight", "preservation")
        wrap(model.sketch_field, "hull_distance", "preservation")
    wrap(model, "objective", "losses")
    if hasattr(model, "_sampling_losses"):
        wrap(model, "_sampling_losses", "losses")
    wrap(trainer.optimizers, "optimizer_scaler_step_some", "optimiser")
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


def edit_flags(work: Path, method: str, base: Path, args, resolution: int, sketch_resolution: int,
               output: str = "edits") -> List[str]:
    return [*harness.sked_flags(base, work, f"{method}-{resolution}", "cpu", output=output),
            "--pipeline.model.guidance-resolution", str(resolution),
            "--pipeline.model.silhouette-resolution", str(sketch_resolution)]


def make_bases(work: Path, methods: List[str], args) -> Dict[str, Path]:
    from sked_ns.demo.splat_base import SplatFit

    harness.demo_scene(work, rewrite=False)
    # instant-ngp's full-grid passes take minutes
    return {method: harness.demo_base(work, method, args.base_steps, splat_fit=SplatFit(steps=args.base_steps),
                                      grid_passes=2) for method in methods}


def census_of(work: Path, method: str, base: Path, args, proposal_update: bool = True) -> Dict:
    """One kind's step at --resolution, counted at --measure-resolution."""
    ratio = (args.resolution / args.measure_resolution) ** 2
    sketch = max(8, round(args.silhouette_resolution * args.measure_resolution / args.resolution))
    chunk = None if args.field_chunk is None else int(args.field_chunk / ratio)
    if chunk is None:  # the plan's choice at the reported size, on the named device
        chosen = planned_chunk(work, method, base, args)
        chunk = int(chosen / ratio) if chosen > 0 else 0
    trainer = harness.set_up_edit([*edit_flags(work, method, base, args, args.measure_resolution, sketch),
                                   *(["--pipeline.model.field-chunk", str(chunk)] if chunk is not None else []),
                                   *args.extra, *harness.reference_edit_tail(work)], ImageGradient(cached=True))
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
        "model": type(model).__name__, "nerf_edit_field": getattr(model.config, "nerf_edit_field", None),
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
        arguments = [*edit_flags(work, method, base, args, args.resolution, args.silhouette_resolution, "plans"),
                     *args.extra, *harness.reference_edit_tail(work)]
        return int(getattr(harness.ns_train_sked(arguments).pipeline.model, "field_chunk", 0))
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
    names = ("compute_ops", "syncs", "chunked_calls", "base_proposal_samples")
    rows = [[key, *(f"{before[key][name]:,} -> {entry[name]:,}" if name in before.get(key, {}) else f"{entry[name]:,}"
                    for name in names)]
            for key, entry in after.items() if isinstance(entry, dict) and "compute_ops" in entry]
    return harness.markdown_table(["step", "compute ops", "syncs", "chunked calls", "frozen-base proposal samples"],
                                  rows)


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
    parser.add_argument("--out", type=Path, default=harness.RESULTS / "step_census.json")
    parser.add_argument("--markdown", action="store_true", help="print the file's before/after table and stop")
    parser.add_argument("extra", nargs="*", help="more ns-train sked flags (before the dataparser)")
    args = parser.parse_args()
    if args.markdown:
        stored = json.loads(args.out.read_text())
        print(markdown(stored.get("before", {}), {k: v for k, v in stored.items() if k != "before"}))
        return
    harness.claim("step_census.py", args.out, args.workdir)
    torch.manual_seed(0)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    with harness.work_folder(args.workdir) as work:
        bases = make_bases(work, args.bases, args)
        results: Dict = {}
        for method in args.bases:
            key = f"{method}@{args.resolution}"
            results[key] = census_of(work, method, bases[method], args)
            if method == "nerfacto":
                results[f"{key}-no-proposal-update"] = census_of(work, method, bases[method], args,
                                                                 proposal_update=False)
            write(args, results)  # each kind as soon as it is counted
    harness.report(table(results), args.out)


def write(args, results: Dict) -> None:
    """Each kind's entry into --out (under --label, when given), the others' kept."""
    existing = json.loads(args.out.read_text()) if args.out.exists() else {}
    (existing.setdefault(args.label, {}) if args.label else existing).update(results)
    existing["environment"] = harness.environment("cpu")
    harness.write_results(args.out, existing)


if __name__ == "__main__":
    main()
