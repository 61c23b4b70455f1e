"""Where an unbounded scene's leak comes from, and when a small part forms (issue 22, scene `lawn`).

    python benchmarks/unbounded_leak.py candidates      # one cpu-100 edit per floater candidate (~4 min each here)
    python benchmarks/unbounded_leak.py where RUN       # where an edit's new mass lies along the eval cameras' rays
    python benchmarks/unbounded_leak.py parts RUN       # the lamp's stem and ball: formed at the sketch views?

Run `benchmarks/edit_quality.py --scenes lawn --work W` first (it writes the scene and trains its base under
W/lawn); pass the same `--work`. `candidates` edits that base as edit_quality's cpu-100 default does, each with
one change, scored by `sked-eval --target` like edit_quality (rows in --output):

- `clip-random`: the random views' rays end where they leave the scene box (no far, contracted samples);
- `no-boost`: no proposal boost in the sketches' hull (`--pipeline.model.edit-box-density 0`);
- `lambda-sp-0`: no L_sp; `no-photo`: no photo anchor (so none of its far rays);
- `mean-appearance`: every photo's appearance embedding set to their mean (edit and frozen base);
- `default-seed1`: the default with other random views (how much a figure moves by chance alone);
- `default-32px`: the default at 32 px renders (the issue's protocol) instead of 24.
- `sketch-sil`: L_sil per sketch pixel (the README's option for small parts), for the small-part figures.

The first and fifth change code, not flags: they are patched into the `ns-train` process (`PATCHES`), for this
measurement only.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Dict

import edit_quality as eq
import harness
import numpy as np
import torch

CANDIDATES = {
    "default": ("", []),
    "clip-random": ("clip_random_views", []),
    "no-boost": ("", ["--pipeline.model.edit-box-density", "0"]),
    "lambda-sp-0": ("", ["--pipeline.model.lambda-sp", "0"]),
    "no-photo": ("", ["--pipeline.model.lambda-photo", "0"]),
    "mean-appearance": ("mean_appearance", []),
    "default-seed1": ("", ["--pipeline.datamanager.seed", "1"]),
    "default-32px": ("", ["--pipeline.model.guidance-resolution", "32", "--pipeline.model.silhouette-resolution", "32"]),
    "sketch-sil": ("", ["--pipeline.model.silhouette-normalisation", "sketch"]),
    # Adam moves every hash entry that gets any gradient by about its rate (eps 1e-15): far entries touched only by
    # tiny, noisy gradients random-walk. A larger eps scales such steps down with their gradient.
    "no-guidance": ("", ["--pipeline.model.guidance.weight", "0"]),
    "one-iteration": ("", ["--max-num-iterations", "1"]),  # what the edit's set-up and first step alone change
    "one-iteration-lr-0": ("", ["--max-num-iterations", "1", "--optimizers.hash-grids.optimizer.lr", "1e-12",
                                "--optimizers.fields.optimizer.lr", "1e-12",
                                "--optimizers.proposal-networks.optimizer.lr", "1e-12"]),  # the set-up alone
    "no-sil": ("", ["--pipeline.model.lambda-sil", "0"]),
    # Adam's first step moves every parameter with any gradient by its full rate (m / sqrt(v) = sign(g)): a warm-up
    # of the edit's learning rates keeps that first jolt off the far field's hash entries.
    "warmup-10": ("", [f"--optimizers.{group}.scheduler.warmup-steps" if i == 0 else "10"
                       for group in ("hash-grids", "fields", "proposal-networks") for i in range(2)]),
    "grid-eps-1e-9": ("", ["--optimizers.hash-grids.optimizer.eps", "1e-9"]),
    "grid-eps-1e-7": ("", ["--optimizers.hash-grids.optimizer.eps", "1e-7"]),
    # The fix (held_field.py): samples far from the sketches are the base's. The rows above ran without it, as this.
    "soft-hold": ("", ["--pipeline.model.keep-threshold", "1"]),
}


# ---- the code candidates, patched into the ns-train process ------------------------------------
def clip_random_views() -> None:
    """The random views' rays end where they leave the scene box."""
    from sked_ns.models.nerf.field_edit import SkedMixin
    from sked_ns.sketches.cameras import ray_aabb

    original = SkedMixin._collide

    def _collide(self, ray_bundle):
        ray_bundle = original(self, ray_bundle)
        if self.training and len(ray_bundle) == self.config.guidance_resolution ** 2:  # the random view's rays
            aabb = self.scene_box.aabb.reshape(-1).to(ray_bundle.origins)
            _, exit_ = ray_aabb(ray_bundle.origins.reshape(-1, 3), ray_bundle.directions.reshape(-1, 3), aabb)
            nearest = float(ray_bundle.nears.max()) + 1e-3
            ray_bundle.fars = torch.minimum(ray_bundle.fars, exit_.reshape(ray_bundle.fars.shape).clamp_min(nearest))
        return ray_bundle

    SkedMixin._collide = _collide


def mean_appearance() -> None:
    """Every photo's appearance embedding set to their mean, in the edit and its frozen base."""
    from sked_ns.models.nerf.nerfacto import SkedNerfactoModel

    original = SkedNerfactoModel.populate_modules

    def populate_modules(self):
        original(self)
        for field in (self.field, self.frozen_base.field):
            with torch.no_grad():
                weight = field.embedding_appearance.embedding.weight
                weight[:] = weight.mean(dim=0, keepdim=True)

    SkedNerfactoModel.populate_modules = populate_modules


def ns_train(arguments, patch: str):
    """`ns-train ARGUMENTS` with the code candidate PATCH (a function of this module) applied first."""
    setup = f"import sys; sys.path.insert(0, {str(harness.BENCHMARKS)!r}); import unbounded_leak; unbounded_leak.{patch}()\n"
    return harness.ns_train_command(arguments, setup if patch else "")


def candidates(work: Path, output: Path, names) -> None:
    scene_work = work / "lawn"
    paths = {key: scene_work / key for key in ("data", "target", "sketches")}
    base = scene_work / "runs" / "base" / "nerfacto" / "base"
    if not (base / "nerfstudio_models").exists():
        raise SystemExit(f"no base at {base}: run benchmarks/edit_quality.py --scenes lawn --work {work} first")
    rows = json.loads(output.read_text()) if output.exists() else []
    for name in names:
        patch, flags = CANDIDATES[name]
        start = time.perf_counter()
        out = scene_work / "candidates" / name
        eq.run(ns_train(eq.edit_arguments(base, paths, "lawn", eq.PROTOCOLS["cpu-100"], out, flags), patch),
               scene_work / f"cand-{name}.log")
        edit_run = max((out / "lawn" / "sked").iterdir())
        metrics = eq.score(edit_run, paths, scene_work / f"cand-{name}.eval.json", scene_work / f"cand-{name}.eval.log")
        rows.append({"tag": name, "patch": patch, "flags": flags, "seconds": time.perf_counter() - start,
                     "summary": eq.summarise(metrics), "where": where(edit_run), "parts": parts(edit_run, work)["mean"]})
        harness.write_results(output, rows)
        print(name, json.dumps({key: rows[-1]["summary"][key] for key in ("leak", "psnr_keep_drop", "psnr_target_changed")}))


LEAK_PIXEL = 0.02


# ---- measurements on one edit ------------------------------------------------------------------
@torch.no_grad()
def where(edit_run: Path, resolution: int = 48) -> Dict[str, float]:
    """Per kept pixel of the eval cameras (P > KEEP_THRESHOLD in edit and base, as sked-eval): the leak, and the edit's
    weight at samples where its density exceeds the base's ("new mass", the part above the base's density), split into
    inside the scene box (|x|_inf <= 1, not contracted) and the contracted far field, and by depth; and at the kept
    pixels whose opacity grew by more than LEAK_PIXEL, the edit's and the base's mean colour error against the photo."""
    from nerfstudio.field_components.field_heads import FieldHeadNames

    from sked_ns.evaluation.novel_views import KEEP_THRESHOLD, _rescaled, _resize
    from sked_ns.evaluation.render import load_pipeline

    pipeline = load_pipeline(edit_run)
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    totals: Dict[str, list] = {}
    for index in range(len(dataset)):
        camera = _rescaled(dataset.cameras[index], resolution)
        rays = model._collide(camera.generate_rays(camera_indices=0, keep_shape=True).flatten())
        outputs, samples, field_outputs, weights = model._render_with(rays, model.field, model.density_fns)
        base = model.render_base(rays)
        positions = samples.frustums.get_positions()
        density, density_base = field_outputs[FieldHeadNames.DENSITY], model.base_field(samples)[FieldHeadNames.DENSITY]
        new = weights * (density - density_base).clamp_min(0) / density.clamp_min(1e-8)
        keep = ((model.expected_preservation(positions, weights, outputs["accumulation"]) > KEEP_THRESHOLD)
                & (base["preservation_weight"] > KEEP_THRESHOLD))[..., 0]
        inside = positions.abs().amax(-1, keepdim=True) <= 1.0
        depth = samples.frustums.starts
        figures = {"leak": (outputs["accumulation"] - base["accumulation"]).clamp_min(0)[..., 0],
                   "base_accumulation": base["accumulation"][..., 0],
                   "new_mass": new.sum(-2)[..., 0], "new_mass_in_box": (new * inside).sum(-2)[..., 0],
                   "new_mass_contracted": (new * ~inside).sum(-2)[..., 0],
                   "new_mass_depth_over_3": (new * (depth > 3)).sum(-2)[..., 0]}
        for key, value in figures.items():
            totals.setdefault(key, []).append(float(value[keep].mean()) if keep.any() else 0.0)
        # Where the edit added opacity, is its colour nearer the photo (the truth at kept pixels) than the base's?
        photo = torch.from_numpy(_resize(dataset.get_image_float32(index).numpy()[..., :3], camera)).reshape(-1, 3)
        leaking = keep & (figures["leak"] > LEAK_PIXEL)
        if leaking.any():
            totals.setdefault("leak_pixels_error_edit", []).append(float((outputs["rgb"] - photo).abs()[leaking].mean()))
            totals.setdefault("leak_pixels_error_base", []).append(float((base["rgb"] - photo).abs()[leaking].mean()))
            totals.setdefault("leak_pixels_fraction", []).append(float(leaking.float().mean()))
    return {key: float(np.mean(values)) for key, values in totals.items()}


def parts(edit_run: Path, work: Path, resolution: int = 64) -> Dict:
    """Per sketch view, over the pixels where the exact target shows the lamp's stem (a few pixels wide) and its ball:
    the mean editable opacity (1 - P) of edit and base, and the fraction of those pixels above 0.5 ("formed")."""
    from sked_ns.demo.scenes.objects import visible_added_part
    from sked_ns.demo.scenes.unbounded import SCENES
    from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at
    from sked_ns.sketches.sketch_set import load_sketch_set, sketch_view_at

    scene = SCENES["lawn"]
    stem, ball = scene.edit_parts
    model = load_pipeline(edit_run).model
    views = []
    for data_view, model_view in zip(load_sketch_set(work / "lawn" / "sketches").views, model.sketch_set.views):
        camera, _ = sketch_view_at(data_view, resolution)
        truth = visible_added_part(scene, np.asarray(data_view.camera_to_world)[:3], float(camera.fx),
                                   int(camera.width), int(camera.height))
        on_stem = truth["visible"] & (stem.sdf(truth["points"]) < ball.sdf(truth["points"]))
        editable = 1.0 - render_at(model, model_view, resolution)["preservation_weight"]
        editable_base = 1.0 - render_base_at(model, model_view, resolution)["preservation_weight"]
        view = {"view": data_view.name}
        for name, where_ in (("stem", on_stem), ("ball", truth["visible"] & ~on_stem)):
            view.update({f"{name}_pixels": int(where_.sum()), f"{name}_opacity": float(editable[where_].mean()),
                         f"{name}_opacity_base": float(editable_base[where_].mean()),
                         f"{name}_formed": float((editable[where_] > 0.5).float().mean())})
        views.append(view)
    return {"views": views, "mean": {key: float(np.mean([v[key] for v in views])) for key in views[0] if key != "view"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("candidates", "where", "parts"))
    parser.add_argument("run", nargs="?", type=Path, help="an edit run (where, parts)")
    parser.add_argument("--work", type=Path, default=Path("benchmark_work"))
    parser.add_argument("--output", type=Path, default=eq.RESULTS / "unbounded_leak.json")
    parser.add_argument("--candidates", default=",".join(CANDIDATES))
    args = parser.parse_args()
    if args.command == "candidates":
        harness.claim("unbounded_leak.py", args.output, args.work)
        candidates(args.work, args.output, args.candidates.split(","))
    elif args.run is None:
        raise SystemExit(f"{args.command} needs an edit run (a folder holding config.yml)")
    else:
        print(json.dumps(where(args.run) if args.command == "where" else parts(args.run, args.work), indent=1))


if __name__ == "__main__":
    main()
