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
- with ground-truth images (the evaluation split's photos, or `--target`): `psnr_keep_gt` and, for
  the base, `psnr_keep_gt_base`;
- with `--target` (images of the intended result at the same cameras): PSNR against the target
  inside and outside the changed region (`psnr_target_changed`, `psnr_target_unchanged`, and the
  base's figures beside them). The changed region is each frame's `changed_mask_path` when given
  (benchmark scenes write it), else where the target differs from the base render by > 0.1.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from sked_ns.cameras import cameras_of
from sked_ns.metrics import psnr_outside, ssim_outside
from sked_ns.sketches import DataparserTransform

KEEP_THRESHOLD = 0.95
"""P above this in base and edit: the pixel shows only what the edit must keep."""
CHANGED_DIFFERENCE = 0.1
"""Without a changed-region mask: target and base render differ by more than this (any channel)."""


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


def transforms_views(path: Path, transform: DataparserTransform, resolution: int, background,
                     with_images: bool) -> List[NovelView]:
    """Cameras of a nerfstudio transforms.json in the base's data frame (its images as ground truth)."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    try:
        meta = json.loads(path.read_text())
        frames = meta["frames"]
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(f"{path}: not a readable nerfstudio transforms.json with 'frames' ({error}).") from error
    views = []
    for index, frame in enumerate(frames):
        get = lambda key: frame.get(key, meta.get(key))  # noqa: E731  (per-frame intrinsics override)
        missing = [key for key in ("fl_x", "w", "h") if get(key) is None]
        if missing or "transform_matrix" not in frame:
            raise ValueError(f"{path}: frame {index} lacks {missing or ['transform_matrix']}; give them per frame or "
                             "at the top level, as nerfstudio's transforms.json does.")
        pose = transform.apply(np.asarray(frame["transform_matrix"], dtype=np.float64)[:3])
        width, height = int(get("w")), int(get("h"))
        camera = cameras_of(torch.tensor(pose[None], dtype=torch.float32), float(get("fl_x")),
                            float(get("fl_y") or get("fl_x")), float(get("cx") if get("cx") is not None else width / 2),
                            float(get("cy") if get("cy") is not None else height / 2), width, height)
        camera = _rescaled(camera, resolution)
        ground_truth = changed = None
        if with_images and "file_path" in frame:
            ground_truth = _read_image(path.parent / frame["file_path"], path, index)
            ground_truth = torch.from_numpy(_resize(_on_background(ground_truth, background), camera))
        if with_images and "changed_mask_path" in frame:
            mask = _read_image(path.parent / frame["changed_mask_path"], path, index)
            changed = torch.from_numpy(_resize(mask[..., :3].max(-1), camera) > 0.5)
        views.append(NovelView(camera, Path(frame.get("file_path", f"frame_{index:03d}")).name, ground_truth, changed))
    return views


def _read_image(image_path: Path, transforms: Path, index: int) -> np.ndarray:
    image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{transforms}: frame {index}'s image {image_path} cannot be read.")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    image = image[..., [2, 1, 0, 3][: image.shape[-1]]]  # BGR(A) -> RGB(A)
    return image.astype(np.float32) / (65535.0 if image.dtype == np.uint16 else 255.0)


def orbit_views(centre: np.ndarray, radius: float, count: int, resolution: int) -> List[NovelView]:
    """`count` cameras on two rings around the edit box (no ground truth)."""
    from sked_ns.clip_score import orbit_cameras
    from sked_ns.random_views import focal_from_fov

    focal = focal_from_fov(50.0, resolution)
    return [NovelView(cameras_of(torch.tensor(pose[None], dtype=torch.float32), focal, focal, resolution / 2,
                                 resolution / 2, resolution, resolution).reshape(()), f"orbit_{index:02d}")
            for index, pose in enumerate(orbit_cameras(centre, radius, count, elevations=(10.0, 30.0, 50.0)))]


def _psnr(a: Tensor, b: Tensor, where: Tensor) -> Optional[float]:
    return psnr_outside(a, b, ~where) if where.any() else None


def score_view(model, view: NovelView) -> Dict:
    """Render edit and base at one camera and compute the novel-view figures (see the module docstring)."""
    from sked_ns.render import render_camera

    edit = render_camera(model, view.camera)
    base = render_camera(model, view.camera, base=True)
    keep = (edit["preservation_weight"] > KEEP_THRESHOLD) & (base["preservation_weight"] > KEEP_THRESHOLD)
    entry: Dict = {"view": view.name, "keep_fraction": float(keep.float().mean())}
    if keep.any():
        entry["psnr_keep"] = psnr_outside(edit["rgb"], base["rgb"], ~keep)
        entry["ssim_keep"] = ssim_outside(edit["rgb"], base["rgb"], ~keep)
        entry["leak"] = float((edit["accumulation"] - base["accumulation"]).clamp_min(0)[keep].mean())
    if view.ground_truth is not None:
        truth = view.ground_truth
        if keep.any():
            entry["psnr_keep_gt"] = psnr_outside(edit["rgb"], truth, ~keep)
            entry["psnr_keep_gt_base"] = psnr_outside(base["rgb"], truth, ~keep)
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


def evaluate_novel_views(model, views: List[NovelView], target: bool = False, sheet_rows: int = 4) -> Dict:
    """Per-view figures, their means, and contact-sheet rows for the first `sheet_rows` views."""
    entries, rows = [], []
    for index, view in enumerate(views):
        scored = score_view(model, view)
        if target and view.ground_truth is not None:
            score_target(scored, view)
        entries.append(scored["entry"])
        if index < sheet_rows:
            rows.append(sheet_row(scored))
    keys = sorted({key for entry in entries for key in entry if key != "view"})
    mean = {key: float(np.mean([e[key] for e in entries if key in e])) for key in keys}
    return {"views": entries, "mean": mean, "keep_threshold": KEEP_THRESHOLD, "rows": rows}
