"""Import the SKED authors' sketch layout (RGBA canvases + `meta_data.pkl`).

Their layout: `sketches/canvas_XX.png` (a black blob on transparent; canvas i belongs to
pose i in sorted order) and `meta_data.pkl`, a pickled dict with `'intrinsics'`
([fx, fy, cx, cy], numpy) and `'poses'` (a torch tensor [N, 4, 4], camera-to-world,
often saved from a CUDA device).

Their camera convention, read off their published poses and their projection code
(`u = fx X / Z + cx`, `v = fy Y / Z + cy` with `[X, Y, Z] = R^T (p - t)`): OpenCV-style
axes (the camera looks along +z, y down) with a mirrored x axis (det R = -1), in a y-up
world. We turn that into a proper OpenGL camera in nerfstudio's z-up world that sees
exactly the same rays: flip x (mirror the canvas, cx -> w - cx), flip y and z, and rotate
y-up to z-up.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
import torch

from sked_ns.errors import ArgumentParser, SkedFileNotFoundError, SkedUserError, check_writable_folder
from sked_ns.method.edit_box import check_sketches_meet
from sked_ns.sketches.cameras import check_camera_to_world
from sked_ns.sketches.sketch_set import SKETCHES_JSON, SketchSet, SketchView, fill_scribbles, save_sketch_set

# y-up world (theirs) -> z-up world (nerfstudio's): (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# Allowed globals of their pickle: numpy arrays and one torch tensor, nothing executable.
_PICKLE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("collections", "OrderedDict"),
}


class _MetaDataUnpickler(pickle.Unpickler):
    """Loads their meta_data.pkl on any device, refusing anything but arrays and tensors."""

    def find_class(self, module: str, name: str):
        if (module, name) == ("torch.storage", "_load_from_bytes"):
            # Storages saved from CUDA: map them to the CPU with torch's safe loader.
            return lambda data: torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        if (module, name) not in _PICKLE_GLOBALS:
            raise pickle.UnpicklingError(f"unexpected object {module}.{name} in the sketch metadata")
        return super().find_class(module, name)


def read_authors_meta(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics [fx, fy, cx, cy] and poses [N, 4, 4] from their meta_data.pkl."""
    try:
        with open(path, "rb") as file:
            meta = _MetaDataUnpickler(file).load()
        intrinsics = np.asarray(meta["intrinsics"], dtype=np.float64).reshape(4)
        poses = meta["poses"]
        poses = poses.detach().cpu().numpy() if isinstance(poses, torch.Tensor) else np.asarray(poses)
    except (OSError, pickle.UnpicklingError, KeyError, ValueError, TypeError, EOFError) as error:
        raise SkedUserError(f"{path}: not a readable SKED meta_data.pkl with 'intrinsics' and 'poses' ({error}).") from error
    return intrinsics, poses.astype(np.float64).reshape(-1, 4, 4)


def authors_pose_to_nerfstudio(pose: np.ndarray, where: str) -> np.ndarray:
    """Their mirrored OpenCV camera in a y-up world -> an OpenGL camera in a z-up world.

    Use together with a horizontally mirrored canvas and cx -> w - cx.
    """
    rotation, origin = pose[:3, :3], pose[:3, 3]
    if not np.isclose(np.linalg.det(rotation), -1.0, atol=1e-3):
        raise SkedUserError(f"{where}: expected the authors' mirrored pose (det R = -1), got det {np.linalg.det(rotation):.3f}.")
    # Mirror x (proper rotation), then OpenCV -> OpenGL (flip y and z): R diag(-1, -1, -1).
    opengl = np.concatenate([-rotation, origin[:, None]], axis=1)
    return check_camera_to_world(Y_UP_TO_Z_UP @ opengl, where)


def import_authors_sketches(folder: Path) -> SketchSet:
    """Read the authors' layout into a model-frame sketch set in nerfstudio's conventions."""
    folder = Path(folder)
    meta_path = folder / "meta_data.pkl"
    if not meta_path.is_file():
        raise SkedFileNotFoundError(f"{meta_path}: missing; the authors' layout has meta_data.pkl beside sketches/.")
    intrinsics, poses = read_authors_meta(meta_path)
    canvases = sorted((folder / "sketches").glob("*.png"))
    if len(canvases) != len(poses):
        raise SkedUserError(f"{folder / 'sketches'}: {len(canvases)} canvases for {len(poses)} poses in {meta_path}.")
    if len(canvases) < 2:
        raise SkedUserError(f"{folder / 'sketches'}: {len(canvases)} canvas(es); a sketch set needs at least two "
                            "views from different viewpoints.")
    fx, fy, cx, cy = intrinsics
    views = []
    for canvas_path, pose in zip(canvases, poses):
        canvas = cv2.imread(str(canvas_path), cv2.IMREAD_UNCHANGED)
        if canvas is None or canvas.ndim != 3 or canvas.shape[2] != 4:
            raise SkedUserError(f"{canvas_path}: expected an RGBA canvas (a black blob on transparent).")
        # Their rule: composite over white, dark pixels are the sketch.
        alpha = canvas[..., 3:4].astype(np.float64) / 255.0
        gray = (canvas[..., :3].astype(np.float64) * alpha + 255.0 * (1.0 - alpha)).mean(axis=2)
        mask = fill_scribbles(gray < 128)
        if not mask.any():
            raise SkedUserError(f"{canvas_path}: the canvas holds no sketch.")
        width = mask.shape[1]
        views.append(
            SketchView(
                mask=mask[:, ::-1].copy(),
                camera_to_world=authors_pose_to_nerfstudio(pose, f"{meta_path} poses[{len(views)}]"),
                fl_x=float(fx),
                fl_y=float(fy),
                cx=float(width - cx),
                cy=float(cy),
                name=str(canvas_path),
            )
        )
    return SketchSet(views=views, frame="model")


def entrypoint(argv: Optional[List[str]] = None) -> None:
    """`sked-import-authors <their folder> <our folder>`."""
    parser = ArgumentParser(prog="sked-import-authors", description="Convert the SKED authors' sketch layout into a sked_ns sketch set.")
    parser.add_argument("source", type=Path, help="folder with meta_data.pkl and sketches/")
    parser.add_argument("output", type=Path, help="new sketch-set folder (sketches.json + masks/)")
    parser.add_argument("--overwrite", action="store_true", help="replace a sketch set already in OUTPUT")
    args = parser.parse_args(argv)
    if (args.output / SKETCHES_JSON).exists() and not args.overwrite:  # before reading anything
        raise SkedUserError(f"sked-import-authors: {args.output / SKETCHES_JSON} already exists. Choose another "
                            "output folder, or pass --overwrite to replace that sketch set.")
    sketch_set = import_authors_sketches(args.source)
    check_sketches_meet(sketch_set.views)  # refused now, not when an edit reads the set
    check_writable_folder(args.output, "OUTPUT")
    path = save_sketch_set(sketch_set, args.output, overwrite=args.overwrite)
    print(f"wrote {path}")
