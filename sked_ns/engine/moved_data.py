"""An edit whose data moved after it trained: rendered from its own record of its cameras, resumed at the data's new
place.

ns-render, ns-viewer and ns-export set an edit up through its datamanager, which nerfstudio's dataparsers read from the
data folder: its cameras, scene box and frame. None of them needs the photos. So an edit that trains records those in
its copy of the base (`<edit run>/base/views.pt`, beside what engine/kept_base.py keeps), and an edit loaded to
render whose data folder is gone reads them there: nothing it renders changes. Its photos are gone all the same: the
viewer draws the training cameras with a blank picture, and anything that compares with a photo (sked-eval, ns-eval)
is told where it was. A resume trains on the photos, so it is refused with the words that give the data's new place.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Dict, List, Optional, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.scene_box import SceneBox

from sked_ns.atomic import write_atomically
from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.sketches.sketch_set import DataparserTransform

VIEWS = "views.pt"
"""The record of an edit's cameras, in the folder of its copy of the base."""
CAMERA_FIELDS = ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "distortion_params", "camera_type",
                 "times")
KEPT_VIEWS = "_sked_kept_views"
"""The datamanager config's attribute (not a field: never saved) by which the pipeline hands it the record to read."""


def data_path(datamanager_config) -> Optional[Path]:
    """The data folder the datamanager reads (nerfstudio prefers the datamanager's --data to its dataparser's)."""
    data = datamanager_config.data if datamanager_config.data is not None else datamanager_config.dataparser.data
    return None if data is None or Path(data) == Path() else Path(data)


def _split_state(outputs: DataparserOutputs) -> Dict:
    cameras = outputs.cameras
    return {"cameras": {name: getattr(cameras, name) for name in CAMERA_FIELDS},
            "image_filenames": [str(name) for name in outputs.image_filenames],
            "alpha_color": outputs.alpha_color, "scene_box": outputs.scene_box.aabb,
            "dataparser_transform": outputs.dataparser_transform, "dataparser_scale": float(outputs.dataparser_scale)}


def _split_outputs(state: Dict) -> DataparserOutputs:
    return DataparserOutputs(image_filenames=[Path(name) for name in state["image_filenames"]],
                             cameras=Cameras(**state["cameras"]), alpha_color=state["alpha_color"],
                             scene_box=SceneBox(aabb=state["scene_box"]),
                             dataparser_transform=state["dataparser_transform"],
                             dataparser_scale=state["dataparser_scale"])


def keep_views(datamanager, folder: Path) -> None:
    """Record the training datamanager's cameras (both splits) and sketch frame in `folder`, once."""
    path = Path(folder) / VIEWS
    if path.exists():
        return
    frame: DataparserTransform = datamanager.data_frame_transform
    state = {"train": _split_state(datamanager.train_dataparser_outputs),
             "eval": _split_state(datamanager.eval_dataset._dataparser_outputs),
             "sketch_frame": torch.from_numpy(np.asarray(frame.transform, dtype=np.float64)),
             "sketch_scale": float(frame.scale)}
    try:
        write_atomically(path, lambda target: torch.save(state, target))
    except OSError as error:
        raise SkedUserError(f"{path}: cannot record the edit's cameras there ({error.strerror or error}); an edit "
                            "whose data later moves renders from them. Free space there.") from error


def views_for_moved_data(pipeline_config) -> Optional[Dict]:
    """For an edit loaded to render: None while its data is where it trained; where it is gone, the edit's record of
    its cameras (refused in one line for an edit that has none)."""
    data = data_path(pipeline_config.datamanager)
    if data is None or data.exists():
        return None
    kept = getattr(pipeline_config.model, "base_kept", None)
    path = Path(kept).parent / VIEWS if kept is not None else None
    if path is None or not path.is_file():
        raise SkedFileNotFoundError(
            f"{data}: this edit's data is no longer there (moved or deleted), and the edit keeps no record of its "
            "cameras to render without it (it was saved by an older sked_ns, or stopped before its first step). "
            "Put the data back there to open it.")
    from nerfstudio.utils.rich_utils import CONSOLE

    CONSOLE.print(f"{data}: the edit's data is no longer there; it opens from its own record of its cameras ({path}), "
                  "without its photos.")
    return torch.load(path, map_location="cpu", weights_only=True)


def kept_frame(views: Dict) -> DataparserTransform:
    """The data -> model frame sketches were placed in, as the edit recorded it."""
    return DataparserTransform(views["sketch_frame"].numpy(), float(views["sketch_scale"]))


@dataclass
class KeptViewsConfig(DataParserConfig):
    """A dataparser reading an edit's record of its cameras in place of its data folder (`data`: where that was)."""

    _target: Type = field(default_factory=lambda: KeptViews)
    views: Dict = field(default_factory=dict)


class KeptViews(DataParser):
    config: KeptViewsConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        return _split_outputs(self.config.views["train" if split == "train" else "eval"])


class PhotolessDataset(InputDataset):
    """A split's cameras without their photos. A photo read says where it was; with `blank_items`, the items
    nerfstudio's viewer draws on each training camera's frustum carry a blank picture of the camera's size."""

    def __init__(self, dataparser_outputs: DataparserOutputs, scale_factor: float = 1.0, data: Optional[Path] = None,
                 blank_items: bool = False):
        super().__init__(dataparser_outputs, scale_factor=scale_factor)
        self.data, self.blank_items = data, blank_items

    def get_numpy_image(self, image_idx: int):
        raise SkedFileNotFoundError(
            f"{self.image_filenames[image_idx]}: the edit's photos are no longer there (its data {self.data} moved or "
            "was deleted), and this needs them; rendering the edit does not. Put the data back there, or give its "
            "new place where the command takes one (sked-eval --data).")

    def get_data(self, image_idx: int, image_type="float32") -> Dict:
        if not self.blank_items:
            return super().get_data(image_idx, image_type)
        camera = self.cameras[image_idx]
        shape = (int(camera.height), int(camera.width), 3)
        image = torch.full(shape, 0.5) if image_type == "float32" else torch.full(shape, 128, dtype=torch.uint8)
        return {"image_idx": image_idx, "image": image}


def dataparser_words(dataparser, data: str) -> List[str]:
    """A dataparser as typed after ns-train's flags: its subcommand, `--data`, and its settings that differ from
    their defaults (typed data replace the saved dataparser whole, so those must be typed again)."""
    from sked_ns.engine.base_scene import dataparser_name

    words = [dataparser_name(dataparser), "--data", data]
    default = type(dataparser)()
    for item in fields(dataparser):
        value = getattr(dataparser, item.name)
        if not item.init or item.name.startswith("_") or item.name == "data" or value == getattr(default, item.name):
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        if all(isinstance(v, (bool, int, float, str, Path)) for v in values):
            words += [f"--{item.name.replace('_', '-')}", *map(str, values)]
    return words


def moved_data_error(run_dir: Path, data: Path, dataparser) -> SkedFileNotFoundError:
    """A resumed edit's data gone from where it trained: the words that resume it at the data's new place."""
    words = shlex.join(dataparser_words(dataparser, "NEW"))
    return SkedFileNotFoundError(
        f"{run_dir}: this edit's data is no longer at {data} (moved or deleted), and a resume trains on its photos. "
        f"Add `{words}` at the end of the command, NEW being the data's new place: the edit resumes with it there.")
