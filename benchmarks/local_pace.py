"""How fast a NeRF edit fills its sketches and carves, the local residual against a trainable copy of the whole base.

    python benchmarks/local_pace.py [--seeds 0 1] [--fields local full-copy] [--workdir DIR] [--previous JSON]

On the tests' demo base (tests/conftest.py: the tiny nerfacto fitted 400 steps) with the tests' edit settings
(reference guidance, 24 px renders), two edits of each kind per seed:

- fill: the demo's hat sketches; IoS at the two sketch views (48 px) after `--checkpoints` iterations;
- carve: no prompt, sketches of a slab through the top of the sphere (tests/engine/test_edit.py's carving test);
  the emptied share at the sketch views, 1 - (the edit's opacity in the masks) / (the base's).

Both are measured inside one run of the last checkpoint's length (the schedules follow that length), with the PSNR
of the edit against its base outside the masks beside them. `--previous`: an earlier results file whose runs this
one does not repeat are kept (under their own names and commit: the whole-field copy does not change with the local
residual's settings, and an earlier local residual is named by what it was).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Dict, List

import harness
import numpy as np
import torch

RESOLUTION = 48
"""The sketch views' render size (the tests' edit metrics)."""


def carve_sketches(folder: Path) -> Path:
    """Two sketch views of a slab through the top of the demo sphere (its base holds it): the carving test's."""
    from sked_ns.demo.scenes import sphere
    from sked_ns.sketches.sketch_set import SketchSet, SketchView, save_sketch_set

    def cap_sdf(points):
        local = points - points.new_tensor([0.0, 0.0, 0.42])
        return torch.maximum(local[..., :2].norm(dim=-1) - 0.3, local[..., 2].abs() - 0.12)

    views = []
    for azimuth, elevation in ((20.0, 20.0), (110.0, 30.0)):
        pose = sphere.orbit_pose(azimuth, elevation, 2.4)
        mask = sphere.render(cap_sdf, pose, 76.8, 64, 64)["hit"].numpy()
        views.append(SketchView(mask=mask, camera_to_world=pose, fl_x=76.8, fl_y=76.8, cx=32, cy=32))
    save_sketch_set(SketchSet(views=views, frame="data"), folder, overwrite=True)
    return folder


@torch.no_grad()
def sketch_figures(model) -> Dict[str, List[float]]:
    """Per sketch view: IoS of the edit, the edit's and the base's mean opacity in the mask, and the PSNR of the edit
    against its base outside the mask (what it keeps)."""
    from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_outside
    from sked_ns.evaluation.render import render_at, render_base_at, resized_mask

    figures: Dict[str, List[float]] = {"ios": [], "opacity": [], "base_opacity": [], "psnr_outside": []}
    for view in model.sketch_set.views:
        mask = resized_mask(view, RESOLUTION)
        edit, base = render_at(model, view, RESOLUTION), render_base_at(model, view, RESOLUTION)
        figures["ios"].append(intersection_over_sketch(edit["accumulation"], mask))
        figures["opacity"].append(float(edit["accumulation"].reshape(mask.shape)[mask].mean()))
        figures["base_opacity"].append(float(base["accumulation"].reshape(mask.shape)[mask].mean()))
        figures["psnr_outside"].append(psnr_outside(edit["rgb"], base["rgb"], mask))
    return figures


def run(work: Path, base: Path, sketches: Path, task: str, field: str, seed: int, checkpoints: List[int]) -> Dict:
    """One edit, measured after each checkpoint's iterations."""
    from sked_ns.engine.edit_run import edit_config, run_edit

    carving = task == "carve"
    config = edit_config(base, work / "data", sketches, work / "edits" / f"{task}-{field}-{seed}",
                         iterations=max(checkpoints), guidance="stable-diffusion" if carving else "reference",
                         guidance_resolution=24, silhouette_resolution=24, steps_per_save=10**6)
    config.machine.seed = seed
    config.pipeline.model.nerf_edit_field = field
    measured: Dict[int, Dict] = {}
    start = time.perf_counter()

    trainer = config._target

    def train_iteration(self, step: int):
        result = trainer.train_iteration(self, step)
        if step + 1 in checkpoints:
            model = self.pipeline.model
            mode = model.training
            model.eval()
            measured[step + 1] = {**sketch_figures(model), "seconds": time.perf_counter() - start}
            print(f"{task} {field} seed {seed} after {step + 1}: {measured[step + 1]}", flush=True)
            model.train(mode)
        return result

    run_edit(config, type("MeasuredTrainer", (trainer,), {"train_iteration": train_iteration}))
    return {str(step): measured[step] for step in sorted(measured)}


def summary(results: Dict, checkpoints: List[int]) -> List[List[str]]:
    """Table rows: per task, field and checkpoint, the figure's mean over seeds and views, with its range over seeds."""
    rows = []
    for task, figure in (("fill", "ios"), ("carve", "emptied")):
        for field, seeds in results.get(task, {}).items():
            for step in checkpoints:
                runs = [run[str(step)] for run in seeds.values() if str(step) in run]  # a kept run may lack one
                if not runs:
                    continue
                values = [per_seed(run, figure) for run in runs]
                kept = [np.mean(run["psnr_outside"]) for run in runs if "psnr_outside" in run]
                rows.append([task, field, step, f"{np.mean(values):.3f}", f"{min(values):.3f}-{max(values):.3f}",
                             f"{np.mean(kept):.1f}" if kept else "-", len(values)])
    return rows


def per_seed(figures: Dict, figure: str) -> float:
    """A run's figure at one checkpoint, over its sketch views: IoS, or the emptied share of the base's opacity."""
    if figure == "ios":
        return float(np.mean(figures["ios"]))
    return float(1.0 - np.sum(figures["opacity"]) / max(np.sum(figures["base_opacity"]), 1e-9))


def keep(results: Dict, previous: Dict, names: Dict[str, str]) -> None:
    """The runs of `previous` this one did not make, its fields renamed by `names`, with the commit they ran at."""
    commit = previous.get("environment", {}).get("commit", "unknown")
    for task in ("fill", "carve"):
        for field, seeds in previous.get(task, {}).items():
            name = names.get(field, field)
            if name not in results.get(task, {}):
                results.setdefault(task, {})[name] = seeds
                results.setdefault("kept_from", {})[f"{task}/{name}"] = commit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--fields", nargs="+", default=["local", "full-copy"])
    parser.add_argument("--tasks", nargs="+", default=["fill", "carve"])
    parser.add_argument("--checkpoints", type=int, nargs="+", default=[30, 100])
    parser.add_argument("--workdir", type=Path, default=None, help="reuse the base built there")
    parser.add_argument("--out", type=Path, default=harness.RESULTS / "local_pace.json")
    parser.add_argument("--previous", type=Path, default=None, help="an earlier results file to keep runs from")
    parser.add_argument("--rename", nargs=2, action="append", default=[], metavar=("FIELD", "NAME"),
                        help="a field of --previous kept under another name (e.g. the residual's earlier settings)")
    args = parser.parse_args()
    harness.claim("local_pace.py", args.out, args.workdir)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from sked_ns.demo.base import build_demo_base
    from sked_ns.demo.scenes import sphere
    from sked_ns.sketches.sketch_set import save_sketch_set

    results: Dict = {"protocol": {"base": "demo nerfacto (tests' tiny), 400 steps", "guidance": "reference (fill)",
                                  "render_px": 24, "measured_px": RESOLUTION, "checkpoints": args.checkpoints}}
    with harness.work_folder(args.workdir) as work:
        built = sorted((work / "bases").glob("*/nerfacto/*/config.yml"))
        if not built:
            sphere.write_demo_dataset(work / "data")
        base = built[-1].parent if built else build_demo_base(work / "data", work / "bases", steps=400,
                                                              points_per_step=4096)
        save_sketch_set(sphere.demo_sketch_set(size=64), work / "hat", overwrite=True)
        sketches = {"fill": work / "hat", "carve": carve_sketches(work / "cap")}
        for task in args.tasks:
            for field in args.fields:
                for seed in args.seeds:
                    figures = run(work, base, sketches[task], task, field, seed, args.checkpoints)
                    results.setdefault(task, {}).setdefault(field, {})[str(seed)] = figures
                    print(task, field, seed, {step: per_seed(f, "ios" if task == "fill" else "emptied")
                                              for step, f in figures.items()}, flush=True)
    if args.previous is not None:
        keep(results, json.loads(args.previous.read_text()), dict(args.rename))
    rows = summary(results, args.checkpoints)
    results["summary"] = [dict(zip(("task", "field", "iterations", "mean", "range", "psnr_outside", "seeds"), row))
                          for row in rows]
    harness.publish(results, args.out)
    harness.report(harness.markdown_table(["task", "field", "iterations", "IoS / emptied share", "range over seeds",
                                           "PSNR outside (dB)", "seeds"], rows), args.out)


if __name__ == "__main__":
    main()
