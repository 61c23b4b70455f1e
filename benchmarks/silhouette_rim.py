"""Where an edit's error against its target lies: on the added part's silhouette rim or inside it.

    python benchmarks/silhouette_rim.py --work WORK --scene hat --tags long-local-field long-full-copy

Reads the edits `edit_quality.py` made under WORK (its --work; the newest run of each tag) and renders each at the
target's cameras at sked-eval's novel-view size (edit_quality.py scores at 96 px). Per view, inside the target's
changed region: its PSNR (edit_quality's "changed region vs target"), the share of its squared error on the region's
one-pixel rim and in its interior (each a sum over those pixels over the region's pixel count, so the two add up
to the region's mean squared error), and the edit's fill on the rim (its colour's projection from the base's onto
the target's: 1 where the rim shows the part as the target does, below 1 where it shows less); outside the region, on
the one-pixel band around it, the squared error against the target (where an edit that overshoots the silhouette
shows it; edit_quality counts it as unchanged region). Writes benchmarks/results/silhouette_rim_<scene>.json.

`--final-samples 1 4` renders each edit of a nerfacto base again with its field's samples per ray multiplied by each
factor, in the edit's renders and its base's (the proposal samples as saved; the edit's folder is not touched): how
much of its error is the render's sampling rather than what it learnt.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Dict, List

import cv2
import harness
import numpy as np
import torch

RING = np.ones((3, 3), np.uint8)
NOVEL_RESOLUTION = 96
"""edit_quality.py's `--novel-resolution`."""
MAX_VIEWS = 12
"""sked-eval's `--max-novel-views` default, which edit_quality.py keeps: the same views it scores."""


@torch.no_grad()
def rim_figures(pipeline, target: Path, resolution: int = NOVEL_RESOLUTION) -> List[Dict]:
    """The figures of each of the target's views (module docstring) for a loaded edit."""
    from sked_ns.evaluation.evaluate import choose_novel_views
    from sked_ns.evaluation.render import render_camera

    views, _ = choose_novel_views(pipeline, None, target, resolution, MAX_VIEWS)
    figures = []
    for view in views:
        if view.changed is None:
            raise SystemExit(f"error: {target}: frame {view.name} has no changed_mask_path; the benchmark scenes' targets "
                             "(edit_quality.py's --work) have one for every frame")
        edit = render_camera(pipeline.model, view.camera)["rgb"].numpy()
        base = render_camera(pipeline.model, view.camera, base=True)["rgb"].numpy()
        figures.append({"view": view.name, **view_figures(edit, base, view.ground_truth.numpy(), view.changed.numpy())})
    return figures


def field_sampler(pipeline, edit_run: Path, factors: List[int]):
    """The edit's proposal sampler, whose field samples per ray `--final-samples` multiplies; None where every factor
    is 1. An edit without one (not of a nerfacto base) is refused in one line."""
    sampler = getattr(pipeline.model, "proposal_sampler", None)
    if sampler is None and max(factors) > 1:
        raise SystemExit(f"error: --final-samples {max(factors)}: {edit_run} is not an edit of a nerfacto base (only a "
                         "proposal sampler's field samples are counted per ray); leave it at 1")
    return sampler


def view_figures(edit: np.ndarray, base: np.ndarray, truth: np.ndarray, changed: np.ndarray) -> Dict:
    """One view's figures from its renders and target (H, W, 3) and the target's changed region (H, W) bool."""
    region = changed.astype(bool)
    mask = region.astype(np.uint8)
    rim = region & ~(cv2.erode(mask, RING) > 0)
    band = (cv2.dilate(mask, RING) > 0) & ~region
    error = ((edit - truth) ** 2).mean(-1)
    towards = truth - base
    fill = ((edit - base) * towards).sum(-1) / np.maximum((towards * towards).sum(-1), 1e-6)
    return {"psnr_changed": float(-10.0 * np.log10(max(float(error[region].mean()), 1e-12))),
            "rim_share": float(error[rim].sum() / region.sum()),
            "interior_share": float(error[region & ~rim].sum() / region.sum()),
            "rim_fill": float(fill[rim].mean()), "band_error": float(error[band].mean()),
            "rim_pixels": int(rim.sum()), "region_pixels": int(region.sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="edit_quality.py's --work folder")
    parser.add_argument("--scene", default="hat")
    parser.add_argument("--tags", nargs="+", required=True, help="edit_quality.py's run tags, e.g. long-local-field")
    parser.add_argument("--final-samples", type=int, nargs="+", default=[1],
                        help="factors on the field's samples per ray of a nerfacto edit's renders (default 1: as saved)")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()
    if min(args.final_samples) < 1:
        raise SystemExit(f"error: --final-samples {min(args.final_samples)}: factors are whole numbers >= 1")
    scene_work = args.work / args.scene
    runs = {}
    for tag in args.tags:
        edits = scene_work / "edits" / tag / args.scene / "sked"
        if not edits.is_dir():
            raise SystemExit(f"error: --tags {tag}: no edit_quality.py edit at {edits}; run edit_quality.py with "
                             f"--work {args.work} first")
        runs[tag] = max(edits.iterdir())
    from sked_ns.evaluation.render import load_pipeline

    # Each edit loaded once, and checked, before the results file is claimed.
    pipelines = {tag: load_pipeline(run) for tag, run in runs.items()}
    samplers = {tag: field_sampler(pipeline, runs[tag], args.final_samples) for tag, pipeline in pipelines.items()}
    output = args.output or harness.RESULTS / f"silhouette_rim_{args.scene}.json"
    harness.claim("silhouette_rim.py", output)
    target = scene_work / "target" / "transforms.json"
    edits = {}
    for tag, pipeline in pipelines.items():
        sampler = samplers[tag]
        saved = None if sampler is None else sampler.num_nerf_samples_per_ray
        for factor in args.final_samples:
            if sampler is not None:  # in memory only: the saved edit is not changed
                sampler.num_nerf_samples_per_ray = saved * factor
            name = tag if factor == 1 else f"{tag} x{factor} field samples"
            edits[name] = {"run": str(runs[tag]), "final_samples": factor, "views": rim_figures(pipeline, target)}
    result = {"scene": args.scene, "novel_resolution": NOVEL_RESOLUTION, "environment": harness.environment("cpu"),
              "edits": edits}
    harness.write_results(output, result)
    rows = [(name, view["view"], f"{view['psnr_changed']:.2f}", f"{view['rim_share']:.5f}",
             f"{view['interior_share']:.5f}", f"{view['rim_fill']:.3f}", f"{view['band_error']:.4f}")
            for name, entry in result["edits"].items() for view in entry["views"]]
    rows += [(name, "mean of the views", f"{np.mean([v['psnr_changed'] for v in entry['views']]):.2f}", "", "", "", "")
             for name, entry in result["edits"].items()]
    harness.report(harness.markdown_table(("edit", "view", "changed region vs target (dB)", "rim share of MSE",
                                           "interior share of MSE", "rim fill", "band outside: MSE"), rows), output)


if __name__ == "__main__":
    main()
