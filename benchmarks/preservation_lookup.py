"""Preservation weights of 1M points: our distance-transform lookup vs the authors' two methods.

The authors compute d_j per sample either with `torch.cdist` to every mask pixel then a
min, or with a SciPy KD-tree over the mask pixels. We precompute one exact Euclidean
distance transform per view and look it up. Sketches are the demo hat seen from 2 or 4
views at 128 and 512 px; points are uniform in [-1, 1]^3.

    python benchmarks/preservation_lookup.py [--points 1000000] [--output benchmarks/results/preservation_lookup.json]

Ours is timed eager and compiled (torch.compile, one-time compile cost reported apart).
Prints a table and writes JSON. cdist on the CPU is timed on a subset and scaled
linearly to the full count (it is exactly linear in points); the table says so.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import harness
import numpy as np
import torch
from harness import sync
from scipy.spatial import cKDTree

from sked_ns.demo.scenes.sphere import demo_sketch_set
from sked_ns.method.preservation import SketchDistanceField

VIEW_ANGLES = ((20.0, 20.0), (110.0, 30.0), (200.0, 25.0), (290.0, 35.0))
CDIST_CHUNK = 2048


def timed(function, repeats: int, device: str) -> tuple[float, object]:
    """Median wall time in seconds over `repeats` runs (after one warm-up run), and the last run's result."""
    results = []
    times = harness.timed_calls(lambda: results.append(function()), repeats, device)
    return statistics.median(times), results[-1]


def pixel_indices(field: SketchDistanceField, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The same float32 projection as our lookup, so all methods measure from the same pixels."""
    projected = torch.einsum("cvk,mk->cvm", field.projection_rows[..., :3], points) + field.projection_rows[..., 3:]
    return (projected[:2] * projected[2].reciprocal()).permute(1, 2, 0).floor(), projected[2]


def kdtree_distance(views, field, points) -> np.ndarray:
    """The authors' KD-tree method (one query per view, mean over views), in image widths."""
    pixels, _ = pixel_indices(field, points)
    per_view = []
    for j, view in enumerate(views):
        rows, cols = np.nonzero(view.mask)
        tree = cKDTree(np.stack([cols, rows], 1).astype(np.float64))
        distance, _ = tree.query(pixels[j].numpy().astype(np.float64), workers=1)
        per_view.append(distance / view.width)
    return np.mean(per_view, axis=0)


def cdist_distance(views, field, points) -> torch.Tensor:
    """The authors' brute-force method: cdist to every mask pixel, then min (chunked)."""
    pixels, _ = pixel_indices(field, points)
    per_view = []
    for j, view in enumerate(views):
        rows, cols = np.nonzero(view.mask)
        mask_pixels = torch.tensor(np.stack([cols, rows], 1), dtype=torch.float32, device=points.device)
        chunks = [torch.cdist(chunk, mask_pixels).min(dim=1).values for chunk in pixels[j].split(CDIST_CHUNK)]
        per_view.append(torch.cat(chunks) / view.width)
    return torch.stack(per_view).mean(0)


def run_case(resolution: int, num_views: int, num_points: int, device: str, cdist_points: int) -> dict:
    views = demo_sketch_set(size=resolution, views=VIEW_ANGLES[:num_views]).views
    generator = torch.Generator().manual_seed(0)
    points_cpu = torch.rand(num_points, 3, generator=generator) * 2 - 1

    start = time.perf_counter()
    field = SketchDistanceField(views)
    setup_s = time.perf_counter() - start
    field = field.to(device)
    points = points_cpu.to(device)
    eager_s, ours = timed(lambda: field.distance(points), repeats=7, device=device)
    ours = ours.cpu()
    compiled = SketchDistanceField(views, compile=True).to(device)
    start = time.perf_counter()
    compiled_out = compiled.distance(points)
    sync(device)
    compile_s = time.perf_counter() - start
    ours_s, _ = timed(lambda: compiled.distance(points), repeats=7, device=device)
    finite = torch.isfinite(ours)
    assert torch.equal(torch.isinf(compiled_out.cpu()), torch.isinf(ours))
    compiled_diff = (compiled_out.cpu()[finite] - ours[finite]).abs().max().item()

    row = {
        "device": device,
        "resolution": resolution,
        "views": num_views,
        "points": num_points,
        "mask_pixels": int(sum(view.mask.sum() for view in views)),
        "ours_setup_s": setup_s,
        "ours_eager_s": eager_s,
        "ours_compile_once_s": compile_s,
        "ours_s": ours_s,
        "max_abs_diff_compiled_vs_eager": compiled_diff,
    }
    field_cpu = field.to("cpu")
    if device == "cpu":
        kd_s, kd = timed(lambda: kdtree_distance(views, field_cpu, points_cpu), repeats=1, device="cpu")
        # Same values wherever a point lands inside every image (outside, ours is the documented upper bound).
        pixels, depth = pixel_indices(field_cpu, points_cpu)
        inside = ((pixels >= 0).all(-1) & (pixels[..., 0] < field_cpu.sizes[0])
                  & (pixels[..., 1] < field_cpu.sizes[1]) & (depth > 0)).all(0)
        difference = (ours[inside] - torch.tensor(kd, dtype=torch.float32)[inside]).abs().max().item()
        row.update(kdtree_s=kd_s, speedup_vs_kdtree=kd_s / ours_s, eager_speedup_vs_kdtree=kd_s / eager_s,
                   max_abs_diff_vs_kdtree=difference,
                   fraction_compared=inside.float().mean().item(),
                   ours_never_below_kdtree=bool((ours + 1e-6 >= torch.tensor(kd, dtype=torch.float32)).all()))
    subset = points[:cdist_points]
    cd_s, cd = timed(lambda: cdist_distance(views, field.to(device), subset), repeats=1, device=device)
    row.update(cdist_s=cd_s * num_points / len(subset), cdist_points_timed=len(subset),
               speedup_vs_cdist=cd_s * num_points / len(subset) / ours_s)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--cdist-points", type=int, default=65_536, help="points cdist is timed on, on the CPU")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "preservation_lookup.json")
    args = parser.parse_args()
    harness.claim("preservation_lookup.py", args.output)

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows = []
    for device in devices:
        for resolution in (128, 512):
            for num_views in (2, 4):
                cdist_points = args.points if device == "cuda" else min(args.cdist_points, args.points)
                rows.append(run_case(resolution, num_views, args.points, device, cdist_points))
                r = rows[-1]
                print(f"{device:4s} {resolution:4d}px {num_views} views: ours {r['ours_s'] * 1e3:8.1f} ms "
                      f"(eager {r['ours_eager_s'] * 1e3:.1f} ms)"
                      + (f" | kd-tree {r['kdtree_s']:7.2f} s ({r['speedup_vs_kdtree']:6.0f}x)" if "kdtree_s" in r else "")
                      + f" | cdist {r['cdist_s']:7.2f} s ({r['speedup_vs_cdist']:6.0f}x)", flush=True)

    harness.write_results(args.output, {
        "benchmark": "preservation_lookup",
        "command": "python benchmarks/preservation_lookup.py",
        "environment": harness.environment(devices[-1]),
        "kdtree": "scipy cKDTree, workers=1 (as the authors' code)",
        "rows": rows,
    })
    harness.report("\n" + table(rows) + "\n* cdist timed on a subset and scaled linearly to the full point count.\n"
                   "Speed-ups use the compiled lookup (one-time compile excluded, listed in the JSON); eager ones are in "
                   "the JSON.", args.output)


def table(rows: list) -> str:
    cells = []
    for r in rows:
        kd = [f"{r['kdtree_s']:.2f}", f"{r['speedup_vs_kdtree']:.0f}"] if "kdtree_s" in r else ["-", "-"]
        diff = f"{r['max_abs_diff_vs_kdtree']:.1e}" if "max_abs_diff_vs_kdtree" in r else "-"
        scaled = "*" if r["cdist_points_timed"] < r["points"] else ""
        cells.append([r["device"], r["resolution"], r["views"], r["mask_pixels"], f"{r['ours_setup_s']:.3f}",
                      f"{r['ours_s'] * 1e3:.1f}", f"{r['ours_eager_s'] * 1e3:.1f}", *kd, f"{r['cdist_s']:.2f}{scaled}",
                      f"{r['speedup_vs_cdist']:.0f}", diff])
    return harness.markdown_table(["device", "px", "views", "mask px", "ours setup (s)", "ours compiled (ms)",
                                   "ours eager (ms)", "KD-tree (s)", "x KD-tree", "cdist (s)", "x cdist",
                                   "max |diff| vs KD-tree"], cells)


if __name__ == "__main__":
    main()
