"""Held-out benchmark scenes: several parts on a textured table, photographed like a small capture.

Defined before any tuning of the edit and reported apart from the demo sphere's scenes,
which the method was tuned on. Each scene is analytic (signed distance functions with albedo
textures, sphere-traced like the demo), so every figure has exact ground truth:

- `vase`: a blue vase with a white band, a checkered ball and a wood-grain table; the edit is a
  flower (green stem, red blossom) standing in the vase: it touches an existing surface.
- `crate`: an orange plank crate, a green can and a tiled table; the edit is a purple handle on
  the crate's side (a ring touching the crate), sketched from three close views.
- `marker`: a checkered book, a striped cup and a wood-grain table; the edit is a yellow marker lying
  diagonally on the book, sketched from two low views 90 degrees apart: each sketch shows
  a thin bar, and the region both allow (their visual hull) is a slab over most of the book, 8.6x the
  marker's volume and 3.4x its outline from above (`sked_ns.drawing.hull_check`).

`catalogue.write_benchmark(name, folder)` writes `data/` (a nerfstudio dataset of the base: train it with
plain `ns-train nerfacto`), `target/` (the edited scene at the dataset's evaluation cameras, with
changed-region masks, for `sked-eval --target`) and `sketches/` (the added part's silhouette
from each sketch view). The definitions are frozen: nothing here is tuned to the method.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Sequence, Tuple

import cv2
import numpy as np
import torch
from torch import Tensor

from sked_ns.demo.scenes.sphere import orbit_pose, trace
from sked_ns.sketches.sketch_set import SketchSet, SketchView, save_sketch_set

SDF = Callable[[Tensor], Tensor]
Albedo = Callable[[Tensor], Tensor]
CAMERA_RADIUS = 2.2
IMAGE_SIZE = 128
FOCAL = 1.1 * IMAGE_SIZE
TRACE_STEPS = 160  # rays grazing the table need more sphere-tracing steps than the lone demo sphere


# ---- primitives ------------------------------------------------------------------------------
def box(centre, half) -> SDF:
    def sdf(points: Tensor) -> Tensor:
        q = (points - points.new_tensor(centre)).abs() - points.new_tensor(half)
        return q.clamp_min(0).norm(dim=-1) + q.amax(dim=-1).clamp_max(0)
    return sdf


def cylinder(centre, radius: float, half_height: float) -> SDF:
    """Capped cylinder along z."""
    def sdf(points: Tensor) -> Tensor:
        local = points - points.new_tensor(centre)
        d = torch.stack([local[..., :2].norm(dim=-1) - radius, local[..., 2].abs() - half_height], dim=-1)
        return d.clamp_min(0).norm(dim=-1) + d.amax(dim=-1).clamp_max(0)
    return sdf


def sphere(centre, radius: float) -> SDF:
    return lambda points: (points - points.new_tensor(centre)).norm(dim=-1) - radius


def capsule(a, b, radius: float) -> SDF:
    def sdf(points: Tensor) -> Tensor:
        start, end = points.new_tensor(a), points.new_tensor(b)
        axis = end - start
        t = (((points - start) * axis).sum(-1) / axis.dot(axis)).clamp(0, 1)
        return (points - start - t[..., None] * axis).norm(dim=-1) - radius
    return sdf


def torus_xz(centre, ring: float, tube: float) -> SDF:
    """A ring in the x-z plane (its hole along y)."""
    def sdf(points: Tensor) -> Tensor:
        local = points - points.new_tensor(centre)
        q = torch.stack([torch.sqrt(local[..., 0] ** 2 + local[..., 2] ** 2) - ring, local[..., 1]], dim=-1)
        return q.norm(dim=-1) - tube
    return sdf


def solid(colour) -> Albedo:
    return lambda points: points.new_tensor(colour).expand(*points.shape[:-1], 3)


def two_tone(pattern: Callable[[Tensor], Tensor], first, second) -> Albedo:
    """`first` where pattern > 0, else `second`."""
    return lambda points: torch.where((pattern(points) > 0)[..., None], points.new_tensor(first), points.new_tensor(second))


@dataclass(frozen=True)
class Part:
    sdf: SDF
    albedo: Albedo


def union(parts: Sequence[Part]) -> Tuple[SDF, Albedo]:
    """One SDF of all parts; each surface point takes the albedo of the part it lies on."""
    def sdf(points: Tensor) -> Tensor:
        return torch.stack([part.sdf(points) for part in parts]).amin(dim=0)

    def albedo(points: Tensor) -> Tensor:
        nearest = torch.stack([part.sdf(points) for part in parts]).argmin(dim=0)
        colours = torch.stack([part.albedo(points) for part in parts])
        return colours.gather(0, nearest[None, ..., None].expand(1, *nearest.shape, 3))[0]

    return sdf, albedo


# ---- the scenes ------------------------------------------------------------------------------
WOOD = two_tone(lambda p: torch.sin(p[..., 0] * 23.0 + 1.5 * torch.sin(p[..., 1] * 6.0)), (0.62, 0.42, 0.25),
                (0.48, 0.3, 0.17))
TILES = two_tone(lambda p: torch.sin(p[..., 0] * 12.0) * torch.sin(p[..., 1] * 12.0), (0.85, 0.85, 0.82),
                 (0.45, 0.47, 0.5))
TABLE_TOP = 0.0
BOOK_TOP = 0.12


@dataclass(frozen=True)
class BenchmarkScene:
    """A base of several parts, an added part (the edit), and the views it is sketched from."""

    name: str
    base_parts: Tuple[Part, ...]
    edit_parts: Tuple[Part, ...]
    sketch_views: Tuple[Tuple[float, float], ...]
    """(azimuth, elevation) in degrees at CAMERA_RADIUS, looking at the origin."""
    description: str

    def edit_sdf(self, points: Tensor) -> Tensor:
        return union(self.edit_parts)[0](points)

    def render_base(self, pose: np.ndarray, focal: float, width: int, height: int) -> Dict[str, Tensor]:
        return trace(*union(self.base_parts), pose, focal, width, height, steps=TRACE_STEPS)

    def render_target(self, pose: np.ndarray, focal: float, width: int, height: int) -> Dict[str, Tensor]:
        return trace(*union(self.base_parts + self.edit_parts), pose, focal, width, height, steps=TRACE_STEPS)

    def sketch_pose(self, azimuth: float, elevation: float) -> np.ndarray:
        """A sketch view's camera-to-world (3, 4): on the capture's sphere, looking at the origin."""
        return orbit_pose(azimuth, elevation, CAMERA_RADIUS)

    def sketch_set(self, size: int = 128) -> SketchSet:
        """Masks = the added part's whole silhouette from each view (3 px dilated); data-frame poses."""
        views = []
        focal = 1.1 * size
        for azimuth, elevation in self.sketch_views:
            pose = self.sketch_pose(azimuth, elevation)
            hits = trace(*union(self.edit_parts), pose, focal, size, size, steps=TRACE_STEPS)["hit"].numpy()
            mask = cv2.dilate(hits.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            views.append(SketchView(mask=mask, camera_to_world=pose, fl_x=focal, fl_y=focal, cx=size / 2, cy=size / 2,
                                    name=f"{self.name}@{azimuth:g}"))
        return SketchSet(views=views, frame="data")


SCENES: Dict[str, BenchmarkScene] = {
    scene.name: scene
    for scene in (
        BenchmarkScene(
            "vase",
            base_parts=(
                Part(box((0.0, 0.0, TABLE_TOP - 0.05), (0.9, 0.9, 0.05)), WOOD),
                Part(cylinder((-0.15, 0.05, 0.25), 0.16, 0.25),
                     two_tone(lambda p: (p[..., 2] - 0.33).abs() - 0.04, (0.2, 0.35, 0.8), (0.92, 0.92, 0.9))),
                Part(sphere((0.38, -0.28, 0.15), 0.15),
                     two_tone(lambda p: torch.sin(p[..., 0] * 30) * torch.sin(p[..., 1] * 30) * torch.sin(p[..., 2] * 30),
                              (0.9, 0.8, 0.2), (0.25, 0.6, 0.3))),
            ),
            edit_parts=(
                Part(capsule((-0.15, 0.05, 0.45), (-0.15, 0.05, 0.7), 0.03), solid((0.2, 0.6, 0.2))),
                Part(sphere((-0.15, 0.05, 0.8), 0.11), solid((0.85, 0.12, 0.15))),
            ),
            sketch_views=((30.0, 20.0), (120.0, 35.0)),
            description="a flower standing in a vase (touches the vase), two views 90 deg apart",
        ),
        BenchmarkScene(
            "crate",
            base_parts=(
                Part(box((0.0, 0.0, TABLE_TOP - 0.05), (0.9, 0.9, 0.05)), TILES),
                Part(box((0.05, 0.0, 0.2), (0.25, 0.2, 0.2)),
                     two_tone(lambda p: torch.sin(p[..., 2] * 28.0), (0.9, 0.55, 0.2), (0.6, 0.33, 0.1))),
                Part(cylinder((-0.45, 0.35, 0.15), 0.1, 0.15), solid((0.2, 0.55, 0.35))),
            ),
            edit_parts=(Part(torus_xz((0.39, 0.0, 0.22), 0.13, 0.045), solid((0.55, 0.2, 0.7))),),
            sketch_views=((-20.0, 15.0), (30.0, 25.0), (80.0, 40.0)),
            description="a handle on the crate's side (touches the crate), three views over 100 deg",
        ),
        BenchmarkScene(
            "marker",
            base_parts=(
                Part(box((0.0, 0.0, TABLE_TOP - 0.05), (0.9, 0.9, 0.05)), WOOD),
                Part(box((-0.05, 0.0, BOOK_TOP / 2), (0.3, 0.22, BOOK_TOP / 2)),
                     two_tone(lambda p: torch.sin(p[..., 0] * 20.0) * torch.sin(p[..., 1] * 20.0), (0.15, 0.45, 0.4),
                              (0.9, 0.88, 0.8))),
                Part(cylinder((0.45, 0.4, 0.13), 0.09, 0.13),
                     two_tone(lambda p: torch.sin(p[..., 2] * 40.0), (0.8, 0.25, 0.2), (0.95, 0.95, 0.92))),
            ),
            edit_parts=(
                Part(capsule((-0.27, -0.15, BOOK_TOP + 0.045), (0.13, 0.14, BOOK_TOP + 0.045), 0.045),
                     solid((0.95, 0.78, 0.12))),
                Part(capsule((0.13, 0.14, BOOK_TOP + 0.045), (0.2, 0.19, BOOK_TOP + 0.045), 0.047), solid((0.12, 0.12, 0.14))),
            ),
            sketch_views=((-10.0, 12.0), (80.0, 12.0)),
            description="a marker lying diagonally on a book (touches it), two low views 90 deg apart: their visual "
                        "hull is a slab over most of the book, 8.6x the marker's volume",
        ),
    )
}


# ---- datasets --------------------------------------------------------------------------------
def capture_poses(count: int = 48) -> List[np.ndarray]:
    """A hand-held-like capture: three rings around the table, staggered in azimuth."""
    elevations = (15.0, 35.0, 55.0)
    return [orbit_pose(360.0 * index / count + 7.0 * (index % 3), elevations[index % 3], CAMERA_RADIUS)
            for index in range(count)]


def eval_indices(count: int, train_fraction: float = 0.9) -> List[int]:
    """The frames nerfstudio's dataparser holds out for evaluation (its fraction split)."""
    from nerfstudio.data.utils.dataparsers_utils import get_train_eval_split_fraction

    _, indices = get_train_eval_split_fraction([f"{i}" for i in range(count)], train_fraction)
    return [int(i) for i in indices]


def _write_frames(folder: Path, frames: List[dict], size: int) -> Path:
    meta = {"fl_x": FOCAL * size / IMAGE_SIZE, "fl_y": FOCAL * size / IMAGE_SIZE, "cx": size / 2, "cy": size / 2,
            "w": size, "h": size, "frames": frames}
    path = folder / "transforms.json"
    path.write_text(json.dumps(meta, indent=2))
    return path


def _png(path: Path, rgb: Tensor) -> None:
    cv2.imwrite(str(path), (rgb.numpy()[..., ::-1] * 255).round().astype(np.uint8))


def write_scene_dataset(scene, poses: List[np.ndarray], folder: Path, size: int = IMAGE_SIZE,
                        sketch_size: int = IMAGE_SIZE) -> Dict[str, Path]:
    """`scene`'s photos at `poses` (data/), its edit's ground truth at the eval cameras with changed-region masks
    (target/), and its sketches at `sketch_size` px (sketches/)."""
    folder = Path(folder)
    focal = FOCAL * size / IMAGE_SIZE
    (folder / "data" / "images").mkdir(parents=True, exist_ok=True)
    (folder / "target" / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for index, pose in enumerate(poses):
        file_path = f"images/frame_{index:03d}.png"
        _png(folder / "data" / file_path, scene.render_base(pose, focal, size, size)["rgb"])
        frames.append({"file_path": file_path, "transform_matrix": np.concatenate([pose, [[0, 0, 0, 1]]]).tolist()})
    _write_frames(folder / "data", frames, size)
    targets = []
    for index in eval_indices(len(poses)):
        base = scene.render_base(poses[index], focal, size, size)
        target = scene.render_target(poses[index], focal, size, size)
        changed = (target["rgb"] - base["rgb"]).abs().amax(dim=-1) > 1e-3
        _png(folder / "target" / f"images/frame_{index:03d}.png", target["rgb"])
        cv2.imwrite(str(folder / "target" / f"images/frame_{index:03d}_changed.png"), changed.numpy().astype(np.uint8) * 255)
        targets.append({**frames[index], "changed_mask_path": f"images/frame_{index:03d}_changed.png"})
    _write_frames(folder / "target", targets, size)
    save_sketch_set(scene.sketch_set(sketch_size), folder / "sketches", overwrite=True)
    return {"data": folder / "data", "target": folder / "target", "sketches": folder / "sketches"}


# ---- the sketch views' ground truth -----------------------------------------------------------
def visible_added_part(scene, camera_to_world: np.ndarray, focal: float, width: int, height: int) -> Dict[str, Tensor]:
    """Where the edited scene shows the added part at one camera ("visible", h x w), and its first surface hits.

    A sketch is the added part's whole silhouette, hidden parts included: where kept content lies in
    front (the crate's wall before half the handle), a correct edit shows the kept content, so that
    pixel is no fill the edit owes the sketch.
    """
    target = scene.render_target(camera_to_world, focal, width, height)
    on_added_part = scene.edit_sdf(target["points"]) < 2e-3  # the trace's hit test is |sdf| < 1e-3
    return {"visible": target["hit"] & on_added_part, "hit": target["hit"], "points": target["points"]}
