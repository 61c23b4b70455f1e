"""`sked-eval`: the paper's protocol on an edited run's sketch views, and the same edit from other views.

Renders every sketch view with the base and the edit and reports PSNR and SSIM outside the
sketches, Intersection-over-Sketch (and the region IoS: only opacity of content near the
sketches counts, so a wall behind the sketch does not fill it), LPIPS outside the sketches and CLIP similarity to the
prompt over 40 views around the edit, the last two only when their weights are available
locally (reported as unavailable otherwise, never faked). Then scores novel views (the base
dataset's evaluation split by default; `sked_ns.evaluation.novel_views`): what the edit must keep
(`psnr_keep`, `ssim_keep`), new opacity where it may not act (`leak`), and with `--target`,
the intended result inside and outside the changed region. Writes JSON and a contact sheet
(base | edit | overlay: one row per sketch view, then a few novel views).
"""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch

from sked_ns.atomic import publish_atomically, write_text_atomically
from sked_ns.engine.base_scene import checkpoint_step
from sked_ns.errors import SkedUserError, warn
from sked_ns.evaluation import novel_views
from sked_ns.evaluation.clip_score import ClipScorer, orbit_cameras
from sked_ns.evaluation.eval_args import DEFAULT_CLIP
from sked_ns.evaluation.eval_cost import EvalWork, estimate_line, seconds_per_pixel
from sked_ns.evaluation.eval_inputs import (
    check_base,
    check_device,
    check_flags,
    check_sketch_masks,
    checked_sketches,
    edit_run_folder,
    edit_scene,
    is_orbit,
    novel_view_cameras,
    orbit_count,
    output_paths,
)
from sked_ns.evaluation.exhaustion import exhaustion_line
from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_outside, ssim_outside
from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at, render_camera, resized_mask
from sked_ns.progress import Progress
from sked_ns.run_lock import describe, holder, writing
from sked_ns.sketches.cameras import cameras_of
from sked_ns.sketches.random_views import focal_from_fov
from sked_ns.sketches.sketch_set import sketch_view_size

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"  # what torchvision fetches for torchmetrics' LPIPS
REGION_IOS_OF_OTHER_BASE = ("n/a: --base's renders carry no preservation weight (only the edit's frozen copy of its "
                            "base knows the sketches); leave --base out to get it")


def _lpips_or_reason():
    """LPIPS needs AlexNet weights: use them only if already in the torch hub cache (no download)."""
    cached = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS
    if not cached.exists():
        return None, f"unavailable: AlexNet weights for LPIPS are not in {cached.parent} (nothing is downloaded)"
    try:
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        return LearnedPerceptualImagePatchSimilarity(normalize=True), None
    except Exception as error:
        return None, f"unavailable: LPIPS could not be built ({type(error).__name__}: {error})"


def clip_similarities(model, sketch_set, prompt: Optional[str], clip_model: str, views: int, resolution: int,
                      own_base: bool) -> Dict:
    """Mean CLIP similarity of the edit (and of its base) to the prompt over `views` orbit views."""
    if not (prompt and prompt.strip()):
        return {"clip_similarity": "unavailable: the edit has no text prompt (reference guidance or carving); "
                                   "pass --prompt to score it against one"}
    scorer, reason = ClipScorer.load(clip_model)
    if scorer is None:
        return {"clip_similarity": reason}
    centre = model.edit_box.center
    radius = float(np.mean([np.linalg.norm(view.camera_to_world[:, 3] - centre) for view in sketch_set.views]))
    cameras = [cameras_of(torch.tensor(pose[None], dtype=torch.float32), *(2 * [focal_from_fov(50.0, resolution)]),
                          resolution / 2, resolution / 2, resolution, resolution)
               for pose in orbit_cameras(centre, radius, views)]
    result = {"clip_similarity": float(np.mean(scorer.similarity([render_camera(model, c)["rgb"] for c in cameras], prompt))),
              "clip_views": views, "clip_model": clip_model, "clip_prompt": prompt}
    if own_base:
        base = [render_camera(model, c, base=True)["rgb"] for c in cameras]
        result["clip_similarity_base"] = float(np.mean(scorer.similarity(base, prompt)))
    return result


def _background(model) -> tuple:
    """The colour ground-truth photos with alpha are composited on (the model's background)."""
    colour = getattr(model.config, "background_color", "white")
    if isinstance(colour, str):
        return (0.0, 0.0, 0.0) if colour == "black" else (1.0, 1.0, 1.0)
    return tuple(float(c) for c in torch.as_tensor(colour).reshape(3))


EVAL_SPLIT = "the base dataset's eval split"
"""Where novel views are scored by default: the photos the base held out."""


def choose_novel_views(pipeline, cameras: str, target: Optional[Path], resolution: int, max_views: int):
    """The cameras novel views are scored at: --target's, the eval split's, a transforms.json's, or an orbit."""
    model = pipeline.model
    background = _background(model)
    transform = pipeline.datamanager.dataparser_transform
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    # nerfstudio-data folds a file's applied_transform into the run's transform; the others ignore it.
    nerfstudio_data = isinstance(pipeline.datamanager.config.dataparser, NerfstudioDataParserConfig)
    if target is not None:
        views = novel_views.transforms_views(target, transform, resolution, background, True, nerfstudio_data)
        source = f"target {target}"
    elif cameras == "eval":
        views, source = novel_views.eval_split_views(pipeline, resolution, background), EVAL_SPLIT
    elif is_orbit(cameras):
        count = orbit_count(cameras)
        radius = float(np.mean([np.linalg.norm(v.camera_to_world[:, 3] - model.edit_box.center)
                                for v in model.sketch_set.views]))
        views, source = novel_views.orbit_views(model.edit_box.center, radius, count, resolution), f"an orbit of {count}"
    else:
        views = novel_views.transforms_views(Path(cameras), transform, resolution, background, True, nerfstudio_data)
        source = cameras
    if len(views) > max_views:  # evenly spread, first and last included
        views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).round().astype(int)]
    return views, source


def evaluate(edit_run: Path, base_run: Optional[Path] = None, sketches: Optional[Path] = None,
             resolution: int = 256, device: str = "cpu", clip_model: str = DEFAULT_CLIP,
             prompt: Optional[str] = None, clip_views: int = 40, clip_resolution: int = 128,
             cameras: Optional[str] = None, target: Optional[Path] = None, novel_resolution: int = 256,
             max_novel_views: int = 12) -> Dict:
    """Metrics of every sketch view, of novel views, their means, and the renders for the contact sheet.
    `cameras`: 'eval' (default), 'orbit[:N]', a camera file or 'none'; with `target`, the target's cameras."""
    cameras = novel_view_cameras(cameras, target)
    edit = edit_scene(edit_run)
    model_config = edit.model_config
    own_base = base_run is None
    if not own_base:
        check_base(Path(base_run), edit, device)
    base_run = Path(base_run) if base_run else Path(model_config.base_checkpoint).parent.parent
    sketches, sketch_set = checked_sketches(sketches, model_config)
    check_sketch_masks(sketch_set, resolution)
    edit_pipeline = load_pipeline(edit.run_dir, device, flag="sked-eval")
    # The edit holds a frozen copy of its own base: render that unless another base is asked for.
    base_pipeline = None if own_base else load_pipeline(base_run, device, flag="--base")
    sketch_set = sketch_set.in_model_frame(edit_pipeline.datamanager.data_frame_transform)
    lpips, lpips_reason = _lpips_or_reason()
    views_to_score, source = ([], None) if cameras == "none" else choose_novel_views(
        edit_pipeline, cameras, target, novel_resolution, max_novel_views)
    say_how_long(edit_pipeline.model, sketch_set, views_to_score, resolution, novel_resolution, device,
                 clip_views if (prompt or model_config.prompt or "").strip() else 0, clip_resolution, own_base)

    views, rows = [], []
    progress = Progress("sked-eval", "sketch view", len(sketch_set.views))
    for index, view in enumerate(sketch_set.views):
        if base_pipeline is None:
            base = render_base_at(edit_pipeline.model, view, resolution)
        else:
            base = render_at(base_pipeline.model, view, resolution)
        after = render_at(edit_pipeline.model, view, resolution)
        mask = resized_mask(view, resolution)
        entry = {
            "view": index,
            "psnr_outside": psnr_outside(after["rgb"], base["rgb"], mask),
            "ssim_outside": ssim_outside(after["rgb"], base["rgb"], mask),
            "ios": intersection_over_sketch(after["accumulation"], mask),
            "ios_base": intersection_over_sketch(base["accumulation"], mask),
        }
        # IoS counts any opacity, so a wall or table behind the sketch "fills" it before any edit; the
        # region IoS counts only opacity of content near the sketches (1 - the pixel's preservation weight).
        if "preservation_weight" in after:
            entry["ios_region"] = intersection_over_sketch(1.0 - after["preservation_weight"], mask)
        if "preservation_weight" in base:
            entry["ios_region_base"] = intersection_over_sketch(1.0 - base["preservation_weight"], mask)
        if lpips is not None:
            keep = (~mask)[None, None].float()  # LPIPS of the images with the sketch blanked in both
            to_nchw = lambda rgb: rgb.permute(2, 0, 1)[None] * keep  # noqa: E731
            entry["lpips_outside"] = float(lpips(to_nchw(after["rgb"]), to_nchw(base["rgb"])))
        views.append(entry)
        overlay = after["rgb"].clone()
        overlay[mask] = overlay[mask] * 0.5 + torch.tensor([0.5, 0.0, 0.0])
        rows.append(torch.cat([base["rgb"], after["rgb"], overlay], dim=1))
        progress.step()
    keys = [key for key in views[0] if key != "view"]
    result = {
        "edit_run": str(edit.run_dir),
        "step": edit_pipeline.sked_loaded_step,
        "checkpoint": str(edit_pipeline.sked_loaded_checkpoint),
        "base_run": str(base_run),
        "sketches": str(sketches),
        "resolution": resolution,
        "views": views,
        "mean": {key: float(np.mean([view[key] for view in views])) for key in keys},
        "lpips_outside": "computed per view" if lpips is not None else lpips_reason,
    }
    for key, whose in (("ios_region", "the edit's"), ("ios_region_base", "the base's")):
        if key not in result["mean"]:  # said, not printed as NaN
            result[key] = (REGION_IOS_OF_OTHER_BASE if key == "ios_region_base" and not own_base
                           else f"n/a: {whose} renders carry no preservation weight")
    result.update(clip_similarities(edit_pipeline.model, sketch_set, prompt or model_config.prompt, clip_model,
                                    clip_views, clip_resolution, own_base))
    if cameras != "none":
        # Against the edit's frozen copy of its base (bit-identical to the base), which knows the sketches.
        novel = novel_views.evaluate_novel_views(edit_pipeline.model, views_to_score, target=target is not None,
                                                 progress=Progress("sked-eval", "novel view", len(views_to_score)))
        width = rows[0].shape[1]
        rows += [torch.nn.functional.interpolate(row.permute(2, 0, 1)[None], scale_factor=width / row.shape[1],
                                                 mode="bilinear")[0].permute(1, 2, 0) for row in novel.pop("rows")]
        result["novel_views"] = {"cameras": source, "resolution": novel_resolution, **novel}
    return {"metrics": result, "sheet": torch.cat(rows, dim=0)}


def say_how_long(model, sketch_set, novel: list, resolution: int, novel_resolution: int, device: str,
                 clip_views: int, clip_resolution: int, clip_base: bool) -> None:
    """One line before the long work: how long this evaluation will take here (a small render timed, eval_cost.py)."""
    def size(camera) -> tuple:
        return int(camera.width.reshape(-1)[0]), int(camera.height.reshape(-1)[0])

    work = EvalWork([sketch_view_size(view, resolution) for view in sketch_set.views],
                    [size(view.camera) for view in novel], clip_views, clip_resolution, clip_base)
    first = sketch_set.views[0]
    per_pixel = seconds_per_pixel(lambda side: tuple(render_at(model, first, side)["rgb"].shape[1::-1]))
    print(estimate_line(work, per_pixel, torch.device(device).type, resolution, novel_resolution), file=sys.stderr,
          flush=True)


def check_live_run(edit, output: Path, sheet: Path) -> None:
    """An edit still training has one writer, its trainer: refused when sked-eval would write into its run folder,
    else warned that the scored checkpoint is the latest so far."""
    writer = holder(edit.run_dir)
    if writer is None:
        return
    step = checkpoint_step(edit.checkpoint)
    inside = [str(path) for path in (output, sheet) if edit.run_dir.resolve() in path.resolve().parents]
    if inside:
        raise SkedUserError(f"sked-eval {edit.run_dir}: the edit is still training ({describe(writer)}), and its run "
                            f"folder has one writer. Wait for it to end, or pass --output and --sheet outside the run "
                            f"folder to score its latest checkpoint now (step {step}).")
    warn(f"sked-eval {edit.run_dir}: the edit is still training ({describe(writer)}); scoring its latest checkpoint "
         f"so far, step {step} (the results record it).")


def write_outputs(outcome: dict, output: Path, sheet: Path) -> None:
    """The contact sheet, then the metrics JSON (whose presence says the evaluation is whole), each written beside
    and renamed into place, so a kill or a full disk leaves the earlier result or none."""
    import cv2

    partial = sheet.with_name(f".{sheet.stem}.partial{sheet.suffix}")  # the suffix tells OpenCV the format
    pixels = (outcome["sheet"].numpy().clip(0, 1) * 255).round().astype(np.uint8)[..., ::-1]
    try:
        with _writing("--sheet", sheet):
            if not cv2.imwrite(str(partial), pixels):
                raise SkedUserError(f"--sheet {sheet}: could not write the contact sheet (OpenCV needs a writable path "
                                    "ending in .png, and space on its disk).")
            publish_atomically(partial, sheet)
    finally:
        with contextlib.suppress(OSError):
            partial.unlink(missing_ok=True)
    with _writing("--output", output):
        write_text_atomically(output, json.dumps(outcome["metrics"], indent=2))


@contextlib.contextmanager
def _writing(flag: str, path: Path):
    """A failure to write one of sked-eval's outputs as one line naming it: a full disk says so."""
    try:
        yield
    except OSError as error:
        line = exhaustion_line(f"{flag} {path}: writing it", error,
                               disk_fix=f"free space there, or pass {flag} on another disk; an earlier result is kept")
        raise SkedUserError(line or f"{flag} {path}: cannot write it ({error.strerror or error}).") from error


def main(args) -> None:
    """sked-eval with parsed arguments: every input, then the outputs, checked before anything is written."""
    run = edit_run_folder(args.config)
    check_flags(args)
    check_device(args.device)
    edit = edit_scene(run)
    if args.base is not None:
        check_base(args.base, edit, args.device)
    _, sketch_set = checked_sketches(args.sketches, edit.model_config)
    check_sketch_masks(sketch_set, args.resolution)
    output, sheet = output_paths(run, args.output, args.sheet, args.overwrite)
    check_live_run(edit, output, sheet)
    hint = "Wait for it to end, or pass another --output (and --sheet)."
    with contextlib.ExitStack() as outputs:  # their one writer, from the check that they may be written on
        for path in dict.fromkeys((output, sheet)):
            outputs.enter_context(writing(path, hint))
        output_paths(run, args.output, args.sheet, args.overwrite)  # again: another sked-eval may have ended meanwhile
        outcome = evaluate(run, args.base, args.sketches, args.resolution, args.device, args.clip_model or DEFAULT_CLIP,
                           args.prompt, args.clip_views, args.clip_resolution, args.cameras, args.target,
                           args.novel_resolution, args.max_novel_views)
        write_outputs(outcome, output, sheet)  # the sheet first: a result JSON is there only with its sheet beside it
    print(sketch_summary(outcome["metrics"]))
    if "novel_views" in outcome["metrics"]:
        print(novel_summary(outcome["metrics"]["novel_views"]))
    print(f"wrote {output} and {sheet} (the edit at step {outcome['metrics']['step']})")


def sketch_summary(metrics: Dict) -> str:
    """One line of the sketch-view means; a figure that could not be computed says why."""
    mean = metrics["mean"]

    def figure(key: str, form: str) -> str:
        value = mean.get(key, metrics.get(key))
        return format(value, form) if isinstance(value, (int, float)) else str(value)

    parts = [f"PSNR outside {figure('psnr_outside', '.2f')} dB", f"SSIM outside {figure('ssim_outside', '.3f')}",
             f"IoS {figure('ios', '.3f')} (base {figure('ios_base', '.3f')})",
             f"region IoS {figure('ios_region', '.3f')} (base {figure('ios_region_base', '.3f')})"]
    lpips = f"LPIPS outside {figure('lpips_outside', '.4f')}" if "lpips_outside" in mean else \
        f"LPIPS: {metrics['lpips_outside']}"
    clip = metrics.get("clip_similarity")
    clip = f"CLIP similarity {clip:.3f}" if isinstance(clip, float) else f"CLIP similarity: {clip}"
    return ", ".join(parts) + f"; {lpips}; {clip}"


def novel_summary(novel: Dict) -> str:
    """One line of the novel-view means (what a user reads first)."""
    mean = novel["mean"]
    parts = [f"{len(novel['views'])} novel views ({novel['cameras']}):"]
    truth = "photos" if novel["cameras"] == EVAL_SPLIT else "ground truth"
    for key, label, unit in (("psnr_keep", "PSNR kept", " dB"), ("ssim_keep", "SSIM kept", ""), ("leak", "leak", ""),
                             ("psnr_keep_gt", f"kept vs {truth}", " dB"), ("ssim_keep_gt", f"SSIM kept vs {truth}", ""),
                             ("psnr_target_changed", "changed vs target", " dB")):
        if key in mean:
            base = mean.get(key + "_base")
            parts.append(f"{label} {mean[key]:.3g}{unit}" + (f" (base {base:.3g}{unit})" if base is not None else ""))
    return " ".join(parts[:1]) + " " + ", ".join(parts[1:])
