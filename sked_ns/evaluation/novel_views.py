"""Novel-view evaluation: does the edit keep the scene from every viewpoint, not only the sketch views?

The paper scores only the sketch views, where floaters in front of the object, damage on its far
side or haze in the empty space around it are barely visible. Here the edit and its frozen base
are rendered at other cameras (the base dataset's evaluation split by default, given cameras, or
an orbit around the edit box), each with its per-pixel preservation weight

    P = sum_i T_i alpha_i w(p_i) + (1 - accumulation),

1 where the pixel shows only content the edit must keep (background counts as kept), 0 where it
shows content the edit may change. A pixel is *kept* when P > KEEP_THRESHOLD in both renders:
neither the base nor the edit shows anything near the sketches there. Over the kept pixels:

- `psnr_keep`, `ssim_keep`: edit against base;
- `leak`: mean of max(0, accumulation_edit - accumulation_base), new opacity where the edit may
  not act (floaters, haze); 0 for a perfect edit;
- with ground-truth images (the evaluation split's photos, or `--target`): `psnr_keep_gt`, `ssim_keep_gt` and,
  for the base, `psnr_keep_gt_base`, `ssim_keep_gt_base` (for a capture: what the base itself misses of its
  photos beside what the edit adds to that);
- with `--target` (images of the intended result at the same cameras): PSNR against the target
  inside and outside the changed region (`psnr_target_changed`, `psnr_target_unchanged`, and the
  base's figures beside them). The changed region is each frame's `changed_mask_path` when given
  (benchmark scenes write it), else where the target differs from the base render by > 0.1.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.evaluation.metrics import SSIM_MIN_SIDE, psnr_outside, ssim_outside
from sked_ns.sketches.cameras import PinholeCamera, cameras_of
from sked_ns.sketches.data_frame import file_to_model
from sked_ns.sketches.data_frame import matrix_field as _matrix
from sked_ns.sketches.data_frame import number_field as _number
from sked_ns.sketches.sketch_set import DataparserTransform

KEEP_THRESHOLD = 0.95
"""P above this in base and edit: the pixel shows only what the edit must keep."""
CHANGED_DIFFERENCE = 0.1
"""Without a changed-region mask: target and base render differ by more than this (any channel)."""
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "EQUIRECTANGULAR",
                 "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R", "ORTHOPHOTO", "FISHEYE624")
"""transforms.json `camera_model`s, as nerfstudio's CAMERA_MODEL_TO_TYPE names them (checked by a test)."""


@dataclass
class NovelView:
    """A camera (model frame) with optional ground truth at its own resolution."""

    camera: object  # nerfstudio Cameras, one camera
    name: str
    ground_truth: Optional[Tensor] = None
    """(h, w, 3) in [0, 1], composited on the model's background."""
    changed: Optional[Tensor] = None
    """(h, w) bool: where the intended result differs from the base."""


def _rescaled(camera, resolution: int):
    longer = max(int(camera.width), int(camera.height))
    camera = camera.reshape(())  # a single camera
    if longer != resolution:
        camera = copy.deepcopy(camera)  # rescaling is in place; the dataset's cameras stay as they are
        camera.rescale_output_resolution(resolution / longer)
    return camera


def _resize(image: np.ndarray, camera) -> np.ndarray:
    size = (int(camera.width), int(camera.height))
    if image.shape[1::-1] == size:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if image.shape[1] > size[0] else cv2.INTER_LINEAR)


def _on_background(image: np.ndarray, background: Sequence[float]) -> np.ndarray:
    if image.shape[-1] == 4:
        alpha = image[..., 3:]
        return image[..., :3] * alpha + np.asarray(background, dtype=np.float32) * (1 - alpha)
    return image[..., :3]


def eval_split_views(pipeline, resolution: int, background) -> List[NovelView]:
    """The base dataset's evaluation split: its cameras and photos (the base's ground truth)."""
    dataset = pipeline.datamanager.eval_dataset
    views = []
    for index in range(len(dataset)):
        camera = _rescaled(dataset.cameras[index], resolution)
        image = _on_background(dataset.get_image_float32(index).numpy(), background)
        name = Path(dataset.image_filenames[index]).name
        views.append(NovelView(camera, name, torch.from_numpy(_resize(image, camera).astype(np.float32))))
    return views


CAMERA_FILES = ("transforms.json", "transforms_test.json")
"""A folder's camera file, first found: nerfstudio-data and instant-ngp-data's, then Blender's (and D-NeRF's) test split."""
DISTORTION_FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""nerfstudio's lens distortion fields, in the order of its `distortion_params`."""


@dataclass
class FrameCamera(PinholeCamera):
    """One frame of a camera file as nerfstudio's dataparsers read it: a PinholeCamera in the file's frame (3x4,
    OpenGL axes) at the file's resolution, with its lens."""

    camera_model: str = "OPENCV"
    """A nerfstudio `camera_model` (CAMERA_MODEL_TO_TYPE): perspective, fisheye, equirectangular, ..."""
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(6))
    """[k1, k2, k3, k4, p1, p2]."""
    image: Optional[Path] = None
    changed_mask: Optional[Path] = None
    name: str = ""


def camera_file(path: Path) -> Path:
    """The camera file at `path`: the file itself, or a folder's transforms.json or (Blender) transforms_test.json."""
    path = Path(path)
    if path.is_dir():
        for name in CAMERA_FILES:
            if (path / name).is_file():
                return path / name
        raise SkedFileNotFoundError(f"{path}: no camera file here (looked for {' and '.join(CAMERA_FILES)}). Pass a "
                                    "nerfstudio-data transforms.json, a Blender transforms_<split>.json, or their folder.")
    if not path.is_file():
        raise SkedFileNotFoundError(f"{path}: no such camera file. Pass a nerfstudio-data transforms.json, a Blender "
                                    "transforms_<split>.json, or their folder.")
    return path


def _image_path(folder: Path, file_path: str) -> Path:
    """As the dataparsers resolve `file_path`: relative to the file's folder, '.png' added if absent (Blender)."""
    path = folder / file_path
    if not path.exists() and (folder / f"{file_path}.png").exists():
        return folder / f"{file_path}.png"
    return path


def _distortion(entry: dict, where: str) -> np.ndarray:
    if "distortion_params" in entry:
        try:
            coefficients = np.asarray(entry["distortion_params"], dtype=np.float64)
        except (TypeError, ValueError):
            coefficients = np.empty(0)
        if coefficients.shape != (6,) or not np.all(np.isfinite(coefficients)):
            raise SkedUserError(f"{where}: 'distortion_params' must be 6 numbers [k1, k2, k3, k4, p1, p2], "
                                f"got {entry['distortion_params']!r}.")
        return coefficients
    return np.array([_number(entry[key], where, key) if key in entry else 0.0 for key in DISTORTION_FIELDS])


def _focal(get, where: str, axis: str, size: Optional[float]) -> Optional[float]:
    """fl_x (fl_y) as nerfstudio's dataparsers find it: given, or from x_fov (degrees) or camera_angle_x (radians)."""
    if get(f"fl_{axis}") is not None:
        return _number(get(f"fl_{axis}"), where, f"fl_{axis}", positive=True)
    for key, radians in ((f"{axis}_fov", False), (f"camera_angle_{axis}", True)):
        if get(key) is not None:
            angle = _number(get(key), where, key, positive=True)
            angle = angle if radians else np.radians(angle)
            if not angle < np.pi:
                raise SkedUserError(f"{where}: '{key}' is the horizontal field of view and must be under "
                                    f"{'pi (radians)' if radians else '180 (degrees)'}, got {get(key)!r}.")
            return None if size is None else 0.5 * size / np.tan(0.5 * angle)
    return None


def read_camera_file(path: Path) -> tuple[Path, dict, List[FrameCamera]]:
    """(file, its JSON, its frames) of a camera file nerfstudio's dataparsers read, intrinsics resolved as they do.

    - nerfstudio-data (`transforms.json`): fl_x, fl_y, cx, cy, w, h, distortion (k1 ... p2 or distortion_params)
      at the top level or per frame; a top-level value wins, as in nerfstudio; `camera_model` at the top level.
    - instant-ngp-data: the same file, with `camera_angle_x` / `x_fov` instead of fl_x, cx and cy at the centre,
      `is_fisheye`.
    - Blender (`transforms_<split>.json`): `camera_angle_x` only; w and h are those of the first frame's image,
      `file_path` has no extension ('.png' is added); poses are used as they are (the dataparser only scales them).
    """
    path = camera_file(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise SkedUserError(f"{path}: not readable as JSON ({error}).") from error
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames or not all(isinstance(frame, dict) for frame in frames):
        raise SkedUserError(f"{path}: expected a JSON object with a non-empty list 'frames' of camera entries, as in "
                            "nerfstudio's transforms.json or Blender's transforms_<split>.json.")
    camera_model = "OPENCV_FISHEYE" if meta.get("is_fisheye") else str(meta.get("camera_model", "OPENCV"))
    if camera_model not in CAMERA_MODELS:
        raise SkedUserError(f"{path}: unknown 'camera_model' {camera_model!r}; nerfstudio knows "
                            f"{', '.join(CAMERA_MODELS)}.")
    image_size = None  # (w, h) of the first frame's image, for files without w and h (Blender)
    result = []
    for index, frame in enumerate(frames):
        where = f"{path} frame {index}"
        get = lambda key: meta[key] if key in meta else frame.get(key)  # noqa: E731  (a top-level value wins)
        if "transform_matrix" not in frame:
            raise SkedUserError(f"{where}: missing 'transform_matrix' (its 4x4 camera-to-world pose).")
        pose = _matrix(frame["transform_matrix"], where, "transform_matrix", 4)
        if (get("w") is None or get("h") is None) and image_size is None:
            image_size = _size_from_image(path, frame, where)
        width = int(_number(get("w"), where, "w", positive=True)) if get("w") is not None else image_size[0]
        height = int(_number(get("h"), where, "h", positive=True)) if get("h") is not None else image_size[1]
        fl_x = _focal(get, where, "x", width)
        if fl_x is None:
            raise SkedUserError(f"{where}: no focal length; give 'fl_x' (pixels) or 'camera_angle_x' (radians, "
                                "Blender) per frame or at the top level, as nerfstudio's dataparsers read it.")
        fl_y = _focal(get, where, "y", height) or fl_x
        distortion = _distortion(meta if any(key in meta for key in (*DISTORTION_FIELDS, "distortion_params"))
                                 else frame, where)
        result.append(FrameCamera(
            camera_to_world=pose, fl_x=fl_x, fl_y=fl_y,
            cx=_number(get("cx"), where, "cx") if get("cx") is not None else width / 2,
            cy=_number(get("cy"), where, "cy") if get("cy") is not None else height / 2,
            width=width, height=height, camera_model=camera_model, distortion=distortion,
            image=_image_path(path.parent, frame["file_path"]) if "file_path" in frame else None,
            changed_mask=path.parent / frame["changed_mask_path"] if "changed_mask_path" in frame else None,
            name=Path(frame.get("file_path", f"frame_{index:03d}")).name))
    return path, meta, result


def _size_from_image(path: Path, frame: dict, where: str) -> tuple[int, int]:
    """(w, h) of a frame's image, read from its header (Blender files carry no w and h)."""
    from PIL import Image

    if "file_path" not in frame:
        raise SkedUserError(f"{where}: no 'w' and 'h' and no 'file_path' to read them from; give 'w' and 'h' "
                            "(pixels) per frame or at the top level.")
    image = _image_path(path.parent, frame["file_path"])
    try:
        with Image.open(image) as opened:
            return opened.size
    except OSError as error:
        raise SkedUserError(f"{where}: no 'w' and 'h', and its image {image} cannot be read ({error}); without 'w' "
                            "and 'h' they are read from the first frame's image (its 'file_path', '.png' added when "
                            "absent), as nerfstudio's Blender dataparser does.") from error


def frame_camera(frame: FrameCamera, transform: DataparserTransform):
    """A nerfstudio `Cameras` (one camera, model frame) of a camera-file frame, lens model and distortion kept."""
    from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras

    pose = torch.tensor(transform.apply(frame.camera_to_world), dtype=torch.float32)
    return Cameras(camera_to_worlds=pose[None], fx=frame.fl_x, fy=frame.fl_y, cx=frame.cx, cy=frame.cy,
                   width=frame.width, height=frame.height,
                   distortion_params=torch.tensor(frame.distortion, dtype=torch.float32)[None],
                   camera_type=CAMERA_MODEL_TO_TYPE[frame.camera_model])


def transforms_views(path: Path, transform: DataparserTransform, resolution: int, background,
                     with_images: bool, applies_file_transform: bool = True) -> List[NovelView]:
    """Cameras of a camera file (`read_camera_file`) in the model frame, its images as ground truth.

    `transform`: the base run's dataparser transform; `applies_file_transform`: the base's dataparser is
    nerfstudio-data (`file_to_model`).
    """
    path, meta, frames = read_camera_file(path)
    to_model = file_to_model(transform, meta, path.parent, applies_file_transform)
    views = []
    for index, frame in enumerate(frames):
        camera = _rescaled(frame_camera(frame, to_model), resolution)
        ground_truth = changed = None
        if with_images and frame.image is not None:
            ground_truth = _read_image(frame.image, path, index)
            ground_truth = torch.from_numpy(_resize(_on_background(ground_truth, background), camera))
        if with_images and frame.changed_mask is not None:
            mask = _read_image(frame.changed_mask, path, index)
            changed = torch.from_numpy(_resize(mask[..., :3].max(-1), camera) > 0.5)
        views.append(NovelView(camera, frame.name, ground_truth, changed))
    return views


def _read_image(image_path: Path, transforms: Path, index: int) -> np.ndarray:
    image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SkedUserError(f"{transforms} frame {index}: its image {image_path} cannot be read (missing, or not an "
                            "image OpenCV reads).")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    image = image[..., [2, 1, 0, 3][: image.shape[-1]]]  # BGR(A) -> RGB(A)
    return image.astype(np.float32) / (65535.0 if image.dtype == np.uint16 else 255.0)


def orbit_views(centre: np.ndarray, radius: float, count: int, resolution: int) -> List[NovelView]:
    """`count` cameras on two rings around the edit box (no ground truth)."""
    from sked_ns.evaluation.clip_score import orbit_cameras
    from sked_ns.sketches.random_views import focal_from_fov

    focal = focal_from_fov(50.0, resolution)
    return [NovelView(cameras_of(torch.tensor(pose[None], dtype=torch.float32), focal, focal, resolution / 2,
                                 resolution / 2, resolution, resolution).reshape(()), f"orbit_{index:02d}")
            for index, pose in enumerate(orbit_cameras(centre, radius, count, elevations=(10.0, 30.0, 50.0)))]


def _psnr(a: Tensor, b: Tensor, where: Tensor) -> Optional[float]:
    return psnr_outside(a, b, ~where) if where.any() else None


def score_view(model, view: NovelView) -> Dict:
    """Render edit and base at one camera and compute the novel-view figures (see the module docstring)."""
    from sked_ns.evaluation.render import render_camera

    edit = render_camera(model, view.camera)
    base = render_camera(model, view.camera, base=True)
    keep = (edit["preservation_weight"] > KEEP_THRESHOLD) & (base["preservation_weight"] > KEEP_THRESHOLD)
    entry: Dict = {"view": view.name, "keep_fraction": float(keep.float().mean())}
    if keep.any():
        entry["psnr_keep"] = psnr_outside(edit["rgb"], base["rgb"], ~keep)
        if min(keep.shape) >= SSIM_MIN_SIDE:  # else left out, not made up
            entry["ssim_keep"] = ssim_outside(edit["rgb"], base["rgb"], ~keep)
        entry["leak"] = float((edit["accumulation"] - base["accumulation"]).clamp_min(0)[keep].mean())
    if view.ground_truth is not None:
        truth = view.ground_truth
        if keep.any():
            entry["psnr_keep_gt"] = psnr_outside(edit["rgb"], truth, ~keep)
            entry["psnr_keep_gt_base"] = psnr_outside(base["rgb"], truth, ~keep)
            if min(keep.shape) >= SSIM_MIN_SIDE:
                entry["ssim_keep_gt"] = ssim_outside(edit["rgb"], truth, ~keep)
                entry["ssim_keep_gt_base"] = ssim_outside(base["rgb"], truth, ~keep)
    return {"entry": entry, "edit": edit, "base": base, "keep": keep}


def score_target(scored: Dict, view: NovelView) -> None:
    """PSNR against the intended result inside and outside the changed region (edit and base)."""
    entry, edit, base = scored["entry"], scored["edit"], scored["base"]
    changed = view.changed
    if changed is None:
        difference = (view.ground_truth - base["rgb"]).abs().amax(dim=-1).numpy().astype(np.float32)
        changed = torch.from_numpy(cv2.dilate((difference > CHANGED_DIFFERENCE).astype(np.uint8), np.ones((3, 3))) > 0)
    entry["changed_fraction"] = float(changed.float().mean())
    for name, render in (("", edit), ("_base", base)):
        inside, outside = _psnr(render["rgb"], view.ground_truth, changed), _psnr(render["rgb"], view.ground_truth, ~changed)
        if inside is not None:
            entry[f"psnr_target_changed{name}"] = inside
        if outside is not None:
            entry[f"psnr_target_unchanged{name}"] = outside


def sheet_row(scored: Dict) -> Tensor:
    """base | edit | edit with the may-change region dimmed and new opacity (leak) in magenta."""
    edit, base, keep = scored["edit"], scored["base"], scored["keep"]
    overlay = edit["rgb"].clone()
    overlay[~keep] = overlay[~keep] * 0.4
    leak = (edit["accumulation"] - base["accumulation"]).clamp_min(0) * keep
    overlay = overlay * (1 - leak[..., None]) + torch.tensor([1.0, 0.0, 1.0]) * leak[..., None]
    return torch.cat([base["rgb"], edit["rgb"], overlay], dim=1)


def evaluate_novel_views(model, views: List[NovelView], target: bool = False, sheet_rows: int = 4,
                         progress=None) -> Dict:
    """Per-view figures, their means, and contact-sheet rows for the first `sheet_rows` views; `progress` (a
    sked_ns.progress.Progress) hears of each view scored."""
    entries, rows = [], []
    for index, view in enumerate(views):
        scored = score_view(model, view)
        if target and view.ground_truth is not None:
            score_target(scored, view)
        entries.append(scored["entry"])
        if index < sheet_rows:
            rows.append(sheet_row(scored))
        if progress is not None:
            progress.step()
    keys = sorted({key for entry in entries for key in entry if key != "view"})
    mean = {key: float(np.mean([e[key] for e in entries if key in e])) for key in keys}
    return {"views": entries, "mean": mean, "keep_threshold": KEEP_THRESHOLD, "rows": rows}
