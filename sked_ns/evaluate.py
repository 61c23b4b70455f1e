"""`sked-eval`: the paper's protocol on an edited run's sketch views, and the same edit from other views.

Renders every sketch view with the base and the edit and reports PSNR and SSIM outside the
sketches, Intersection-over-Sketch (and the region IoS: only opacity of content near the
sketches counts, so a wall behind the sketch does not fill it), LPIPS outside the sketches and CLIP similarity to the
prompt over 40 views around the edit, the last two only when their weights are available
locally (reported as unavailable otherwise, never faked). Then scores novel views (the base
dataset's evaluation split by default; `sked_ns.novel_views`): what the edit must keep
(`psnr_keep`, `ssim_keep`), new opacity where it may not act (`leak`), and with `--target`,
the intended result inside and outside the changed region. Writes JSON and a contact sheet
(base | edit | overlay: one row per sketch view, then a few novel views).
"""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch

from sked_ns.atomic import publish_atomically, write_text_atomically
from sked_ns.base_scene import resolve_base
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, check_writable_folder, warn
from sked_ns import novel_views
from sked_ns.metrics import SSIM_MIN_SIDE, intersection_over_sketch, psnr_outside, ssim_outside
from sked_ns.clip_score import DEFAULT_CLIP, ClipScorer, orbit_cameras
from sked_ns.random_views import focal_from_fov
from sked_ns.render import load_pipeline, render_at, render_base_at, render_camera, resized_mask
from sked_ns.run_lock import writing
from sked_ns.cameras import cameras_of
from sked_ns.sketches import load_sketch_set


ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"  # what torchvision fetches for torchmetrics' LPIPS
LARGE_RENDER = 2048
"""A render side above this is surely a typo (millions of rays a view)."""
MANY_CLIP_VIEWS = 400
"""Ten times the paper's 40 CLIP views: more is surely a typo."""
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


def is_orbit(cameras: str) -> bool:
    return cameras == "orbit" or cameras.startswith("orbit:")


def orbit_count(cameras: str) -> int:
    """N of --cameras orbit[:N] (12 without it)."""
    count = cameras.partition(":")[2] or "12"
    if not (count.isdigit() and int(count) > 0):
        raise SkedUserError(f"--cameras {cameras}: the orbit's view count must be a whole number >= 1 (e.g. orbit:12).")
    return int(count)


def _flagged(flag: str, typed, error: SkedUserError) -> str:
    """A camera-file error as `--target FILE: what is wrong` (the file as typed, named once)."""
    message = str(error)
    return f"{flag} {message}" if message.startswith(str(typed)) else f"{flag} {typed}: {message}"


def check_camera_file(flag: str, typed: Path, target: bool) -> None:
    """The camera file a flag names, read as novel views read it, its images there; a target's frames must each
    have one (the intended result)."""
    try:
        _, _, frames = novel_views.read_camera_file(typed)
    except SkedUserError as error:
        raise type(error)(_flagged(flag, typed, error)) from error
    for index, frame in enumerate(frames):
        if target and frame.image is None:
            raise SkedUserError(f"{flag} {typed}: frame {index} has no 'file_path'; a target's frames are images of "
                                "the intended result (the edit is scored against them).")
        for what, image in (("image", frame.image), ("changed-region mask", frame.changed_mask)):
            if image is not None and not image.is_file():
                raise SkedFileNotFoundError(f"{flag} {typed}: frame {index}'s {what} {image} does not exist.")


def novel_view_cameras(cameras: Optional[str], target: Optional[Path]) -> str:
    """--cameras checked before anything loads ('eval' when not given): a --target is scored at its own cameras, so
    --cameras beside it is refused; the camera file either names is read and checked."""
    if target is not None:
        if cameras is not None:
            off = ", which --cameras none turns off" if cameras == "none" else ""
            raise SkedUserError(f"--cameras {cameras} and --target {target}: the target is scored at its own "
                                f"cameras{off}; pass one of them.")
        check_camera_file("--target", Path(target), target=True)
        return "eval"
    cameras = "eval" if cameras is None else cameras
    if is_orbit(cameras):
        orbit_count(cameras)
    elif cameras not in ("eval", "none"):
        if not Path(cameras).exists():
            raise SkedFileNotFoundError(f"--cameras {cameras}: no such camera file or folder (or give 'eval', "
                                        "'orbit[:N]' or 'none').")
        check_camera_file("--cameras", Path(cameras), target=False)
    return cameras


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
        views, source = novel_views.eval_split_views(pipeline, resolution, background), "the base dataset's eval split"
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
    edit_pipeline = load_pipeline(edit.run_dir, device)
    # The edit holds a frozen copy of its own base: render that unless another base is asked for.
    base_pipeline = None if own_base else load_pipeline(base_run, device)
    sketch_set = sketch_set.in_model_frame(edit_pipeline.datamanager.data_frame_transform)
    lpips, lpips_reason = _lpips_or_reason()

    views, rows = [], []
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
    keys = [key for key in views[0] if key != "view"]
    result = {
        "edit_run": str(edit.run_dir),
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
        views_to_score, source = choose_novel_views(edit_pipeline, cameras, target, novel_resolution, max_novel_views)
        # Against the edit's frozen copy of its base (bit-identical to the base), which knows the sketches.
        novel = novel_views.evaluate_novel_views(edit_pipeline.model, views_to_score, target=target is not None)
        width = rows[0].shape[1]
        rows += [torch.nn.functional.interpolate(row.permute(2, 0, 1)[None], scale_factor=width / row.shape[1],
                                                 mode="bilinear")[0].permute(1, 2, 0) for row in novel.pop("rows")]
        result["novel_views"] = {"cameras": source, "resolution": novel_resolution, **novel}
    return {"metrics": result, "sheet": torch.cat(rows, dim=0)}


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1 (a size or a count of views)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


def edit_run_folder(config: Path) -> Path:
    """The run folder of sked-eval's CONFIG argument (a config.yml or its folder), checked up front so a bad
    path is named as sked-eval takes it (not as ns-train's --load-dir)."""
    run = config.parent if config.name == "config.yml" else config
    if not (run / "config.yml").is_file():
        raise SkedFileNotFoundError(f"sked-eval {config}: no {run / 'config.yml'}. Pass the edited run's config.yml "
                                    "(outputs/<experiment>/sked/<timestamp>/config.yml) or its run folder.")
    return run


def edit_scene(run: Path):
    """The edited run (config and latest checkpoint), refused if it is not a SKED edit."""
    edit = resolve_base(run, flag="sked-eval")
    if edit.family != "sked":
        raise SkedUserError(f"sked-eval {run}: a '{edit.method}' run, not a SKED edit; pass the config.yml of an "
                            "ns-train sked run (its base is what the edit is compared with).")
    check_run_files(edit, f"sked-eval {run}")
    return edit


def check_run_files(scene, named: str) -> None:
    """What loading a run reads besides its checkpoint: its data and, for an edit, its base's checkpoint and its
    sketch set (the model is set up from them), each named with its place in config.yml."""
    datamanager = scene.config.pipeline.datamanager
    needed = [("data", getattr(datamanager, "data", None) or getattr(datamanager.dataparser, "data", None))]
    if scene.family == "sked":
        needed += [("base's checkpoint", scene.model_config.base_checkpoint),
                   ("sketch set", scene.model_config.sketches)]
    for what, path in needed:
        if path is not None and not Path(path).exists():
            raise SkedFileNotFoundError(f"{named}: its {what} {path} is missing (named in {scene.run_dir / 'config.yml'}, "
                                        "and loading the run needs it); put it back there.")


def check_base(base: Path, edit, device: str) -> None:
    """--base: a run sked-eval can render here, other than the edit."""
    scene = resolve_base(base, flag="--base")
    check_run_files(scene, f"--base {base}")
    if scene.run_dir.resolve() == edit.run_dir.resolve():
        raise SkedUserError(f"--base {base}: that is the edit itself; leave --base out to compare the edit with its "
                            "base, or pass the base's run folder.")
    if scene.family == "instant-ngp" and not device.startswith("cuda"):
        raise SkedUserError(f"--base {base}: an instant-ngp run renders with nerfacc's CUDA kernels only; pass "
                            "--device cuda on a GPU, or leave --base out (the edit's frozen copy of its base renders "
                            "anywhere).")
    if scene.family == "sked":
        warn(f"--base {base}: a SKED edit, not a base scene; the metrics compare the two edits.")


def checked_sketches(typed: Optional[Path], model_config) -> tuple:
    """(folder, sketch set): --sketches, or the edit's own; a problem names which."""
    folder = Path(typed) if typed else Path(model_config.sketches)
    try:
        return folder, load_sketch_set(folder)
    except (OSError, ValueError) as error:
        if typed:
            raise SkedUserError(f"--sketches {typed}: {error}") from error
        raise SkedUserError(f"the edit's sketch set {folder} (its config.yml) cannot be loaded: {error} Pass "
                            "--sketches <folder with sketches.json>.") from error


def check_sketch_masks(sketch_set, resolution: int) -> None:
    """IoS needs sketch pixels and the outside metrics pixels outside the sketch, at the size views render."""
    for index, view in enumerate(sketch_set.views):
        mask = resized_mask(view, resolution)
        name = f"sketch view {index}" + (f" ({view.name})" if view.name else "")
        if min(mask.shape) < SSIM_MIN_SIDE:
            least = int(np.ceil(SSIM_MIN_SIDE * max(view.width, view.height) / min(view.width, view.height)))
            raise SkedUserError(f"--resolution {resolution}: {name} renders at {mask.shape[1]}x{mask.shape[0]} px, too "
                                f"small for SSIM (at least {SSIM_MIN_SIDE} px a side); pass --resolution {least} or more.")
        if not mask.any():
            raise SkedUserError(f"--resolution {resolution}: {name} covers no pixel at this size; pass a larger "
                                "--resolution.")
        if mask.all():
            raise SkedUserError(f"{name} covers its whole image at --resolution {resolution}: nothing outside the "
                                "sketch to compare; redraw it smaller than the view.")


def check_device(device: str) -> None:
    try:
        parsed = torch.device(device)
    except RuntimeError:
        raise SkedUserError(f"--device {device}: not a device torch knows; pass cpu, cuda or cuda:<index>.") from None
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise SkedUserError(f"--device {device}: no CUDA GPU is visible here; pass --device cpu.")
        if parsed.index is not None and parsed.index >= count:
            raise SkedUserError(f"--device {device}: only {count} GPU(s) visible here (cuda:0 to cuda:{count - 1}).")
    elif parsed.type != "cpu":
        raise SkedUserError(f"--device {device}: sked-eval renders on cpu or cuda.")


def check_clip_model(source: str) -> None:
    """A --clip-model typed by the user names a folder or a model in the Hugging Face cache (nothing is downloaded);
    the default's absence is reported in the results instead."""
    if Path(source).expanduser().exists():
        return
    try:
        from huggingface_hub import try_to_load_from_cache

        cached = try_to_load_from_cache(source, "config.json")
    except Exception:  # not a hub id at all
        cached = None
    if not isinstance(cached, str):
        raise SkedFileNotFoundError(f"--clip-model {source}: no such folder, nor a model of that name in the Hugging "
                                    "Face cache (sked-eval downloads nothing); pass a folder saved with "
                                    f"save_pretrained, or leave it out ({DEFAULT_CLIP}).")


def warn_unusual(args) -> None:
    """Legal settings that are almost surely a mistake."""
    for flag, value in (("--resolution", args.resolution), ("--novel-resolution", args.novel_resolution),
                        ("--clip-resolution", args.clip_resolution)):
        if value > LARGE_RENDER:
            warn(f"{flag} {value}: renders of {value * value} rays a view; sked-eval's renders are usually "
                 f"128-512 px.")
    if args.clip_views > MANY_CLIP_VIEWS:
        warn(f"--clip-views {args.clip_views}: that many renders for one CLIP figure; the paper averages 40.")
    if args.cameras is not None and is_orbit(args.cameras) and orbit_count(args.cameras) > args.max_novel_views:
        warn(f"--cameras {args.cameras}: only {args.max_novel_views} of the {orbit_count(args.cameras)} orbit views "
             f"are scored (--max-novel-views {args.max_novel_views}).")


def _earlier_result(path: Path) -> bool:
    """Whether `path` holds a result sked-eval wrote (so --overwrite may replace it)."""
    try:
        return "edit_run" in json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, TypeError):
        return False


def output_paths(run: Path, output: Optional[Path], sheet: Optional[Path], overwrite: bool) -> tuple[Path, Path]:
    """Where the metrics JSON and contact sheet go: next to the edit by default; an earlier result is never
    replaced unless --overwrite says so, and nothing else ever."""
    import cv2

    output = output if output is not None else run / "sked_eval.json"
    sheet = sheet if sheet is not None else output.with_suffix(".png")
    for flag, path in (("--output", output), ("--sheet", sheet)):
        if path.is_dir():
            raise SkedUserError(f"{flag} {path}: a folder; pass a file name in it.")
    if output.resolve() == sheet.resolve():
        raise SkedUserError(f"--output {output} and --sheet {sheet}: the same file; the metrics are JSON and the "
                            "sheet an image: pass two names.")
    if not cv2.haveImageWriter(str(sheet)):
        raise SkedUserError(f"--sheet {sheet}: OpenCV writes no image with that ending; end it in .png (or .jpg).")
    existing = [str(path) for path in (output, sheet) if path.exists()]
    if existing and not overwrite:
        raise SkedUserError(f"sked-eval: {' and '.join(existing)} already exist(s) (an earlier evaluation?). Pass "
                            "another --output (and --sheet), or --overwrite to replace them.")
    if output.exists() and not _earlier_result(output):
        raise SkedUserError(f"--output {output}: not an earlier sked-eval result, and --overwrite replaces only those; "
                            "pass another name.")
    # Before minutes of rendering, not after: a folder that cannot hold the results is refused now.
    check_writable_folder(output.parent, "--output")
    check_writable_folder(sheet.parent, "--sheet")
    return output, sheet


def write_outputs(outcome: dict, output: Path, sheet: Path) -> None:
    """The contact sheet, then the metrics JSON (whose presence says the evaluation is whole), each written beside
    and renamed into place, so a kill leaves the earlier result or none."""
    import cv2

    partial = sheet.with_name(f".{sheet.stem}.partial{sheet.suffix}")  # the suffix tells OpenCV the format
    if not cv2.imwrite(str(partial), (outcome["sheet"].numpy().clip(0, 1) * 255).round().astype(np.uint8)[..., ::-1]):
        raise SkedUserError(f"--sheet {sheet}: could not write the contact sheet (OpenCV needs a writable path "
                            "ending in .png).")
    publish_atomically(partial, sheet)
    write_text_atomically(output, json.dumps(outcome["metrics"], indent=2))


def eval_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sked-eval", description=__doc__.split("\n")[0])
    parser.add_argument("config", type=Path, help="the edited run's config.yml (or its run folder)")
    parser.add_argument("--base", type=Path, default=None, help="base run folder (default: the one the edit used)")
    parser.add_argument("--sketches", type=Path, default=None, help="sketch set (default: the one the edit used)")
    parser.add_argument("--output", type=Path, default=None,
                        help="metrics JSON to write (default: sked_eval.json in the edit's run folder)")
    parser.add_argument("--sheet", type=Path, default=None, help="contact sheet PNG (default: next to --output)")
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier --output / --sheet")
    parser.add_argument("--resolution", type=positive_int, default=256)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--prompt", default=None, help="prompt for CLIP similarity (default: the edit's)")
    parser.add_argument("--clip-model", default=None, help=f"CLIP hub id (cached) or local folder (default {DEFAULT_CLIP})")
    parser.add_argument("--clip-views", type=positive_int, default=40, help="views around the edit for CLIP similarity")
    parser.add_argument("--clip-resolution", type=positive_int, default=128, help="render size of those views")
    parser.add_argument("--cameras", default=None,
                        help="novel views: 'eval' (the base dataset's eval split; the default), 'orbit[:N]' around the "
                             "edit box, a camera file in the base's data frame (nerfstudio-data transforms.json, "
                             "Blender transforms_<split>.json, or their folder), or 'none'")
    parser.add_argument("--target", type=Path, default=None,
                        help="ground truth of the intended result (a camera file as for --cameras, with its images): "
                             "scored at its own cameras (instead of --cameras) inside and outside the changed region")
    parser.add_argument("--novel-resolution", type=positive_int, default=256, help="longer side of the novel-view renders")
    parser.add_argument("--max-novel-views", type=positive_int, default=12, help="at most this many novel views (evenly spread)")
    return parser


def check_flags(args) -> None:
    """What sked-eval's flags name, checked without the edit: cameras, target, base folder, sketches, prompt."""
    novel_view_cameras(args.cameras, args.target)
    if args.base is not None and not Path(args.base).exists():
        raise SkedFileNotFoundError(f"--base {args.base}: no such run folder.")
    if args.sketches is not None:
        check_sketch_masks(checked_sketches(args.sketches, None)[1], args.resolution)
    if args.prompt is not None and not args.prompt.strip():
        raise SkedUserError(f"--prompt {args.prompt!r}: empty; leave it out to use the edit's prompt.")
    if args.clip_model is not None:
        check_clip_model(args.clip_model)
    warn_unusual(args)


def check_eval_flags(flags) -> None:
    """sked-batch's `eval:` flags, before the edit they follow runs: parsed and checked as sked-eval will (the
    report reads sked_eval.json in the run folder, so --output and --sheet are refused)."""
    parser = eval_parser()

    def refuse(message: str):
        raise SkedUserError(message)

    parser.error = refuse
    args = parser.parse_args(["<the job's run>/config.yml", *flags])
    for flag in ("output", "sheet"):
        if getattr(args, flag) is not None:
            raise SkedUserError(f"--{flag} is not for a plan's eval flags: the report reads sked_eval.json and "
                                "sked_eval.png in each job's run folder.")
    check_flags(args)


def entrypoint() -> None:
    from sked_ns.compat import quiet_third_party_warnings
    from sked_ns.errors import show_warnings_as_lines

    quiet_third_party_warnings()
    show_warnings_as_lines()
    args = eval_parser().parse_args()
    # Every input, then the outputs, before anything is written or rendered.
    run = edit_run_folder(args.config)
    check_flags(args)
    check_device(args.device)
    edit = edit_scene(run)
    if args.base is not None:
        check_base(args.base, edit, args.device)
    _, sketch_set = checked_sketches(args.sketches, edit.model_config)
    check_sketch_masks(sketch_set, args.resolution)
    output, sheet = output_paths(run, args.output, args.sheet, args.overwrite)
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
    print(f"wrote {output} and {sheet}")


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
    for key, label, unit in (("psnr_keep", "PSNR kept", " dB"), ("ssim_keep", "SSIM kept", ""), ("leak", "leak", ""),
                             ("psnr_keep_gt", "kept vs ground truth", " dB"),
                             ("psnr_target_changed", "changed vs target", " dB")):
        if key in mean:
            base = mean.get(key + "_base")
            parts.append(f"{label} {mean[key]:.3g}{unit}" + (f" (base {base:.3g}{unit})" if base is not None else ""))
    return " ".join(parts[:1]) + " " + ", ".join(parts[1:])


if __name__ == "__main__":
    entrypoint()
