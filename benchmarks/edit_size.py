"""Edit size: what a NeRF edit trains, holds in its optimiser and saves, as a whole-field copy and as a local edit.

    python benchmarks/edit_size.py                               # nerfacto and instant-ngp at nerfstudio's sizes
    python benchmarks/edit_size.py --bases nerfacto --workdir /tmp/w

Sets up a real `ns-train sked` edit of the demo scene for each base (fitted with its method's own architecture:
nerfacto's hash table 2^19), once per `--pipeline.model.nerf-edit-field` ("full-copy": 0.7's edit; "local": the base's networks over the box,
the default; "local-residual": 0.8's local edit),
runs one iteration (the guidance replaced by a stand-in image gradient, as the step census does) so that Adam's state
exists, saves the checkpoint as the trainer does, and records: trainable parameters, optimiser state bytes, the
checkpoint's size (and its model and optimiser parts), the local grid's shape, and what the edit holds between steps
(its model with the frozen base, and the optimiser state, as benchmarks/memory.py counts them) beside the base's
weights as the memory plan reads them (tests/engine/test_memory_plan.py checks the plan against both).

Writes benchmarks/results/edit_size.json and prints a table.
"""

from __future__ import annotations

import argparse
import io
import os
from pathlib import Path
from typing import Dict

import harness
import torch
from harness import ImageGradient
from memory import resident_bytes

REPRESENTATIONS = ("full-copy", "local", "local-residual")


def tensor_bytes(value) -> int:
    """Bytes of every tensor in a nested state (dicts, lists)."""
    if torch.is_tensor(value):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(tensor_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(tensor_bytes(v) for v in value)
    return 0


def serialised_bytes(value) -> int:
    buffer = io.BytesIO()
    torch.save(value, buffer)
    return buffer.tell()


def size_of(work: Path, method: str, base: Path, representation: str, args) -> Dict:
    """One edit's trainable state and checkpoint after one iteration."""
    flags = [*harness.sked_flags(base, work, f"{method}-{representation}", "cpu", iterations=2),
             "--pipeline.model.guidance-resolution", str(args.resolution),
             "--pipeline.model.silhouette-resolution", str(args.resolution),
             "--pipeline.model.nerf-edit-field", representation, *harness.reference_edit_tail(work)]
    trainer = harness.set_up_edit(flags, ImageGradient(cached=True))
    trainer.train_iteration(0)
    trainer.save_checkpoint(0)
    checkpoint = sorted(trainer.checkpoint_dir.glob("*.ckpt"))[-1]
    saved = torch.load(checkpoint, map_location="cpu", weights_only=False)
    optimisers = trainer.optimizers.optimizers
    model = trainer.pipeline.model
    local = getattr(model, "local_field", None)
    from sked_ns.engine.memory_plan import checkpoint_weight_bytes

    return {
        "resident_bytes": resident_bytes(trainer),
        "base_weight_bytes": checkpoint_weight_bytes(Path(model.config.base_checkpoint)),
        "trainable_parameters": sum(p.numel() for o in optimisers.values() for g in o.param_groups for p in g["params"]),
        "optimiser_state_bytes": sum(tensor_bytes(o.state_dict()["state"]) for o in optimisers.values()),
        "checkpoint_bytes": checkpoint.stat().st_size,
        "checkpoint_model_bytes": serialised_bytes(saved["pipeline"]),
        "checkpoint_optimiser_bytes": serialised_bytes(saved["optimizers"]),
        "saved_model_keys": sorted({key.split(".")[1] for key in saved["pipeline"] if key.startswith("_model.")}),
        "local_grid": None if local is None else {**local.shape, "box": local.box.tolist()},
        "base_checkpoint_bytes": Path(model.config.base_checkpoint).stat().st_size,
    }


def table(results: Dict) -> str:
    rows = []
    for key, entry in results.items():
        if not isinstance(entry, dict) or "full-copy" not in entry:
            continue
        old, new, residual = entry["full-copy"], entry["local"], entry.get("local-residual")
        for name, unit in (("trainable_parameters", 1), ("optimiser_state_bytes", 1e6), ("checkpoint_bytes", 1e6)):
            rows.append([key, name.replace("_bytes", " (MB)").replace("_", " "), f"{old[name] / unit:,.2f}",
                         f"{new[name] / unit:,.2f}", f"{new[name] / old[name]:.1%}",
                         "-" if residual is None else f"{residual[name] / unit:,.2f}"])
    return harness.markdown_table(["base", "quantity", "full copy", "local", "local / full", "local residual"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bases", nargs="+", default=["nerfacto", "instant-ngp"])
    parser.add_argument("--resolution", type=int, default=16, help="random- and sketch-view size of the one step")
    parser.add_argument("--base-steps", type=int, default=60, help="fitting steps of the demo bases")
    parser.add_argument("--workdir", type=Path, default=None, help="reuse bases built there")
    parser.add_argument("--out", type=Path, default=harness.RESULTS / "edit_size.json")
    args = parser.parse_args()
    harness.claim("edit_size.py", args.out, args.workdir)
    torch.manual_seed(0)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    results: Dict = {}
    with harness.work_folder(args.workdir) as work:
        harness.demo_scene(work, rewrite=False)
        for method in args.bases:
            base = harness.demo_base(work, method, args.base_steps, grid_passes=2)
            results[method] = {representation: size_of(work, method, base, representation, args)
                               for representation in REPRESENTATIONS}
            results["environment"] = harness.environment("cpu")
            harness.write_results(args.out, results)  # each base as soon as it is measured
    harness.report(table(results), args.out)


if __name__ == "__main__":
    main()
