"""Sketch sets on instant-ngp's fox, made programmatically as the benchmark needs them, and their checks.

    python benchmarks/capture_fox.py sketches DATA OUT [--views 0001 0025]   # a hat region on the fox's head
    python benchmarks/capture_fox.py check DATA SKETCHES                     # placement and edit box, both frames
    python benchmarks/capture_fox.py edit DATA SKETCHES BASE OUT [--iterations 100] [--output results.json]
    python benchmarks/capture_fox.py measure results.json [--strip strip.png]   # that edit measured again, in place

DATA is the dataset `benchmarks/capture_prep.py` wrote. A sketch view stands where a photo was taken (its
camera, as a user snaps the viewer to a training camera before sketching), and its mask is the silhouette of a
ball over the fox's forehead, where a hat would go: `HAT` in the data frame of the fox's transforms.json,
found by projecting it onto the photos (its place is relative to the point the cameras look at). The masks are
pinhole silhouettes of the ball on the photo's camera without its lens, as the viewer shows a view.

`check` reads the set as an edit of a nerfacto base does (the data frame mapped by nerfstudio-data with each
--center-method) and prints what the placement checks and the edit box say: the warnings the set gives, whether the
box holds the ball, and where the point the cameras look at (the fox) lands in nerfstudio's frame.

`edit` runs `ns-train sked` of BASE towards the composite target (a cone in the edit box,
`pipeline.model.guidance:reference --pipeline.model.guidance.primitive cone`; --primitive hull: the sketches' hull) at
a CPU's protocol (RESOLUTION px guidance renders, SILHOUETTE_RESOLUTION px sketch views, SAMPLES_PER_RAY_SCALE of the
base's samples), in this process as `ns-train` runs
it, timing each step and the process's peak resident memory while the steps run; with --output it then measures
the edit (`capture_measure.py`: held-out photos and the sketch views; --strip: its picture strip).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import resource
import sys
import time
import warnings
from pathlib import Path
from typing import Sequence

import harness
import numpy as np
import torch

from sked_ns.demo.composite_target import PRIMITIVES
from sked_ns.demo.scenes.objects import sphere
from sked_ns.demo.scenes.sphere import trace
from sked_ns.sketches.sketch_set import SketchSet, SketchView, load_sketch_set, save_sketch_set

HAT = ((0.68, -0.855, 1.45), 0.35)
"""(centre, radius) of the hat region in the fox's data frame: over the forehead, between the ears."""
RESOLUTION = 24
"""Guidance render side, px: edit_quality.py's CPU protocols (the random views frame the edit box)."""
SILHOUETTE_RESOLUTION = 64
"""Sketch views' render side, px: a whole photo's frame, where the hat region's sketches cover 3-5 pixels at 24 px
(the edit warns so) and 30-40 at 64, the side capture_measure scores IoS at; L_sil renders only the masks' pixels."""
SAMPLES_PER_RAY_SCALE = 0.25
"""A NeRF base's samples per ray in the edit's renders, as edit_quality.py's CPU protocols."""
RECORDED_RUN = ("command", "run", "iterations", "resolution", "silhouette_resolution", "samples_per_ray_scale", "timing")
"""What `edit` records of the run beside its measurement (`measure` keeps it)."""
VIEWS = ("0001", "0025")
"""Two photos about 55 degrees apart along the arc: the fox's left side and its front."""


def _frames(data: Path):
    meta = json.loads((data / "transforms.json").read_text())
    return meta, {Path(frame["file_path"]).stem: np.asarray(frame["transform_matrix"])[:3] for frame in meta["frames"]}


def hat_sketches(data: Path, views: Sequence[str] = VIEWS) -> SketchSet:
    """The hat region's silhouette at each named photo's camera (pinhole, the photo's size)."""
    meta, poses = _frames(data)
    centre, radius = HAT
    sketch_views = []
    for name in views:
        if name not in poses:
            raise SystemExit(f"error: --views {name}: no photo {name} in {data / 'transforms.json'}.")
        pose = poses[name]
        hit = trace(sphere(centre, radius), lambda p: p * 0 + 1, pose, meta["fl_x"], meta["w"], meta["h"])["hit"]
        sketch_views.append(SketchView(mask=hit.numpy(), camera_to_world=pose, fl_x=meta["fl_x"], fl_y=meta["fl_x"],
                                       cx=meta["w"] / 2, cy=meta["h"] / 2, name=f"fox@{name}"))
    return SketchSet(views=sketch_views, frame="data")


def check(data: Path, sketches: Path) -> dict:
    """What the placement checks and the edit box say of the set, in the data frame and nerfstudio's."""
    from nerfstudio.cameras.camera_utils import focus_of_attention
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.models.nerfacto import NerfactoModelConfig

    from sked_ns.method.edit_box import compute_edit_box, content_bounds
    from sked_ns.sketches.placement import check_camera_placement
    from sked_ns.sketches.sketch_set import DataparserTransform

    sketch_set = load_sketch_set(sketches)
    centre, radius = HAT
    _, poses = _frames(data)
    stacked = torch.as_tensor(np.stack(list(poses.values())), dtype=torch.float32)
    looked_at = focus_of_attention(stacked, stacked[:, :3, 3].mean(dim=0)).double()
    on_hat = torch.as_tensor(centre, dtype=torch.float64) + radius * 0.95 * torch.nn.functional.normalize(
        torch.randn(2000, 3, dtype=torch.float64), dim=-1)
    report = {}
    for method in ("focus", "poses"):
        outputs = NerfstudioDataParserConfig(data=data, center_method=method).setup().get_dataparser_outputs("train")
        transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64),
                                        float(outputs.dataparser_scale))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            views = sketch_set.in_model_frame(transform).views
            check_camera_placement(views)
            box = compute_edit_box(views, *content_bounds(NerfactoModelConfig(), outputs.scene_box.aabb.numpy()))
        held = float(box.contains(transform.points_to_model(on_hat)).double().mean())
        report[method] = {"warnings": [str(w.message) for w in caught],
                          "looked_at_in_model_frame": transform.points_to_model(looked_at).numpy().round(3).tolist(),
                          "box_min": box.min.round(3).tolist(),
                          "box_max": box.max.round(3).tolist(), "hat_share_in_box": round(held, 3)}
    return report


def edit_arguments(data: Path, sketches: Path, base: Path, out: Path, iterations: int, primitive: str = "cone") -> list:
    """`ns-train sked ...` as a user types it for a measured edit of a capture on a CPU (docs/captures.md)."""
    dataparser = ["--center-method", "focus"] if "center_method: focus" in (base / "config.yml").read_text() else []
    return ["sked", "--load-dir", str(base), "--sketches", str(sketches), "--output-dir", str(out),
            "--experiment-name", "fox", "--max-num-iterations", str(iterations), "--steps-per-save", str(iterations),
            "--vis", "tensorboard", "--machine.device-type", "cpu",
            "--pipeline.model.guidance-resolution", str(RESOLUTION),
            "--pipeline.model.silhouette-resolution", str(SILHOUETTE_RESOLUTION),
            "--pipeline.model.samples-per-ray-scale", str(SAMPLES_PER_RAY_SCALE),
            "--pipeline.model.edit-box-warmup", str(max(1, iterations // 10)),
            # Random views where the photos were, relative to the first sketch view: the capture is an arc.
            "--pipeline.datamanager.azimuth-range", "-60", "60",
            "--pipeline.datamanager.elevation-range", "-10", "45",
            "pipeline.model.guidance:reference", "--pipeline.model.guidance.primitive", primitive,
            "nerfstudio-data", *dataparser, "--data", str(data)]


def _rss_peak_gb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def run_edit(arguments: list) -> dict:
    """`ns-train ARGUMENTS` in this process; each step's wall time and the peak RSS from the first step on."""
    from nerfstudio.scripts.train import entrypoint

    from sked_ns.engine.trainer import SkedTrainer
    from sked_ns.method.options import without_lpips

    times, plain = [], SkedTrainer.train_iteration
    before = {}

    def timed(trainer, step):
        if not times and "rss" not in before:
            before["rss"] = _rss_peak_gb()
            with contextlib.suppress(OSError):  # Linux: the peak counts again from here
                Path("/proc/self/clear_refs").write_text("5")
        start = time.perf_counter()
        result = plain(trainer, step)
        times.append(time.perf_counter() - start)
        return result

    SkedTrainer.train_iteration = timed
    argv, sys.argv = sys.argv, ["ns-train", *arguments]
    try:
        with without_lpips():
            entrypoint()
    finally:
        SkedTrainer.train_iteration, sys.argv = plain, argv
    settled = sorted(times[1:]) or times
    return {"steps": len(times), "first_step_s": times[0], "median_step_s": settled[len(settled) // 2],
            "mean_step_s": sum(settled) / len(settled), "peak_rss_gb_set_up": before.get("rss"),
            "peak_rss_gb_steps": _rss_peak_gb()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    make = commands.add_parser("sketches")
    make.add_argument("data", type=Path)
    make.add_argument("out", type=Path)
    make.add_argument("--views", nargs="+", default=list(VIEWS))
    test = commands.add_parser("check")
    test.add_argument("data", type=Path)
    test.add_argument("sketches", type=Path)
    test.add_argument("--output", type=Path, help="also write the report here (JSON)")
    edit = commands.add_parser("edit")
    for name in ("data", "sketches", "base", "out"):
        edit.add_argument(name, type=Path)
    edit.add_argument("--iterations", type=int, default=100)
    edit.add_argument("--primitive", choices=PRIMITIVES, default="cone",
                      help="the composite target's part (hull: the sketches' hull, which fills them; a cone, ball or "
                           "box sized from the edit box fills part of them)")
    edit.add_argument("--output", type=Path, help="measure the edit and write the results here (JSON)")
    edit.add_argument("--strip", type=Path, help="a PNG of photo | base | edit | difference at three held-out photos")
    again = commands.add_parser("measure", help="measure again the edit a results file of `edit` records, in place")
    again.add_argument("results", type=Path)
    again.add_argument("--strip", type=Path)
    arguments = parser.parse_args(argv)
    if arguments.command == "edit":
        if arguments.output is not None:
            harness.claim("capture_fox.py", arguments.output)
        command = edit_arguments(arguments.data, arguments.sketches, arguments.base, arguments.out, arguments.iterations,
                                 arguments.primitive)
        timing = run_edit(command)
        run = max((arguments.out / "fox" / "sked").iterdir())
        result = {"command": "ns-train " + " ".join(command), "run": str(run), "iterations": arguments.iterations,
                  "resolution": RESOLUTION, "silhouette_resolution": SILHOUETTE_RESOLUTION,
                  "samples_per_ray_scale": SAMPLES_PER_RAY_SCALE, "timing": timing}
        if arguments.output is not None:
            from capture_measure import measure

            with torch.no_grad():
                result.update(measure(run, strip=arguments.strip))
        harness.publish(result, arguments.output)
    elif arguments.command == "measure":
        harness.claim("capture_fox.py", arguments.results)
        from capture_measure import measure

        recorded = json.loads(arguments.results.read_text())
        result = {key: recorded[key] for key in RECORDED_RUN if key in recorded}
        with torch.no_grad():
            result.update(measure(Path(recorded["run"]), strip=arguments.strip))
        harness.publish(result, arguments.results)
    elif arguments.command == "sketches":
        save_sketch_set(hat_sketches(arguments.data, arguments.views), arguments.out)
        print(f"sketches of the hat region from {', '.join(arguments.views)} in {arguments.out}")
    else:
        if arguments.output is not None:
            harness.claim("capture_fox.py", arguments.output)
        report = {"data": str(arguments.data), "sketches": str(arguments.sketches),
                  "views": [view.name for view in load_sketch_set(arguments.sketches).views],
                  "scene_box": [[-1.0] * 3, [1.0] * 3], **check(arguments.data, arguments.sketches)}
        harness.publish(report, arguments.output)


if __name__ == "__main__":
    main(sys.argv[1:])
