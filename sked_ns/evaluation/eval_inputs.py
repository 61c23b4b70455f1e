"""What sked-eval is given, checked before anything is rendered or written: the runs, sketches, cameras, target,
device, CLIP weights and output paths; and its command line."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from sked_ns.engine.base_scene import resolve_base
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, check_writable_folder, warn
from sked_ns.evaluation import novel_views
from sked_ns.evaluation.eval_args import DEFAULT_CLIP, eval_parser
from sked_ns.evaluation.metrics import SSIM_MIN_SIDE
from sked_ns.evaluation.render import resized_mask
from sked_ns.method.frozen_base import base_weights
from sked_ns.sketches.sketch_set import load_sketch_set

LARGE_RENDER = 2048
"""A render side above this is surely a typo (millions of rays a view)."""
MANY_CLIP_VIEWS = 400
"""Ten times the paper's 40 CLIP views: more is surely a typo."""
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
        if scene.model_config.base_checkpoint is not None:
            base_weights(scene.model_config)  # the edit's own copy of its base (the base run's before it has one)
        needed += [("sketch set", scene.model_config.sketches)]
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
    if scene.representation is not None and scene.representation.stock_render_needs_cuda and not device.startswith("cuda"):
        raise SkedUserError(f"--base {base}: an {scene.family} run renders with CUDA kernels only; pass "
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
    if args.load_config is not None:
        raise SkedUserError("--load-config is not for a plan's eval flags: each job evaluates its own run.")
    for flag in ("output", "sheet"):
        if getattr(args, flag) is not None:
            raise SkedUserError(f"--{flag} is not for a plan's eval flags: the report reads sked_eval.json and "
                                "sked_eval.png in each job's run folder.")
    check_flags(args)
