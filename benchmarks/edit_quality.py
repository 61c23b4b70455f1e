"""Edit quality as users see it, on scenes the method was not tuned on: novel views, floaters, target colour.

    python benchmarks/edit_quality.py              # every scene and protocol (hours on a 2-core CPU)
    python benchmarks/edit_quality.py --quick      # one scene, a few iterations (smoke run)
    python benchmarks/edit_quality.py --replot     # the table again from the results JSON
    python benchmarks/edit_quality.py --base splatfacto   # the same edits of Gaussian-splat bases
    python benchmarks/edit_quality.py --base instant-ngp --scenes hat   # instant-ngp bases of the demo sphere

Scenes: `hat` (the demo sphere's edit, which SKED's defaults were tuned on) and the held-out
`vase` and `crate` (`sked_ns.demo.scenes.objects`, defined before any tuning), reported apart;
`--scenes antenna` (or `handle`) adds another of the demo sphere's edits, tuned-on too.
`--scenes lawn` edits the held-out unbounded scene (`sked_ns.demo.scenes.unbounded`: a ground to the
horizon under a sky, low cameras among the objects), reported apart as "held-out, unbounded".
Each base is trained like a user trains one: `ns-train nerfacto` with its defaults apart from
the iterations, the rays per batch, the hash-table size and the CPU (nerfstudio's LPIPS metric, an AlexNet
download, is skipped: there is no network here); the demo sphere's photos (nothing behind the object but white)
train with a white background, as such captures are (nerfstudio's blender data). Each edit is `ns-train sked`
with reference guidance towards the scene's known target; each is scored by `sked-eval --target` at the base
dataset's evaluation cameras (novel views: none of them is a sketch view) and at the sketch views.
`--base splatfacto` edits a splatfacto base of each scene instead: `ns-train splatfacto` needs CUDA, so
it is fitted on the CPU (`sked_ns.demo.splat_base`, SPLAT_FIT, seeded from the scene's surface points as a
structure-from-motion cloud would be) and saved as `ns-train splatfacto` saves a run; its rows say `splatfacto`.
`--base instant-ngp` edits an instant-ngp base at the method's own size: `ns-train instant-ngp` needs nerfacc's CUDA
kernels, so it is fitted on the CPU to the demo sphere's analytic shape and colours (`sked_ns.demo.base`, NGP_FIT
steps), not to its photos; only the demo sphere's scenes have it; its rows say `instant-ngp`.

Protocols (the paper's 10,000 iterations at 128 px are out of a CPU's reach): `cpu-100` is 100
iterations, `long` 500, both at 24 px renders with a quarter of the base's samples per ray and
the presets' warm-up fraction (10%); `cpu-100-48` and `long-48` (run only when asked, reported apart) are
the same at 48 px renders, `long-1x` and `long-0.5x` the same at the `sked` and `sked-fast` presets' samples per
ray, `cpu-100-0.5x` `cpu-100` at `sked-fast`'s. Figures: novel-view `psnr_keep_gt` of edit and base (vs ground truth)
and its drop, `leak`, IoS at the sketch views, PSNR against the target inside the changed region. Writes
benchmarks/results/edit_quality.json and prints the README table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import harness
import numpy as np
from harness import RESULTS, ns_train_command

TUNED, HELD_OUT = ("hat", "handle", "antenna"), ("vase", "crate", "marker")  # the demo sphere's edits are tuned on
UNBOUNDED = ("lawn",)  # held out too, reported apart: ground to the horizon and sky (unbounded_scenes)
# A CPU step of a full-size nerfacto base at 32 px with nerfacto's 400 samples per ray takes ~25 s here:
# the protocols render at 24 px with a quarter of the samples (a user's --samples-per-ray-scale).
PROTOCOLS = {"cpu-100": {"iterations": 100, "resolution": 24, "samples_per_ray_scale": 0.25},
             "long": {"iterations": 500, "resolution": 24, "samples_per_ray_scale": 0.25},
             # Splat renders are cheap: the same edits at 48 px renders (run only when asked, reported apart).
             "cpu-100-48": {"iterations": 100, "resolution": 48, "samples_per_ray_scale": 0.25},
             "long-48": {"iterations": 500, "resolution": 48, "samples_per_ray_scale": 0.25},
             # The presets' own samples per ray, sked's (1x) and sked-fast's (0.5x): run only when asked, reported apart.
             "long-1x": {"iterations": 500, "resolution": 24, "samples_per_ray_scale": 1.0},
             "long-0.5x": {"iterations": 500, "resolution": 24, "samples_per_ray_scale": 0.5},
             "cpu-100-0.5x": {"iterations": 100, "resolution": 24, "samples_per_ray_scale": 0.5}}
DEFAULT_PROTOCOLS = ("cpu-100", "long")
DEFAULT_SCENES = ("hat", "vase", "crate")
BASE_ITERATIONS = 400
BASE_RAYS = 256
BASE_LOG2_HASHMAP = 15  # nerfacto's default 19 is sized for real scenes; these are 128 px objects
BASES = ("nerfacto", "splatfacto", "instant-ngp")
NGP_FIT = 300
"""The instant-ngp bases' CPU fit steps (sked_ns.demo.base.build_demo_base)."""
SPLAT_FIT = {"steps": 200, "num_gaussians": 2000}
"""The splat bases' CPU fit (`SplatFit` fields; the rest its defaults)."""


def run(command: List[str], log: Path) -> None:
    """A command as a user types it, its output kept; a failure stops the benchmark with the log's tail."""
    with log.open("w") as handle:
        done = subprocess.run(command, stdout=handle, stderr=subprocess.STDOUT, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command[:3])} ... failed (log {log}):\n{log.read_text()[-3000:]}")


def fit_splat_base(scene: str, data: Path, output: Path, fit: Dict, log: Path) -> Path:
    """A splatfacto run of the scene's photos, fitted on the CPU; its fit's PSNR goes to `log` (JSON)."""
    from sked_ns.demo.scenes.catalogue import scene_named
    from sked_ns.demo.splat_base import SplatFit, dataset_point_cloud, last_fit
    from sked_ns.demo.splat_base import fit_splat_base as fit_base

    run_dir = output / "splat-base" / "splatfacto" / "base"
    if not (run_dir / "nerfstudio_models").exists():
        cloud = dataset_point_cloud(data, scene_named(scene).render_base)
        fit_base(data, output, SplatFit(**fit), seed_points=cloud, experiment="splat-base")
        harness.write_results(log, last_fit)
    return run_dir


def fit_ngp_base(data: Path, output: Path) -> Path:
    """An instant-ngp run at the method's own size, fitted on the CPU to the demo sphere (the base of its scenes)."""
    from sked_ns.demo.base import build_demo_base

    run_dir = output / "demo-base-ngp" / "instant-ngp" / "base"
    if not (run_dir / "nerfstudio_models").exists():
        with harness.few_grid_passes(1):  # one pass over the 4 x 128^3 occupancy cells (harness.py says why)
            build_demo_base(data, output, steps=NGP_FIT, tiny=None, method="instant-ngp")
    return run_dir


def white_backdrop(scene: str) -> bool:
    """The demo sphere's photos show the object on plain white, nothing behind it: its base trains with a white
    background. With nerfacto's default (last_sample) 400 iterations fill the empty space with white mass in front of
    the sphere at the evaluation cameras (eight retrains of the `hat` base, one at 3480315's code: 11-17 dB there;
    white: 22.7 dB, two seeds). The other scenes' bases came out sound with the default, which they keep."""
    from sked_ns.demo.scenes import sphere as demo_scene

    return scene in demo_scene.SCENES


def base_arguments(scene: str, data: Path, output: Path, iterations: int) -> List[str]:
    """The `ns-train nerfacto` arguments of a scene's base, as a user types them; its run is
    output/base/nerfacto/TIMESTAMP, named by its background so an older base with another one is not reused."""
    white = white_backdrop(scene)
    background = ["--pipeline.model.background-color", "white"] if white else []
    return ["nerfacto", "--data", str(data), "--output-dir", str(output), "--experiment-name", "base",
            "--timestamp", "base-white" if white else "base", "--max-num-iterations", str(iterations),
            "--vis", "tensorboard", "--machine.device-type", "cpu",
            "--pipeline.datamanager.train-num-rays-per-batch", str(BASE_RAYS),
            "--pipeline.model.log2-hashmap-size", str(BASE_LOG2_HASHMAP), *background,
            "--steps-per-save", str(iterations), "--viewer.quit-on-train-completion", "True",
            "nerfstudio-data", "--data", str(data)]


def train_base(scene: str, data: Path, output: Path, iterations: int, log: Path) -> Path:
    arguments = base_arguments(scene, data, output, iterations)
    run_dir = output / "base" / "nerfacto" / arguments[arguments.index("--timestamp") + 1]
    if not (run_dir / "nerfstudio_models").exists():
        run(ns_train_command(arguments), log)
    return run_dir


def step_time(scene: str, work: Path, protocol: Dict, name: str = "cpu-100") -> Dict:
    """CPU seconds per edit iteration of the scene's splatfacto and nerfacto bases at the same render size: edits of
    5 and 25 iterations each, the difference of their CPU time (set-up cancels) over 20. The nerfacto base is a
    30-iteration `ns-train nerfacto` (the step cost is its architecture's, not its quality's)."""
    import resource

    paths = {key: work / key for key in ("data", "target", "sketches")}
    bases = {"splatfacto": fit_splat_base(scene, paths["data"], work / "runs", SPLAT_FIT, work / "splat-base.json"),
             "nerfacto": train_base(scene, paths["data"], work / "runs-steptime", 30, work / "steptime-base.log")}
    timings = {}
    for kind, base in bases.items():
        cpu = {}
        for iterations in (5, 25):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            run(ns_train_command(edit_arguments(base, paths, scene, {**protocol, "iterations": iterations},
                                        work / "steptime" / f"{kind}-{name}-{iterations}")),
                work / f"steptime-{kind}-{name}-{iterations}.log")
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu[iterations] = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
        timings[kind] = {"cpu_s_per_step": (cpu[25] - cpu[5]) / 20, "cpu_s_5_and_25_iterations": [cpu[5], cpu[25]]}
    return timings


def edit_arguments(base: Path, paths: Dict[str, Path], scene: str, protocol: Dict, output: Path,
                   extra: Optional[List[str]] = None) -> List[str]:
    """The `ns-train` arguments of one edit, as a user types them (a variant's guidance flags go after its
    subcommand, where tyro reads them)."""
    iterations, resolution = protocol["iterations"], protocol["resolution"]
    model_flags, guidance_flags = [], []
    for flag, *values in _flag_groups(extra or []):
        (guidance_flags if flag.startswith("--pipeline.model.guidance.") else model_flags).extend([flag, *values])
    return ["sked", "--load-dir", str(base), "--sketches", str(paths["sketches"]), "--output-dir", str(output),
            "--experiment-name", scene, "--max-num-iterations", str(iterations), "--vis", "tensorboard",
            "--machine.device-type", "cpu", "--steps-per-save", str(iterations),
            "--pipeline.model.guidance-resolution", str(resolution),
            "--pipeline.model.silhouette-resolution", str(resolution),
            "--pipeline.model.samples-per-ray-scale", str(protocol.get("samples_per_ray_scale", 1.0)),
            "--pipeline.model.edit-box-warmup", str(max(1, iterations // 10)), *model_flags,
            # Subcommands last, each followed by its own flags: the guidance, then the dataparser.
            "pipeline.model.guidance:reference", "--pipeline.model.guidance.target", scene, *guidance_flags,
            "nerfstudio-data", "--data", str(paths["data"])]


def _flag_groups(arguments: List[str]) -> List[List[str]]:
    """Each flag with the values after it (a tuple field takes several)."""
    groups: List[List[str]] = []
    for argument in arguments:
        if argument.startswith("--") or not groups:
            groups.append([argument])
        else:
            groups[-1].append(argument)
    return groups


def edit(base: Path, paths: Dict[str, Path], scene: str, protocol: Dict, output: Path, log: Path,
         extra: Optional[List[str]] = None) -> Path:
    run(ns_train_command(edit_arguments(base, paths, scene, protocol, output, extra)), log)
    return max((output / scene / "sked").iterdir())


def score(edit_run: Path, paths: Dict[str, Path], output: Path, log: Path) -> Dict:
    # A rerun of a tag replaces its evaluation (sked-eval never does unasked).
    run([sys.executable, "-m", "sked_ns.evaluation.eval_cli", str(edit_run), "--output", str(output), "--overwrite",
         "--resolution", "64", "--target", str(paths["target"]), "--novel-resolution", "96"], log)
    return json.loads(output.read_text())


def sketch_view_fill(edit_run: Path, scene: str, sketches: Path, resolution: int = 64) -> Dict:
    """Region IoS over the sketch pixels where the exact target shows the added part (`ios_visible`), and the
    region IoS the exact target itself scores (`ios_region_perfect`): a sketch holds the part's hidden
    pixels too, so a correct edit cannot fill all of it, and region IoS alone cannot say how far it is off."""
    from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at
    from sked_ns.method.preservation import SketchDistanceField
    from sked_ns.sketches.sketch_set import load_sketch_set

    model = load_pipeline(edit_run).model
    data_views = load_sketch_set(sketches).views
    field = SketchDistanceField(data_views)  # w is the same in the data frame: its distances are in image widths
    views = [view_fill(scene, data_view, field, model.config.beta, resolution,
                       1.0 - render_at(model, model_view, resolution)["preservation_weight"],
                       1.0 - render_base_at(model, model_view, resolution)["preservation_weight"])
             for data_view, model_view in zip(data_views, model.sketch_set.views)]
    scored = [view for view in views if "ios_visible" in view]
    mean = lambda key: float(np.mean([view[key] for view in scored])) if scored else None  # noqa: E731
    return {"ios_visible": mean("ios_visible"), "ios_visible_base": mean("ios_visible_base"),
            "ios_visible_min": min((view["ios_visible"] for view in scored), default=None),
            "ios_region_perfect": float(np.mean([view["ios_region_perfect"] for view in views])),
            "ios_region_perfect_min": min(view["ios_region_perfect"] for view in views),
            "sketch_views": views}


def view_fill(scene: str, data_view, field, beta: float, resolution: int, editable_opacity, base_editable_opacity
              ) -> Dict:
    """One sketch view's fill scores, given edit and base renders of the opacity the edit may change (1 - the
    pixel's preservation weight) at `resolution`; the exact target is traced in the data frame, where `field`
    (the sketches' SketchDistanceField) gives its preservation weight."""
    import torch

    from sked_ns.demo.scenes.catalogue import scene_named
    from sked_ns.demo.scenes.objects import visible_added_part
    from sked_ns.evaluation.metrics import intersection_over_sketch
    from sked_ns.sketches.sketch_set import sketch_view_at

    camera, mask = sketch_view_at(data_view, resolution)
    truth = visible_added_part(scene_named(scene), np.asarray(data_view.camera_to_world)[:3], float(camera.fx),
                               int(camera.width), int(camera.height))
    weight = field.preservation_weight(truth["points"].reshape(-1, 3), beta)
    perfect = torch.where(truth["hit"], 1.0 - weight.reshape(mask.shape), torch.zeros(mask.shape))
    visible = mask & truth["visible"]
    entry = {"visible_fraction": float(visible.sum() / mask.sum()), "ios_region_perfect": intersection_over_sketch(perfect, mask)}
    if visible.any():
        entry["ios_visible"] = intersection_over_sketch(editable_opacity, visible)
        entry["ios_visible_base"] = intersection_over_sketch(base_editable_opacity, visible)
    return entry


def summarise(metrics: Dict) -> Dict:
    novel = metrics["novel_views"]["mean"]
    row = {
        "ios": metrics["mean"]["ios"],
        "ios_region": metrics["mean"].get("ios_region"),
        "ios_region_base": metrics["mean"].get("ios_region_base"),
        "psnr_outside_sketch_views": metrics["mean"]["psnr_outside"],
        "psnr_keep_vs_base": novel.get("psnr_keep"),
        "leak": novel.get("leak"),
        "psnr_keep_gt": novel.get("psnr_target_unchanged"),
        "psnr_keep_gt_base": novel.get("psnr_target_unchanged_base"),
        # The same over the pixels that show preserved content in base and edit (sked-eval's psnr_keep_gt):
        # what preservation is answerable for; the column above also charges the edit's shape in the hull.
        "psnr_kept_pixels_gt": novel.get("psnr_keep_gt"),
        "psnr_kept_pixels_gt_base": novel.get("psnr_keep_gt_base"),
        "psnr_target_changed": novel.get("psnr_target_changed"),
        "psnr_target_changed_base": novel.get("psnr_target_changed_base"),
        "ios_min": min(view["ios"] for view in metrics["views"]),
        "ios_region_min": min((view["ios_region"] for view in metrics["views"] if "ios_region" in view), default=None),
    }
    if row["psnr_keep_gt"] is not None and row["psnr_keep_gt_base"] is not None:
        row["psnr_keep_drop"] = row["psnr_keep_gt_base"] - row["psnr_keep_gt"]
    return row


def _region_ios(s: Dict) -> str:
    # Plain IoS counts a wall behind the sketch as filled; region IoS counts only content near the sketches.
    if s.get("ios_region") is None:
        return "not measured"
    low = f" (min {s['ios_region_min']:.2f})" if s.get("ios_region_min") is not None else ""
    perfect = f"; exact target {s['ios_region_perfect']:.2f}" if s.get("ios_region_perfect") is not None else ""
    return f"{s['ios_region_base']:.2f} -> {s['ios_region']:.2f}{low}{perfect}"


def _visible_ios(s: Dict) -> str:
    if s.get("ios_visible") is None:
        return "not measured"
    return f"{s['ios_visible_base']:.2f} -> {s['ios_visible']:.2f} (min {s['ios_visible_min']:.2f})"


def _kept_pixels(s: Dict) -> str:
    if s.get("psnr_kept_pixels_gt") is None:
        return "not recorded"
    return f"{s['psnr_kept_pixels_gt_base']:.1f} -> {s['psnr_kept_pixels_gt']:.1f}"


def table(results: Dict) -> str:
    rows = []
    for row in results["runs"]:
        s = row["summary"]
        variant = row["variant"] + (f" [seed {row['seed']}]" if "seed" in row else "")
        rows.append([row["scene"], row.get("base", "nerfacto"), row["set"], row["protocol"], variant,
                     f"{s['psnr_keep_gt_base']:.1f} -> {s['psnr_keep_gt']:.1f} ({s['psnr_keep_drop']:+.2f})",
                     _kept_pixels(s), f"{s['leak']:.4f}", _region_ios(s), _visible_ios(s),
                     f"{s['ios']:.2f} ({s['ios_min']:.2f})",
                     f"{s['psnr_target_changed_base']:.1f} -> {s['psnr_target_changed']:.1f}", f"{row['seconds']:.0f}"])
    return harness.markdown_table(["scene", "base", "set", "protocol", "variant", "novel PSNR kept, base -> edit (drop)",
                                   "kept pixels only", "leak", "region IoS, base -> edit",
                                   "region IoS where the target shows the part", "IoS (min)",
                                   "target PSNR changed, base -> edit", "s"], rows)


_BEFORE_RESIDUAL = ["--pipeline.model.colour-residual", "False"]
_SOFT_HOLD = ["--pipeline.model.keep-threshold", "1"]  # the paper's soft hold (no sample held exactly)
VARIANTS = {"default": [],
            # NeRF bases: what an edit trains, pinned whatever the default is.
            "local-field (NeRF edits: the base's networks over the edit box, a grid of changes and copies of its MLPs, "
            "a learnt hull proposal at five times the grids' rate and the colour residual)": [
                "--pipeline.model.nerf-edit-field", "local"],
            "local-field-0.9 (the local field as 0.9 made it: no hull proposal, no colour residual)": [
                "--pipeline.model.nerf-edit-field", "local", "--pipeline.model.hull-proposal-grid", "0",
                *_BEFORE_RESIDUAL],
            "no-hull-proposal (NeRF local field: the hull sampled evenly, as 0.9's)": [
                "--pipeline.model.hull-proposal-grid", "0"],
            "full-copy (NeRF edits: a trained copy of the base's whole field; the paper's model, the default until 0.9)": [
                "--pipeline.model.nerf-edit-field", "full-copy"],
            "no-colour-residual": _BEFORE_RESIDUAL,
            "paper (occupancy target, whole-ray L_sil, no photo anchor, no exact hold)": [
                "--pipeline.model.preservation-target", "occupancy", "--pipeline.model.silhouette-opacity", "any",
                "--pipeline.model.lambda-photo", "0", *_BEFORE_RESIDUAL, *_SOFT_HOLD],
            "previous-default (occupancy target, whole-ray L_sil, photo anchor on)": [
                "--pipeline.model.preservation-target", "occupancy", "--pipeline.model.silhouette-opacity", "any",
                *_BEFORE_RESIDUAL, *_SOFT_HOLD],
            "density-target-only (whole-ray L_sil, photo anchor on)": ["--pipeline.model.silhouette-opacity", "any",
                                                                       *_BEFORE_RESIDUAL, *_SOFT_HOLD],
            # NeRF bases: kept content held by L_pres and the photo anchor only, as before held_field.py.
            "soft-hold (keep-threshold 1: no sample held exactly; L_pres and the photo anchor hold kept content)":
                _SOFT_HOLD,
            # NeRF bases: the frozen base's proposal networks at every sample while training, not their grid.
            "proposal-networks (base-proposal-grid 0: the base's proposal networks, not a grid of them)": [
                "--pipeline.model.base-proposal-grid", "0"],
            # Guidance is the only loss on the random views' colours: what leaks without it is L_sil's.
            "no-guidance (L_sil, L_pres, photo anchor only)": ["--pipeline.model.guidance.weight", "0"],
            # A small sketch has few rays to pull its part into being: L_sil per sketch pixel.
            "sketch-normalised-sil (L_sil per sketch pixel)": ["--pipeline.model.silhouette-normalisation", "sketch"],
            # Adam moves a hash entry by about its lr a step: a thin part needs a high density, so many steps.
            "grid-lr-3x (hash grids' Adam lr 0.15, to 0.015)": ["--optimizers.hash-grids.optimizer.lr", "0.15",
                                                                "--optimizers.hash-grids.scheduler.lr-final", "0.015"],
            # Splat bases: splatfacto's Adam rates (sized for 30,000 steps) and 1,000 seeds at half their spacing.
            "splatfacto-rates (splatfacto's Adam rates, 1,000 seeds at 0.5x spacing: the previous splat default)": [
                "--pipeline.model.splat-learning-rates", "splatfacto", "--pipeline.model.num-seeds", "1000",
                "--pipeline.model.seed-size", "0.5"],
            # Splat bases: each training render at 2x its size, averaged down (the Gaussians' footprint between pixels).
            "supersample-1 (splat training renders at one sample a pixel: the previous splat default)": [
                "--pipeline.model.splat-supersampling", "1"],
            # Splat bases: the reference target at one sample a pixel beside the edit's supersampled render.
            "point-target (reference target sampled at pixel centres, not as the render: the default before 2026-12-02)": [
                "--pipeline.model.guidance.sampling", "pixel-centre"],
            # The random views' field of view (the authors' 40-80 deg): narrower frames the part in more pixels.
            "fov-20-40 (random views' field of view 20-40 deg, not fitted to the edit box)": [
                "--pipeline.datamanager.fov-range", "20", "40", "--pipeline.datamanager.edit-fill", "0"],
            "authors-fov (random views in the authors' 40-80 deg field of view whatever the edit's size: the default "
            "before the views framed the edit box)": ["--pipeline.datamanager.edit-fill", "0"],
            "supersample-2 (splat training renders at 2x, averaged down)": ["--pipeline.model.splat-supersampling", "2"],
            "seeds-1000 (1,000 seeds as wide as their spacing)": ["--pipeline.model.num-seeds", "1000"],
            "seeds-60 (60 seeds as wide as their spacing)": ["--pipeline.model.num-seeds", "60"],
            "seeds-3000 (3,000 seeds as wide as their spacing)": ["--pipeline.model.num-seeds", "3000"],
            "seeds-10000 (10,000 seeds as wide as their spacing)": ["--pipeline.model.num-seeds", "10000"],
            # Issue 23, what carves a two-view visual hull: the guidance's weight, L_sp, the warm-up's proposal boost,
            # L_sil's weight, and L_new (the opacity the edit adds over the base) at three weights.
            "guidance-3x (reference weight 90)": ["--pipeline.model.guidance.weight", "90"],
            "sparsity-100x (lambda_sp 0.05)": ["--pipeline.model.lambda-sp", "0.05"],
            "no-boost (no proposal density in the hull during warm-up)": ["--pipeline.model.edit-box-density", "0"],
            "sil-0.3 (lambda_sil 0.3)": ["--pipeline.model.lambda-sil", "0.3"],
            "new-mass-0.3 (L_new weight 0.3)": ["--pipeline.model.lambda-new-mass", "0.3"],
            "new-mass-1 (L_new weight 1)": ["--pipeline.model.lambda-new-mass", "1"],
            "new-mass-5 (L_new weight 5)": ["--pipeline.model.lambda-new-mass", "5"],
            "new-mass-20 (L_new weight 20)": ["--pipeline.model.lambda-new-mass", "20"]}


def _set(scene: str) -> str:
    return "tuned" if scene in TUNED else "held-out, unbounded" if scene in UNBOUNDED else "held-out"


def _tag(variant: str) -> str:
    # Variant names hold commas, so the command line and the file names use their first word.
    return variant.split()[0]


def _run_tag(base: str, protocol: str, variant: str, seed: Optional[int] = None) -> str:
    """The name of a run's files under --work: splat bases' edits apart from nerfacto's, another seed's apart."""
    prefix = {"splatfacto": "splat-", "instant-ngp": "ngp-"}.get(base, "")
    return f"{prefix}{protocol}-{_tag(variant)}{'' if seed is None else f'-seed{seed}'}"


def _variant(tag: str) -> str:
    names = [name for name in VARIANTS if _tag(name) == tag.strip()]
    if not names:
        raise SystemExit(f"--variants: no variant {tag!r}; choose from {', '.join(map(_tag, VARIANTS))}")
    return names[0]


def rescore(output: Path, work: Path, variants: List[str], scenes: Optional[List[str]]) -> None:
    """Scores again, with this checkout, the recorded runs whose edits are still under `work` (sked-eval and the sketch
    views): for a change to how an edit renders, the same trained edits, free of training's run-to-run spread. The
    newest edit of a run's tag is taken only if its sked-eval JSON holds the recorded IoS (a later run of the same tag
    replaces the files); the row keeps what it held under `scored_before` and names the commit that scored it."""
    results = json.loads(output.read_text())
    for row in results["runs"]:
        if row["variant"] not in variants or (scenes and row["scene"] not in scenes):
            continue
        tag = _run_tag(row.get("base", "nerfacto"), row["protocol"], row["variant"], row.get("seed"))
        scene_work = work / row["scene"]
        evaluation, edits = scene_work / f"{tag}.eval.json", scene_work / "edits" / tag / row["scene"] / "sked"
        if not (evaluation.exists() and edits.exists()):
            continue
        if abs(json.loads(evaluation.read_text())["mean"]["ios"] - row["summary"]["ios"]) > 1e-9:
            print(f"{row['scene']} {tag}: the edit on disk is a later run; left as recorded")
            continue
        paths = {key: scene_work / key for key in ("target", "sketches")}
        try:
            edit_run = max(edits.iterdir())
            metrics = score(edit_run, paths, evaluation, scene_work / f"{tag}.eval.log")
            summary = {**summarise(metrics), **sketch_view_fill(edit_run, row["scene"], paths["sketches"])}
        except (ValueError, RuntimeError) as error:  # e.g. an edit saved by an older sked_ns
            print(f"{row['scene']} {tag}: not re-scored: {error}".splitlines()[0])
            continue
        row["scored_before"] = {"commit": row.get("scored_by", row["commit"]), "summary": row["summary"]}
        row.update(summary=summary, scored_by=harness.commit())
        harness.write_results(output, results)
        print(table({"runs": [row]}).splitlines()[-1], flush=True)
    print(table(results))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="hat only, 4 edit iterations, a 30-iteration base")
    parser.add_argument("--scenes", default=None,
                        help=f"comma-separated (default {','.join(DEFAULT_SCENES)}): " + ", ".join(TUNED + HELD_OUT + UNBOUNDED))
    parser.add_argument("--protocols", default=None,
                        help=f"comma-separated, of {', '.join(PROTOCOLS)} (default {','.join(DEFAULT_PROTOCOLS)}; "
                             "with --step-time: the first one's render size)")
    parser.add_argument("--variants", default=",".join(map(_tag, VARIANTS)),
                        help="comma-separated variant tags (first words): " + ", ".join(map(_tag, VARIANTS)))
    parser.add_argument("--work", type=Path, default=Path("benchmark_work"), help="datasets, bases, edits, logs")
    parser.add_argument("--output", type=Path, default=RESULTS / "edit_quality.json")
    parser.add_argument("--base", choices=BASES, default="nerfacto",
                        help="the bases edited: nerfacto (ns-train nerfacto on the CPU), splatfacto (fitted on the CPU) or "
                             "instant-ngp (fitted on the CPU to the demo sphere's shape)")
    parser.add_argument("--step-time", metavar="SCENE", default=None,
                        help="only time a CPU edit step of SCENE's splatfacto and nerfacto bases (cpu-100's render size; "
                             "run with OMP_NUM_THREADS=1 for one core); prints JSON")
    parser.add_argument("--seed", type=int, default=None,
                        help="the edits' --machine.seed (default: nerfstudio's, 42): a run-to-run spread; bases keep theirs")
    parser.add_argument("--replot", action="store_true")
    parser.add_argument("--rescore", action="store_true",
                        help="score again, with this checkout, the recorded runs (of --variants, and --scenes if given) "
                             "whose edits are still under --work: for a change to rendering only")
    args = parser.parse_args()
    if args.replot:
        print(table(json.loads(args.output.read_text())))
        return
    if args.rescore:
        harness.claim("edit_quality.py", args.output, args.work)
        rescore(args.output, args.work, [_variant(tag) for tag in args.variants.split(",")],
                args.scenes.split(",") if args.scenes else None)
        return
    if args.step_time:
        from sked_ns.demo.scenes.catalogue import write_benchmark

        work = args.work / args.step_time
        if not (work / "sketches" / "sketches.json").exists():
            write_benchmark(args.step_time, work)
        protocol = (args.protocols or "cpu-100").split(",")[0]
        print(json.dumps(step_time(args.step_time, work, PROTOCOLS[protocol], protocol), indent=2))
        return
    scenes = ["hat"] if args.quick else (args.scenes.split(",") if args.scenes else list(DEFAULT_SCENES))
    if args.base == "instant-ngp":
        from sked_ns.demo.scenes import sphere

        if [scene for scene in scenes if scene not in sphere.SCENES]:  # before anything is claimed or written
            raise SystemExit(f"error: --base instant-ngp: only the demo sphere's scenes ({', '.join(sphere.SCENES)}) "
                             f"have an instant-ngp base here; --scenes {','.join(scenes)}")
    harness.claim("edit_quality.py", args.output, args.work)
    from sked_ns.demo.scenes.catalogue import write_benchmark

    protocols = {"quick": {"iterations": 4, "resolution": 16, "samples_per_ray_scale": 0.25}} if args.quick else {
        name: PROTOCOLS[name] for name in (args.protocols or ",".join(DEFAULT_PROTOCOLS)).split(",")}
    variants = ["default"] if args.quick else [_variant(tag) for tag in args.variants.split(",")]
    base_iterations = 30 if args.quick else BASE_ITERATIONS
    results = {"protocol": __doc__.split("Protocols")[1].split("Writes")[0].strip(), "base_iterations": base_iterations,
               "base_rays_per_batch": BASE_RAYS, "environment": harness.environment("cpu"), "runs": []}
    if args.output.exists() and not args.quick:
        results["runs"] = json.loads(args.output.read_text()).get("runs", [])
    done = {(r["scene"], r.get("base", "nerfacto"), r["protocol"], r["variant"], r.get("seed")) for r in results["runs"]}
    seed_flags = [] if args.seed is None else ["--machine.seed", str(args.seed)]
    splat = args.base == "splatfacto"
    if args.base == "instant-ngp":
        results["ngp_fit"] = NGP_FIT
    if splat:
        results["splat_fit"] = SPLAT_FIT
    for scene in scenes:
        work = args.work / scene
        paths = {key: work / key for key in ("data", "target", "sketches")}
        if not (work / "sketches" / "sketches.json").exists():
            write_benchmark(scene, work)
        start = time.perf_counter()
        if splat:
            base = fit_splat_base(scene, paths["data"], work / "runs", SPLAT_FIT, work / "splat-base.json")
        elif args.base == "instant-ngp":
            base = fit_ngp_base(paths["data"], work / "runs")
        else:
            base = train_base(scene, paths["data"], work / "runs", base_iterations, work / "base.log")
        print(f"{scene}: base ready ({time.perf_counter() - start:.0f} s)", flush=True)
        for protocol_name, protocol in protocols.items():
            for variant in variants:
                if (scene, args.base, protocol_name, variant, args.seed) in done:
                    continue
                tag = _run_tag(args.base, protocol_name, variant, args.seed)
                start = time.perf_counter()
                edit_run = edit(base, paths, scene, protocol, work / "edits" / tag, work / f"{tag}.log",
                                [*VARIANTS[variant], *seed_flags])
                metrics = score(edit_run, paths, work / f"{tag}.eval.json", work / f"{tag}.eval.log")
                seconds = time.perf_counter() - start
                summary = {**summarise(metrics), **sketch_view_fill(edit_run, scene, paths["sketches"])}
                results["runs"].append({"scene": scene, "base": args.base, "set": _set(scene),
                                        "protocol": protocol_name, "variant": variant,
                                        **({} if args.seed is None else {"seed": args.seed}),
                                        "seconds": seconds, "commit": harness.commit(), "summary": summary})
                harness.write_results(args.output, results)
                print(table({"runs": results["runs"][-1:]}).splitlines()[-1], flush=True)
    harness.report(table(results), args.output)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
