"""Data frames: where a camera file's poses sit relative to the model frame.

nerfstudio-data folds a `transforms.json`'s `applied_transform` / `applied_scale` (ns-process-data writes them)
into the run's dataparser transform, which so starts from the original (COLMAP) frame, not the file's. Camera
files read by sked-eval and sketch sets declared in the data frame hold the file's poses: both go through here.
Imports no model code (the datamanager uses it while the model is set up).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from sked_ns.errors import SkedUserError
from sked_ns.sketches.sketch_set import (
    SKETCHES_JSON,
    DataparserTransform,
    SketchSet,
    check_declared_frame,
    load_sketch_set,
)

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


def model_frame_sketches(sketches: Optional[Path], metadata: Dict) -> SketchSet:
    """The sketch set in the model's frame; `metadata` is the train dataset's, as nerfstudio hands it to the model."""
    if sketches is None:
        raise SkedUserError("SKED needs a sketch set: pass --sketches <folder with sketches.json>.")
    if SKETCH_FRAME not in metadata:
        raise ValueError("A SKED model is set up by SkedPipeline with a SkedDataManager (they know the data's frame).")
    sketch_set = load_sketch_set(sketches)
    if TRAINING_CAMERAS in metadata:
        check_declared_frame(sketch_set, metadata[SKETCH_FRAME], *metadata[TRAINING_CAMERAS],
                             Path(sketches) / SKETCHES_JSON)
    return sketch_set.in_model_frame(metadata[SKETCH_FRAME])
