"""Sketch sets: the on-disk format users and tools share.

A sketch set is a folder with `sketches.json` and one PNG mask per view::

    {
      "frame": "data",            # or "model"
      "views": [
        {"mask_path": "masks/view_00.png",
         "transform_matrix": [[...4x4 camera-to-world, OpenGL axes...]],
         "fl_x": 400.0, "fl_y": 400.0, "cx": 256.0, "cy": 256.0, "w": 512, "h": 512},
        ...
      ]
    }

Views may carry nerfstudio's lens distortion fields (`k1` ... `p2` or `distortion_params`, as in
`transforms.json`, perspective cameras only): a mask painted on a distorted photo is resampled
at load time to the pinhole camera with the same intrinsics, the camera SKED renders with.

`"frame": "data"` (the default) means the poses live in the coordinate frame of the base
scene's `transforms.json`, so a user can paint masks straight onto two of their own
photos and copy those photos' camera entries. `"frame": "model"` means nerfstudio's
internal frame, the one the viewer shows. Masks are white (or opaque, for RGBA) on black
(or transparent); closed scribbles are filled.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, List, Literal, Optional, Tuple

import cv2
import numpy as np
import torch

from sked_ns.errors import SkedFileExistsError, SkedFileNotFoundError, SkedUserError
from sked_ns.run_lock import writing
from sked_ns.sketches.cameras import cameras_of, check_camera_to_world, distort

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras

SKETCHES_JSON = "sketches.json"
FRAMES = ("data", "model")
Frame = Literal["data", "model"]
DISTORTION_FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""nerfstudio's lens distortion fields, in the order of its `distortion_params`."""
PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""transforms.json `camera_model`s that nerfstudio treats as perspective cameras (k1 ... p2 in `distort`)."""


@dataclass(frozen=True)
class DataparserTransform:
    """The transform nerfstudio's dataparser applied to the base scene (data -> model frame)."""

    transform: np.ndarray = field(default_factory=lambda: np.eye(4)[:3])
    """3x4 matrix applied to data-frame poses."""
    scale: float = 1.0
    """Scale applied to the translations afterwards."""

    @classmethod
    def from_json(cls, path: Path) -> "DataparserTransform":
        """Read the `dataparser_transforms.json` nerfstudio writes next to a run's config.yml."""
        try:
            data = json.loads(Path(path).read_text())
            transform = np.asarray(data["transform"], dtype=np.float64)
            scale = float(data["scale"])
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise SkedUserError(f"{path}: not a readable nerfstudio dataparser_transforms.json ({error}).") from error
        if transform.shape != (3, 4) or not np.all(np.isfinite(transform)) or not (math.isfinite(scale) and scale > 0):
            raise SkedUserError(f"{path}: 'transform' must be a finite 3x4 matrix and 'scale' a positive number.")
        return cls(transform=transform, scale=scale)

    def apply(self, camera_to_world: np.ndarray) -> np.ndarray:
        """Map a 3x4 data-frame camera-to-world pose into the model frame, as the dataparser does."""
        rotation = self.transform[:, :3] @ camera_to_world[:, :3]
        origin = (self.transform[:, :3] @ camera_to_world[:, 3] + self.transform[:, 3]) * self.scale
        return np.concatenate([rotation, origin[:, None]], axis=1)

    def invert(self, camera_to_world: np.ndarray) -> np.ndarray:
        """Map a 3x4 model-frame pose back into the data frame (the dataparser's rotation is rigid)."""
        rotation_t = self.transform[:, :3].T
        origin = rotation_t @ (camera_to_world[:, 3] / self.scale - self.transform[:, 3])
        return np.concatenate([rotation_t @ camera_to_world[:, :3], origin[:, None]], axis=1)

    def points_to_model(self, points: "torch.Tensor") -> "torch.Tensor":
        """Data-frame points (..., 3) -> model frame."""
        matrix = torch.as_tensor(self.transform, dtype=points.dtype, device=points.device)
        return (points @ matrix[:, :3].T + matrix[:, 3]) * self.scale

    def points_to_data(self, points: "torch.Tensor") -> "torch.Tensor":
        """Model-frame points (..., 3) -> data frame."""
        matrix = torch.as_tensor(self.transform, dtype=points.dtype, device=points.device)
        return (points / self.scale - matrix[:, 3]) @ matrix[:, :3]


@dataclass(frozen=True)
class SketchView:
    """One sketch view: a pinhole camera and the filled mask of the region to edit."""

    mask: np.ndarray
    """(h, w) bool, True inside the region to edit."""
    camera_to_world: np.ndarray
    """3x4 camera-to-world, OpenGL axes, in the sketch set's frame."""
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    name: str = ""
    """Where the mask came from, for error messages."""

    @property
    def width(self) -> int:
        return int(self.mask.shape[1])

    @property
    def height(self) -> int:
        return int(self.mask.shape[0])

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([self.fl_x, self.fl_y, self.cx, self.cy], dtype=np.float64)

    def bounding_box(self) -> tuple[int, int, int, int]:
        """Pixel-edge box (u0, v0, u1, v1) around every mask pixel, all contours included."""
        rows = np.flatnonzero(self.mask.any(axis=1))
        cols = np.flatnonzero(self.mask.any(axis=0))
        return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


@dataclass(frozen=True)
class SketchSet:
    """Two or more sketch views in one coordinate frame."""

    views: List[SketchView]
    frame: Frame = "data"

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise SkedUserError(f"Unknown sketch frame {self.frame!r}: use one of {FRAMES}.")
        if len(self.views) < 2:
            raise SkedUserError(
                f"A sketch set needs at least two views to place the edit in 3D, got {len(self.views)}. "
                "Sketch the region from a second, different viewpoint."
            )

    def in_model_frame(self, dataparser_transform: Optional[DataparserTransform] = None) -> "SketchSet":
        """The same views with poses in nerfstudio's model frame.

        A data-frame set needs the base scene's dataparser transform; a model-frame set is
        returned unchanged.
        """
        if self.frame == "model":
            return self
        if dataparser_transform is None:
            raise ValueError(
                "This sketch set's poses are in the data frame ('frame': 'data'): pass the base scene's "
                "dataparser transform (its run folder's dataparser_transforms.json)."
            )
        views = [
            replace(
                view,
                camera_to_world=check_camera_to_world(
                    dataparser_transform.apply(view.camera_to_world), f"{view.name} (after the dataparser transform)"
                ),
            )
            for view in self.views
        ]
        return SketchSet(views=views, frame="model")


def sketch_view_size(view: SketchView, resolution: int) -> Tuple[int, int]:
    """(width, height) of a sketch view rescaled so the longer side is `resolution` pixels."""
    scale = resolution / max(view.width, view.height)
    return max(1, round(view.width * scale)), max(1, round(view.height * scale))


def sketch_view_at(view: SketchView, resolution: int) -> Tuple[Cameras, torch.Tensor]:
    """A sketch view's camera and mask rescaled so the longer side is `resolution` pixels."""
    width, height = sketch_view_size(view, resolution)
    sx, sy = width / view.width, height / view.height
    mask = cv2.resize(view.mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) > 0.5
    camera = cameras_of(torch.tensor(view.camera_to_world[None], dtype=torch.float32),
                        view.fl_x * sx, view.fl_y * sy, view.cx * sx, view.cy * sy, width, height)
    return camera, torch.from_numpy(mask)


def fill_scribbles(mask: np.ndarray) -> np.ndarray:
    """Fill every closed stroke; a filled blob stays as it is."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = np.zeros(mask.shape, dtype=np.uint8)
    cv2.drawContours(filled, contours, -1, color=1, thickness=cv2.FILLED)
    return filled.astype(bool) | mask


def mask_from_image(image: np.ndarray) -> np.ndarray:
    """Binary mask from a PNG: alpha where the image has transparency, else brightness."""
    scale = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    image = image.astype(np.float64) / scale
    if image.ndim == 3 and image.shape[2] == 4 and image[..., 3].min() < 1.0:
        return image[..., 3] > 0.5
    if image.ndim == 3:
        image = image[..., :3].mean(axis=2)
    return image > 0.5


def read_mask(path: Path, width: int, height: int) -> np.ndarray:
    """Read, binarise and fill one mask, checking it against its camera's size."""
    if not path.is_file():
        raise SkedFileNotFoundError(f"{path}: mask file not found. Check 'mask_path' in {SKETCHES_JSON}.")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SkedUserError(f"{path}: cannot read this mask as an image; save it as a PNG.")
    if image.shape[:2] != (height, width):
        raise SkedUserError(
            f"{path}: mask is {image.shape[1]}x{image.shape[0]} but its camera says w={width}, h={height}. "
            "Draw the mask on a canvas of the camera's size (or fix 'w'/'h')."
        )
    mask = fill_scribbles(mask_from_image(image))
    if not mask.any():
        raise SkedUserError(f"{path}: the mask is empty. Paint the region to edit in white (or opaque).")
    return mask


def undistort_mask(mask: np.ndarray, fl_x: float, fl_y: float, cx: float, cy: float, coefficients: np.ndarray) -> np.ndarray:
    """A mask painted on a distorted photo, as the pinhole camera with the same intrinsics sees it.

    Each pixel takes the photo's pixel its centre distorts into (nearest). The photo's rim that the
    pinhole view does not see (a thin border for barrel distortion) is dropped.
    """
    height, width = mask.shape
    rows, cols = np.mgrid[0:height, 0:width] + 0.5
    distorted = distort(np.stack([(cols - cx) / fl_x, (rows - cy) / fl_y], axis=-1), coefficients)
    u = np.floor(distorted[..., 0] * fl_x + cx)
    v = np.floor(distorted[..., 1] * fl_y + cy)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    undistorted = np.zeros_like(mask)
    undistorted[inside] = mask[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    return undistorted


def _number(entry: dict, key: str, where: str, positive: bool = False) -> float:
    if key not in entry:
        raise SkedUserError(f"{where}: missing field '{key}'.")
    try:
        value = float(entry[key])
    except (TypeError, ValueError):
        raise SkedUserError(f"{where}: field '{key}' must be a number, got {entry[key]!r}.") from None
    if not math.isfinite(value) or (positive and value <= 0):
        raise SkedUserError(f"{where}: field '{key}' must be a finite{' positive' if positive else ''} number, got {value}.")
    return value


def _distortion(entry: dict, camera_model: str, where: str) -> np.ndarray:
    """[k1, k2, k3, k4, p1, p2], read as nerfstudio reads a transforms.json frame (missing fields are 0)."""
    if camera_model not in PERSPECTIVE_MODELS:
        raise SkedUserError(
            f"{where}: 'camera_model' {camera_model!r} is not a perspective camera; sketch masks need one of "
            f"{PERSPECTIVE_MODELS}. Paint the mask on an undistorted (pinhole) image of the view, or on a render of the "
            "base (`sked-sketch`), and give that camera."
        )
    if "distortion_params" not in entry:
        return np.array([_number(entry, key, where) if key in entry else 0.0 for key in DISTORTION_FIELDS])
    try:
        coefficients = np.asarray(entry["distortion_params"], dtype=np.float64)
    except (TypeError, ValueError):
        coefficients = np.empty(0)
    if coefficients.shape != (6,) or not np.all(np.isfinite(coefficients)):
        raise SkedUserError(f"{where}: 'distortion_params' must be 6 finite numbers [k1, k2, k3, k4, p1, p2], "
                         f"got {entry['distortion_params']!r}.")
    return coefficients


def _view_from_json(entry: dict, folder: Path, index: int, camera_model: str = "OPENCV") -> SketchView:
    where = f"{folder / SKETCHES_JSON} views[{index}]"
    if not isinstance(entry, dict):
        raise SkedUserError(f"{where}: each view must be a JSON object.")
    if "mask_path" not in entry:
        raise SkedUserError(f"{where}: missing field 'mask_path'.")
    if "transform_matrix" not in entry:
        raise SkedUserError(f"{where}: missing field 'transform_matrix'.")
    width, height = (_number(entry, key, where, positive=True) for key in ("w", "h"))
    if width != int(width) or height != int(height):
        raise SkedUserError(f"{where}: 'w' and 'h' must be whole pixel counts.")
    try:
        matrix = np.asarray(entry["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise SkedUserError(f"{where}: 'transform_matrix' must be a 4x4 array of numbers.") from None
    mask_path = folder / entry["mask_path"]
    fl_x, fl_y = (_number(entry, key, where, positive=True) for key in ("fl_x", "fl_y"))
    cx, cy = (_number(entry, key, where) for key in ("cx", "cy"))
    coefficients = _distortion(entry, str(entry.get("camera_model", camera_model)), where)
    mask = read_mask(mask_path, int(width), int(height))
    if coefficients.any():
        mask = undistort_mask(mask, fl_x, fl_y, cx, cy, coefficients)
        if not mask.any():
            raise SkedUserError(
                f"{mask_path}: the mask is empty once the lens distortion of {where} is removed (it lies where the "
                "undistorted camera does not see). Check the distortion fields k1 ... p2 / 'distortion_params'."
            )
    return SketchView(
        mask=mask,
        camera_to_world=check_camera_to_world(matrix, f"{where} 'transform_matrix'"),
        fl_x=fl_x, fl_y=fl_y, cx=cx, cy=cy,
        name=str(mask_path),
    )


def load_sketch_set(folder: Path) -> SketchSet:
    """Load a sketch set folder; every problem names the file and field to fix."""
    folder = Path(folder)
    json_path = folder / SKETCHES_JSON
    if not json_path.is_file():
        raise SkedFileNotFoundError(f"{json_path}: no sketch set here (expected {SKETCHES_JSON} and PNG masks).")
    try:
        meta = json.loads(json_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SkedUserError(f"{json_path}: not valid JSON ({error}).") from error
    if not isinstance(meta, dict):
        raise SkedUserError(f"{json_path}: expected a JSON object with 'views'.")
    frame = meta.get("frame", "data")
    if frame not in FRAMES:
        raise SkedUserError(f"{json_path}: unknown 'frame' {frame!r}; use 'data' (the base's transforms.json) or 'model'.")
    entries = meta.get("views")
    if not isinstance(entries, list):
        raise SkedUserError(f"{json_path}: missing the list 'views'.")
    if len(entries) < 2:
        raise SkedUserError(
            f"{json_path}: {len(entries)} view(s); SKED needs at least two sketch views from different viewpoints."
        )
    camera_model = str(meta.get("camera_model", "OPENCV"))  # a view's own 'camera_model' takes precedence
    views = [_view_from_json(entry, folder, i, camera_model) for i, entry in enumerate(entries)]
    return SketchSet(views=views, frame=frame)


def save_sketch_set(sketch_set: SketchSet, folder: Path, overwrite: bool = False) -> Path:
    """Write a sketch set folder; refuses to replace an existing one unless asked to.

    Views are pinhole cameras (lens distortion is removed at load time), so nothing is lost.
    """
    folder = Path(folder)
    # One writer (two sked-sketch saves at once would mix their masks), from the check that the set is new.
    with writing(folder, "Wait for it to finish, or save into another folder."):
        return _write_sketch_set(sketch_set, folder, overwrite)


def _write_sketch_set(sketch_set: SketchSet, folder: Path, overwrite: bool) -> Path:
    json_path = folder / SKETCHES_JSON
    if json_path.exists() and not overwrite:
        raise SkedFileExistsError(f"{json_path} already exists: choose another folder or pass overwrite=True.")
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    entries = []
    for index, view in enumerate(sketch_set.views):
        mask_name = f"masks/view_{index:02d}.png"
        if not cv2.imwrite(str(folder / mask_name), view.mask.astype(np.uint8) * 255):  # OpenCV fails silently
            raise OSError(f"{folder / mask_name}: could not write this mask; check that the folder is writable.")
        matrix = np.concatenate([view.camera_to_world, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
        entries.append(
            {
                "mask_path": mask_name,
                "transform_matrix": matrix.tolist(),
                "fl_x": float(view.fl_x),
                "fl_y": float(view.fl_y),
                "cx": float(view.cx),
                "cy": float(view.cy),
                "w": view.width,
                "h": view.height,
            }
        )
    json_path.write_text(json.dumps({"frame": sketch_set.frame, "views": entries}, indent=2))
    return json_path
