"""Drawing a sketch set over a trained base: the session behind the viewer panel and the headless path.

`SketchSession` knows nothing about the viewer: capture a camera, click the points of a
closed scribble (or upload a mask drawn elsewhere), preview, add or remove views, see the
edit box of the views so far, and save the set. Poses are kept in nerfstudio's model frame
(what the viewer shows) and saved in the base's data frame, like sets drawn on training photos.

The headless path renders canvases of the base at training cameras for any paint program
(`write_canvases`) and reads the painted canvases back (`import_canvases`). Either way the set's
coverage is reported (`sked_ns.drawing.hull_check`): whether the sketches pin the part down, or leave a
visual hull far bulkier than any sketch shows, and which view to add then.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from sked_ns.drawing.hull_check import HullCheck, check_hull
from sked_ns.errors import SkedFileExistsError, SkedFileNotFoundError, SkedUserError, reading
from sked_ns.method.edit_box import EditBox, check_sketches_meet, compute_edit_box
from sked_ns.run_lock import writing
from sked_ns.sketches.cameras import PinholeCamera, check_camera_to_world
from sked_ns.sketches.sketch_set import (
    SKETCHES_JSON,
    DataparserTransform,
    SketchSet,
    SketchView,
    fill_scribbles,
    load_sketch_set,
    mask_from_image,
    save_sketch_set,
)

CANVASES_JSON = "canvases.json"
STROKE_THRESHOLD = 0.15
MODEL_UP = np.array([0.0, 0.0, 1.0])
"""Up in nerfstudio's model frame, where sessions keep their views."""
"""A painted pixel differs from the canvas by more than this (max over channels, colours in [0, 1])."""


@dataclass
class PendingView:
    """The captured view being drawn on."""

    camera: PinholeCamera
    canvas: np.ndarray
    """(h, w, 3) float render of the base."""
    mask: np.ndarray
    points: List[Tuple[float, float]] = field(default_factory=list)
    """Clicked pixel positions of the scribble being drawn."""


def tinted(canvas: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The canvas with the masked pixels half red."""
    image = canvas.copy()
    image[mask] = 0.5 * image[mask] + 0.5 * np.array([1.0, 0.0, 0.0])
    return image


class SketchSession:
    """Sketch views being drawn over a base scene."""

    def __init__(self, render: Callable[[PinholeCamera], np.ndarray], transform: DataparserTransform,
                 scene_box: Optional[np.ndarray] = None, bounded: bool = True) -> None:
        self.render = render
        self.transform = transform
        self.scene_box, self.bounded = scene_box, bounded  # the base's (edit_box.content_bounds)
        self.views: List[SketchView] = []
        self.canvases: List[np.ndarray] = []  # the render each view was drawn on, for the viewer
        self.pending: Optional[PendingView] = None

    # ---- drawing one view -----------------------------------------------------------------
    def capture(self, camera: Optional[PinholeCamera]) -> np.ndarray:
        """Start a view at `camera` (the viewer's current one); returns the canvas."""
        if camera is None:
            raise ValueError("No viewer client is connected: open the viewer's URL in a browser, then capture.")
        canvas = np.clip(self.render(camera), 0.0, 1.0)
        self.pending = PendingView(camera=camera, canvas=canvas, mask=np.zeros(canvas.shape[:2], dtype=bool))
        return canvas

    def _require_pending(self) -> PendingView:
        if self.pending is None:
            raise ValueError("No captured view: press 'Capture view' first.")
        return self.pending

    def add_point(self, x: float, y: float) -> int:
        """A scribble point at screen position (x, y) in [0, 1] (OpenCV image axes); returns the count."""
        pending = self._require_pending()
        if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
            raise ValueError(f"Screen position ({x:.3f}, {y:.3f}) is outside the view.")
        pending.points.append((x * pending.camera.width, y * pending.camera.height))
        return len(pending.points)

    def close_scribble(self) -> None:
        """Fill the polygon of the clicked points into the view's mask (several scribbles add up)."""
        pending = self._require_pending()
        if len(pending.points) < 3:
            raise ValueError(f"A closed scribble needs at least 3 points, got {len(pending.points)}: click more.")
        polygon = np.round(np.array(pending.points) - 0.5).astype(np.int32)  # pixel j covers [j, j + 1)
        filled = np.zeros(pending.mask.shape, dtype=np.uint8)
        cv2.fillPoly(filled, [polygon], 1)
        pending.mask |= filled.astype(bool)
        pending.points = []

    def upload_mask(self, data: bytes, name: str = "upload") -> Optional[str]:
        """Use an image drawn elsewhere as the view's mask; returns a warning when it was resized."""
        pending = self._require_pending()
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if image is None:
            raise ValueError(f"{name}: not an image this tool can read; upload a PNG mask (white on black).")
        mask = mask_from_image(image)
        message = None
        height, width = pending.mask.shape
        if mask.shape != (height, width):
            if abs(mask.shape[1] / mask.shape[0] - width / height) > 0.01:
                raise ValueError(f"{name}: {mask.shape[1]}x{mask.shape[0]} has another aspect ratio than the "
                                 f"captured view ({width}x{height}); draw it on a canvas of that view.")
            message = f"{name}: resized from {mask.shape[1]}x{mask.shape[0]} to the view's {width}x{height}."
            warnings.warn(message, stacklevel=2)
            mask = cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
        pending.mask = fill_scribbles(mask)
        return message

    def clear(self) -> None:
        pending = self._require_pending()
        pending.mask[:] = False
        pending.points = []

    def preview(self) -> np.ndarray:
        """The canvas with the mask tinted red and the open scribble's points marked."""
        pending = self._require_pending()
        image = tinted(pending.canvas, pending.mask)
        for x, y in pending.points:
            cv2.circle(image, (int(x), int(y)), max(1, pending.camera.width // 100), (1.0, 0.8, 0.0), -1)
        return image

    def add_view(self) -> SketchView:
        """Keep the captured view and its mask."""
        pending = self._require_pending()
        if pending.points:
            self.close_scribble()
        if not pending.mask.any():
            raise ValueError("The mask is empty: click around the region (then 'Close scribble') or upload a mask.")
        camera = pending.camera
        view = SketchView(mask=pending.mask.copy(), camera_to_world=camera.camera_to_world, fl_x=camera.fl_x,
                          fl_y=camera.fl_y, cx=camera.cx, cy=camera.cy, name=f"view {len(self.views)}")
        self.views.append(view)
        self.canvases.append(pending.canvas)
        self.pending = None
        return view

    def view_image(self, index: int) -> np.ndarray:
        """Saved view `index`: its canvas with the mask tinted, as it looked when drawn."""
        return tinted(self.canvases[index], self.views[index].mask)

    def remove_view(self, index: int) -> None:
        if not 0 <= index < len(self.views):
            raise ValueError(f"No view {index}: there are {len(self.views)}.")
        del self.views[index]
        del self.canvases[index]

    # ---- the set --------------------------------------------------------------------------
    def edit_box(self) -> Optional[EditBox]:
        """Where the sketches meet in 3D (model frame); None with fewer than two views."""
        return compute_edit_box(self.views, self.scene_box, self.bounded) if len(self.views) >= 2 else None

    def hull_check(self) -> Optional[HullCheck]:
        """Do the views pin the part down (`sked_ns.drawing.hull_check`)? None with fewer than two views."""
        box = self.edit_box()
        # nerfstudio's model frame has +z up (its dataparsers orient the scene so, Blender's is so already).
        return check_hull(self.views, up=MODEL_UP, box=box) if box is not None else None

    def sketch_set(self) -> SketchSet:
        """The views in the base's data frame (portable across dataparser settings)."""
        views = [SketchView(mask=v.mask, camera_to_world=self.transform.invert(v.camera_to_world), fl_x=v.fl_x,
                            fl_y=v.fl_y, cx=v.cx, cy=v.cy, name=v.name) for v in self.views]
        return SketchSet(views=views, frame="data")

    def save(self, folder: Path) -> Path:
        """Write the set; never replaces an existing one."""
        folder = Path(folder)
        if (folder / SKETCHES_JSON).exists():
            raise SkedFileExistsError(f"{folder / SKETCHES_JSON} already exists: save into a new folder "
                                  "(an existing sketch set is never overwritten).")
        self.edit_box()  # sketches that do not meet in 3D are an error now, not at edit time
        return save_sketch_set(self.sketch_set(), folder)


# ---- headless: canvases for any paint program -------------------------------------------------
def write_canvases(render: Callable[[PinholeCamera], np.ndarray], cameras: Sequence[PinholeCamera],
                   transform: DataparserTransform, folder: Path, names: Optional[Sequence[str]] = None) -> Path:
    """Render `view_XX.png` canvases and `canvases.json` (their cameras, data frame) into `folder`."""
    folder = Path(folder)
    with writing(folder, "Wait for it to finish, or choose a new folder for the canvases."):  # its one writer
        return _write_canvases(render, cameras, transform, folder, names)


def check_new_canvas_folder(folder: Path, command: str = "sked-sketch canvases") -> None:
    """The canvases go into a new (or empty) folder: another set's canvases, a sketch set or the user's own files
    there would be mixed with them or overwritten (view_XX.png)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise SkedFileExistsError(f"{command}: {folder} is a file; name a new folder for the canvases.")
    held = sorted(entry.name for entry in folder.iterdir()) if folder.is_dir() else []
    if not held:
        return
    what = {CANVASES_JSON: "canvases", SKETCHES_JSON: "a sketch set"}
    kind = next((f"{what[name]} ({folder / name})" for name in (CANVASES_JSON, SKETCHES_JSON) if name in held),
                f"{len(held)} file(s) or folder(s), e.g. {held[0]}")
    raise SkedFileExistsError(f"{command}: {folder} already holds {kind}; choose a new folder for the canvases "
                              "(nothing there is overwritten).")


def _write_canvases(render, cameras, transform, folder: Path, names) -> Path:
    check_new_canvas_folder(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for index, camera in enumerate(cameras):
        image = np.clip(render(camera), 0.0, 1.0)
        path = folder / f"view_{index:02d}.png"
        cv2.imwrite(str(path), (image * 255).round().astype(np.uint8)[..., ::-1])
        pose = np.concatenate([transform.invert(camera.camera_to_world), [[0.0, 0.0, 0.0, 1.0]]])
        entries.append({"canvas": path.name, "name": names[index] if names else path.stem,
                        "transform_matrix": pose.tolist(), "fl_x": camera.fl_x, "fl_y": camera.fl_y,
                        "cx": camera.cx, "cy": camera.cy, "w": camera.width, "h": camera.height})
    (folder / CANVASES_JSON).write_text(json.dumps({"frame": "data", "views": entries}, indent=2))
    return folder / CANVASES_JSON


def painted_mask(canvas: np.ndarray, painted: np.ndarray) -> np.ndarray:
    """Strokes = pixels the painter changed; closed strokes are filled."""
    if painted.shape[:2] != canvas.shape[:2]:
        raise ValueError(f"painted image is {painted.shape[1]}x{painted.shape[0]}, the canvas "
                         f"{canvas.shape[1]}x{canvas.shape[0]}")
    difference = np.abs(painted[..., :3].astype(np.float64) - canvas[..., :3].astype(np.float64)).max(axis=-1) / 255.0
    return fill_scribbles(difference > STROKE_THRESHOLD)


def import_canvases(folder: Path, out: Path) -> Path:
    """Painted canvases -> a sketch set. Per view: `view_XX_mask.png` (white on black) or
    `view_XX_sketch.png` (the canvas with the region outlined or painted over); others are skipped."""
    folder = Path(folder)
    meta_path = folder / CANVASES_JSON
    if not meta_path.is_file():
        raise SkedFileNotFoundError(f"{meta_path}: not a canvas folder (make one with `sked-sketch canvases`).")
    with reading(str(meta_path), "Make the canvases with `sked-sketch canvases` and keep its canvases.json."):
        meta = json.loads(meta_path.read_text())
        views, skipped = read_painted_views(folder, meta["views"])
    if len(views) < 2:
        raise SkedUserError(f"{folder}: {len(views)} painted view(s) (none for {', '.join(skipped) or '-'}); save at "
                            "least two as view_XX_sketch.png (painted canvas) or view_XX_mask.png (white on black).")
    check_sketches_meet(views)  # refused now, not when an edit reads the set
    return save_sketch_set(SketchSet(views=views, frame=meta.get("frame", "data")), Path(out))


def read_painted_views(folder: Path, entries) -> Tuple[List[SketchView], List[str]]:
    """The sketch views of a canvas folder's painted canvases, and the canvases left unpainted."""
    views, skipped = [], []
    for entry in entries:
        stem = Path(entry["canvas"]).stem
        mask_path, sketch_path = folder / f"{stem}_mask.png", folder / f"{stem}_sketch.png"
        if mask_path.exists():
            image = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise SkedUserError(f"{mask_path}: cannot read this image; save it as a PNG.")
            mask = fill_scribbles(mask_from_image(image))
            source = mask_path
        elif sketch_path.exists():
            canvas = cv2.imread(str(folder / entry["canvas"]), cv2.IMREAD_COLOR)
            painted = cv2.imread(str(sketch_path), cv2.IMREAD_COLOR)
            if painted is None:
                raise SkedUserError(f"{sketch_path}: cannot read this image; save it as a PNG.")
            try:
                mask = painted_mask(canvas, painted)
            except ValueError as error:
                raise SkedUserError(f"{sketch_path}: {error}; paint on the canvas itself.") from error
            source = sketch_path
        else:
            skipped.append(stem)
            continue
        if mask.shape != (entry["h"], entry["w"]):
            raise SkedUserError(f"{source}: {mask.shape[1]}x{mask.shape[0]}, but the canvas is {entry['w']}x{entry['h']}.")
        if not mask.any():
            raise SkedUserError(f"{source}: nothing drawn (the mask is empty).")
        pose = check_camera_to_world(entry["transform_matrix"], f"{folder / CANVASES_JSON} {stem} 'transform_matrix'")
        views.append(SketchView(mask=mask, camera_to_world=pose, fl_x=entry["fl_x"], fl_y=entry["fl_y"],
                                cx=entry["cx"], cy=entry["cy"], name=str(source)))
    return views, skipped


def sketch_set_coverage(folder: Path) -> HullCheck:
    """The hull check of a saved sketch set, in its own frame (up: its model frame's +z, else the cameras' mean up)."""
    sketch_set = load_sketch_set(Path(folder))
    return check_hull(sketch_set.views, up=MODEL_UP if sketch_set.frame == "model" else None)
