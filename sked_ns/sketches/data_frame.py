"""Data frames: where a camera file's poses sit relative to the model frame.

nerfstudio-data folds a `transforms.json`'s `applied_transform` / `applied_scale` (ns-process-data writes them)
into the run's dataparser transform, which so starts from the original (COLMAP) frame, not the file's. Camera
files read by sked-eval and sketch sets declared in the data frame hold the file's poses: both go through here.
Imports no model code (the datamanager uses it while the model is set up).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from sked_ns.errors import SkedUserError, warn
from sked_ns.sketches.placement import check_camera_placement, meeting_point, view_label
from sked_ns.sketches.sketch_set import SKETCHES_JSON, DataparserTransform, SketchSet, load_sketch_set

IMPLIED_COLMAP_TRANSFORM = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]
"""What nerfstudio-data assumes as `applied_transform` for a COLMAP folder whose transforms.json has none."""


def number_field(value, where: str, key: str, positive: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SkedUserError(f"{where}: '{key}' must be a number, got {value!r}.") from None
    if not np.isfinite(number) or (positive and number <= 0):
        raise SkedUserError(f"{where}: '{key}' must be a finite{' positive' if positive else ''} number, got {value!r}.")
    return number


def matrix_field(value, where: str, key: str, rows: int) -> np.ndarray:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        matrix = np.empty(0)
    if matrix.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(matrix)):
        raise SkedUserError(f"{where}: '{key}' must be a {rows}x4 matrix of finite numbers, got {value!r}.")
    return matrix[:3]


def file_to_model(transform: DataparserTransform, meta: dict, folder: Path, applies_file_transform: bool = True
                  ) -> DataparserTransform:
    """The map from a camera file's poses to the model frame.

    `transform` (the run's dataparser_transforms.json) starts from the *original* data frame; nerfstudio-data
    files processed from COLMAP and the like hold poses already moved by their `applied_transform` and
    `applied_scale`, which nerfstudio-data folds into that transform. Undo them, as nerfstudio-data does;
    other dataparsers (`applies_file_transform=False`: instant-ngp-data, blender-data) ignore both fields.
    """
    if not applies_file_transform:
        return transform
    where = f"{folder} camera file"
    if "applied_transform" in meta:
        applied = matrix_field(meta["applied_transform"], where, "applied_transform", 3)
    elif (folder / "colmap" / "sparse" / "0").exists():
        applied = np.asarray(IMPLIED_COLMAP_TRANSFORM, dtype=np.float64)
    else:
        applied = np.eye(4)[:3]
    applied_scale = number_field(meta.get("applied_scale", 1.0), where, "applied_scale", positive=True)
    to_data = np.linalg.inv(np.concatenate([applied, [[0.0, 0.0, 0.0, 1.0]]]))
    matrix = np.concatenate([transform.transform, [[0.0, 0.0, 0.0, 1.0]]]) @ to_data
    return DataparserTransform(transform=matrix[:3], scale=transform.scale / applied_scale)


def data_frame_transform(dataparser_config, transform: DataparserTransform) -> DataparserTransform:
    """The map from a sketch set's data frame (the frame of the data's transforms.json, where users copy camera
    entries from) to the model frame. nerfstudio-data folds the file's applied_transform / applied_scale into
    the run's transform (which so starts from the original COLMAP frame): undo them; other dataparsers' run
    transform starts from the file's frame already."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    data = getattr(dataparser_config, "data", None)
    if not isinstance(dataparser_config, NerfstudioDataParserConfig) or data is None:
        return transform
    data = Path(data)
    path = data if data.suffix == ".json" else data / "transforms.json"
    if not path.is_file():
        return transform
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise SkedUserError(f"{path}: not readable as JSON ({error}).") from error
    # nerfstudio looks for COLMAP's folder under the data path itself (never under a .json file).
    return file_to_model(transform, meta, data)


SKETCH_FRAME = "sked_dataparser_transform"
"""Dataset metadata key: the data -> model frame, which the model reads to load the sketch set."""


TRAINING_CAMERAS = "sked_training_cameras"
"""Dataset metadata key: the training cameras' positions and the scene box centre (model frame), to check the
sketch set's declared frame against."""


FRAME_MISFIT = math.log(2.0)
"""Sketch cameras over 2x nearer or farther from the scene centre than the training cameras do not fit a frame..."""
FRAME_FIT = math.log(1.5)
"""...and they fit it within 1.5x: the dataparser's scale (0.43 for the demo) tells the two frames apart."""
IN_CONTENT = 10.0
"""A sketch camera this many times nearer what it sketches than the photos were taken stands in the scene's content."""


def _log_ratios(distances: np.ndarray, typical: float) -> float:
    return float(np.abs(np.log(np.maximum(distances, 1e-12) / max(typical, 1e-12))).max())


def frame_misfit(sketch_set: SketchSet, training_positions: np.ndarray, centre: np.ndarray) -> float:
    """How far the sketch cameras are from the training cameras' distance to the scene centre (model frame):
    the largest |log(ratio)| over views, 0 when every sketch camera is as far as a typical training camera."""
    typical = float(np.median(np.linalg.norm(training_positions - centre, axis=1)))
    return _log_ratios(np.array([np.linalg.norm(view.camera_to_world[:, 3] - centre) for view in sketch_set.views]),
                       typical)


def sketch_distances(sketch_set: SketchSet, training_positions: np.ndarray) -> tuple[np.ndarray, float]:
    """Each sketch camera's distance to where the sketches meet, and a typical training camera's (model frame)."""
    point = meeting_point(sketch_set.views)
    typical = float(np.median(np.linalg.norm(training_positions - point, axis=1)))
    return np.array([np.linalg.norm(view.camera_to_world[:, 3] - point) for view in sketch_set.views]), typical


def sketch_distance_misfit(sketch_set: SketchSet, training_positions: np.ndarray) -> float:
    """How far the sketch cameras stand from where their sketches meet, against the training cameras' distance to
    that point: the largest |log(ratio)| over views. A reading that sets the cameras far nearer what they sketch
    than the photos were taken (inside the scene's content) does not fit, whatever its distance to the centre."""
    return _log_ratios(*sketch_distances(sketch_set, training_positions))


def warn_cameras_in_content(sketch_set: SketchSet, training_positions: np.ndarray, json_path: Path) -> None:
    """Warn of sketch cameras (model frame) standing IN_CONTENT nearer their sketched region than the photos."""
    distances, typical = sketch_distances(sketch_set, training_positions)
    near = [index for index, distance in enumerate(distances) if distance * IN_CONTENT < typical]
    if near:
        names = " and ".join(view_label(sketch_set.views, index) for index in near)
        many = len(near) > 1
        warn(f"{json_path}: {names}: {'the cameras stand' if many else 'the camera stands'} "
             f"{typical / distances[near].max():.0f}x or more nearer the region the sketches mark than the base's "
             f"photos were taken, as if inside the scene's content. If so, move {'them' if many else 'it'} back out "
             "to look at the region from outside (as the photos do); a close-up this near is legal, but the edit is "
             "then a speck.")


def check_declared_frame(sketch_set: SketchSet, transform: DataparserTransform, training_positions: np.ndarray,
                         centre: np.ndarray, json_path: Path) -> None:
    """Refuse a sketch set whose cameras fit the training cameras only when read in the other frame (poses
    copied from transforms.json but declared "model", or from the viewer but declared "data"): the edit box
    would be scaled and shifted by the dataparser's transform, silently. The other frame is named only where its
    cameras stand as the training cameras do both from the scene centre and from what they sketch: cameras that
    misfit for another reason (inside the scene's content) misfit in either frame, and switching would not help."""
    other = "model" if sketch_set.frame == "data" else "data"
    as_declared = sketch_set.in_model_frame(transform)
    declared = frame_misfit(as_declared, training_positions, centre)
    as_other = replace(sketch_set, frame=other).in_model_frame(transform)
    alternative = frame_misfit(as_other, training_positions, centre)
    if declared > FRAME_MISFIT and alternative < FRAME_FIT and \
            sketch_distance_misfit(as_other, training_positions) < FRAME_MISFIT:
        raise SkedUserError(
            f"{json_path}: \"frame\": \"{sketch_set.frame}\", but read so its cameras are up to "
            f"{math.exp(declared):.1f}x nearer or farther from the scene than the base's training cameras; read as "
            f"\"{other}\" they are within {math.exp(alternative):.2f}x. Set \"frame\": \"{other}\" in {json_path.name} "
            "(\"data\": poses copied from the base's transforms.json; \"model\": poses from nerfstudio's viewer).")
    warn_cameras_in_content(as_declared, training_positions, json_path)


def model_frame_sketches(sketches: Optional[Path], metadata: Dict) -> SketchSet:
    """The sketch set in the model's frame; `metadata` is the train dataset's, as nerfstudio hands it to the model."""
    if sketches is None:
        raise SkedUserError("SKED needs a sketch set: pass --sketches <folder with sketches.json>.")
    if SKETCH_FRAME not in metadata:
        raise ValueError("A SKED model is set up by SkedPipeline with a SkedDataManager (they know the data's frame).")
    sketch_set = load_sketch_set(sketches)
    json_path = Path(sketches) / SKETCHES_JSON
    # A camera inside the sketched region is so in either frame: said before the frame is second-guessed.
    check_camera_placement(sketch_set.views, str(json_path))
    if TRAINING_CAMERAS in metadata:
        check_declared_frame(sketch_set, metadata[SKETCH_FRAME], *metadata[TRAINING_CAMERAS], json_path)
    return sketch_set.in_model_frame(metadata[SKETCH_FRAME])
