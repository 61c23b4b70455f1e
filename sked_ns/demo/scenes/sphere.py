"""The embedded demo scene: an analytic object rendered on the CPU, no downloads.

A two-tone sphere ("the base") on which the demo edit puts a hat: a short cylinder on
top ("the target"). Both are signed distance functions, sphere-traced in torch, so the
demo and the tests can make a nerfstudio dataset, sketch masks and ground-truth renders
of the edit at any pose. World frame: z up, object at the origin, radius ~0.5.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch
from torch import Tensor

from sked_ns.sketches.random_views import look_at, orbit_position
from sked_ns.sketches.sketch_set import SketchSet, SketchView

SPHERE_RADIUS = 0.5
HAT_CENTRE = (0.0, 0.0, 0.62)
HAT_RADIUS, HAT_HALF_HEIGHT = 0.22, 0.14
BACKGROUND = 1.0  # white, like nerfstudio's synthetic scenes


def sphere_sdf(points: Tensor) -> Tensor:
    return points.norm(dim=-1) - SPHERE_RADIUS


def hat_sdf(points: Tensor) -> Tensor:
    """Capped cylinder standing on the sphere's top."""
    local = points - points.new_tensor(HAT_CENTRE)
    radial = local[..., :2].norm(dim=-1) - HAT_RADIUS
    axial = local[..., 2].abs() - HAT_HALF_HEIGHT
    outside = torch.stack([radial.clamp_min(0), axial.clamp_min(0)], dim=-1).norm(dim=-1)
    return outside + torch.maximum(radial, axial).clamp_max(0)


def edited_sdf(points: Tensor) -> Tensor:
    return torch.minimum(sphere_sdf(points), hat_sdf(points))


def handle_sdf(points: Tensor) -> Tensor:
    """A torus standing on the sphere's +x side, like a mug handle."""
    local = points - points.new_tensor([0.55, 0.0, 0.05])
    ring = torch.stack([torch.sqrt(local[..., 0] ** 2 + local[..., 2] ** 2) - 0.2, local[..., 1]], dim=-1)
    return ring.norm(dim=-1) - 0.06


def antenna_sdf(points: Tensor) -> Tensor:
    """A thin rod standing on top, with a ball at its tip: a small, thin edit."""
    local = points - points.new_tensor([0.0, 0.0, 0.64])
    radial = local[..., :2].norm(dim=-1) - 0.04
    axial = local[..., 2].abs() - 0.16
    rod = torch.stack([radial.clamp_min(0), axial.clamp_min(0)], dim=-1).norm(dim=-1) + torch.maximum(radial, axial).clamp_max(0)
    ball = (points - points.new_tensor([0.0, 0.0, 0.82])).norm(dim=-1) - 0.07
    return torch.minimum(rod, ball)


def albedo(points: Tensor, edit_sdf: Callable[[Tensor], Tensor] = hat_sdf) -> Tensor:
    """Blue-ish sphere with a warm stripe, red edit: easy to tell apart in renders."""
    on_edit = edit_sdf(points) < sphere_sdf(points)
    stripe = (torch.sin(points[..., 0] * 9.0) > 0.6).unsqueeze(-1)
    sphere = torch.where(stripe, points.new_tensor([0.95, 0.75, 0.25]), points.new_tensor([0.25, 0.45, 0.85]))
    return torch.where(on_edit.unsqueeze(-1), points.new_tensor([0.85, 0.15, 0.15]), sphere)


def shade(points: Tensor, sdf: Callable[[Tensor], Tensor], albedo_fn: Callable[[Tensor], Tensor]) -> Tensor:
    """Albedo under a fixed sun and sky: a function of position only, so a NeRF can match it."""
    offsets = torch.eye(3, dtype=points.dtype) * 1e-3
    normal = torch.stack([sdf(points + o) - sdf(points - o) for o in offsets], dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    sun = points.new_tensor([0.4, -0.5, 0.77])
    light = 0.35 + 0.4 * (normal * sun).sum(-1).clamp_min(0) + 0.25 * (0.5 + 0.5 * normal[..., 2])
    return (albedo_fn(points) * light[..., None]).clamp(0, 1)


def surface_colour(
    points: Tensor, sdf: Callable[[Tensor], Tensor] = edited_sdf, edit_sdf: Callable[[Tensor], Tensor] = hat_sdf
) -> Tensor:
    return shade(points, sdf, lambda p: albedo(p, edit_sdf))


def orbit_pose(azimuth_deg: float, elevation_deg: float, radius: float) -> np.ndarray:
    return look_at(orbit_position(azimuth_deg, elevation_deg, radius), np.zeros(3))


def camera_rays(camera_to_world: np.ndarray, focal: float, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Origins and unit directions (h, w, 3) of a pinhole camera's pixel centres (OpenGL: looking down -z)."""
    pose = torch.as_tensor(camera_to_world, dtype=torch.float32)
    cols, rows = torch.meshgrid(torch.arange(width) + 0.5, torch.arange(height) + 0.5, indexing="xy")
    local = torch.stack([(cols - width / 2) / focal, -(rows - height / 2) / focal, -torch.ones_like(cols)], dim=-1)
    directions = local @ pose[:, :3].T
    directions = directions / directions.norm(dim=-1, keepdim=True)
    return pose[:, 3].expand_as(directions), directions


def trace(
    sdf: Callable[[Tensor], Tensor], albedo_fn: Callable[[Tensor], Tensor], camera_to_world: np.ndarray, focal: float,
    width: int, height: int, steps: int = 96,
) -> dict[str, Tensor]:
    """Sphere-trace one view of any SDF scene: rgb (h, w, 3), hit mask (h, w) and world hit points (h, w, 3)."""
    origin, directions = camera_rays(camera_to_world, focal, width, height)
    travelled = torch.zeros(directions.shape[:-1])
    for _ in range(steps):
        distance = sdf(origin + travelled[..., None] * directions)
        travelled = travelled + distance.clamp_max(1.0)
    points = origin + travelled[..., None] * directions
    hit = sdf(points).abs() < 1e-3
    rgb = torch.where(hit[..., None], shade(points, sdf, albedo_fn), torch.full_like(points, BACKGROUND))
    return {"rgb": rgb.clamp(0, 1), "hit": hit, "points": points}


def render(
    sdf: Callable[[Tensor], Tensor], camera_to_world: np.ndarray, focal: float, width: int, height: int,
    edit_sdf: Callable[[Tensor], Tensor] = hat_sdf,
) -> dict[str, Tensor]:
    """The demo object (sphere, and `edit_sdf`'s part where `sdf` includes it) at one view."""
    return trace(sdf, lambda p: albedo(p, edit_sdf), camera_to_world, focal, width, height)


def demo_camera_poses(num_views: int, radius: float = 2.4) -> list[np.ndarray]:
    """Training views of the demo dataset: two rings around the object."""
    poses = []
    for index in range(num_views):
        elevation = 15.0 if index % 2 == 0 else 40.0
        poses.append(orbit_pose(360.0 * index / num_views, elevation, radius))
    return poses


def write_demo_dataset(folder: Path, num_views: int = 24, size: int = 96, sdf=sphere_sdf) -> Path:
    """A nerfstudio dataset (transforms.json + PNGs) of the demo object."""
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    focal = 1.2 * size
    frames = []
    for index, pose in enumerate(demo_camera_poses(num_views)):
        image = render(sdf, pose, focal, size, size)["rgb"]
        name = f"images/frame_{index:03d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor((image.numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
        frames.append({"file_path": name, "transform_matrix": np.concatenate([pose, [[0, 0, 0, 1]]]).tolist()})
    meta = {"fl_x": focal, "fl_y": focal, "cx": size / 2, "cy": size / 2, "w": size, "h": size, "frames": frames}
    path = folder / "transforms.json"
    path.write_text(json.dumps(meta, indent=2))
    return path


@dataclass(frozen=True)
class EditScene:
    """A benchmark edit of the demo sphere: what is added, and the views it is sketched from."""

    name: str
    edit_sdf: Callable[[Tensor], Tensor]
    sketch_views: Tuple[Tuple[float, float], ...]
    """(azimuth, elevation) in degrees, cameras at radius 2.4 looking at the origin."""
    description: str = ""

    def target_sdf(self, points: Tensor) -> Tensor:
        return torch.minimum(sphere_sdf(points), self.edit_sdf(points))

    def render_target(self, camera_to_world: np.ndarray, focal: float, width: int, height: int) -> dict[str, Tensor]:
        return render(self.target_sdf, camera_to_world, focal, width, height, edit_sdf=self.edit_sdf)

    def render_base(self, camera_to_world: np.ndarray, focal: float, width: int, height: int) -> dict[str, Tensor]:
        return render(sphere_sdf, camera_to_world, focal, width, height)

    def sketch_set(self, size: int = 128, views: Optional[Sequence[Tuple[float, float]]] = None) -> SketchSet:
        """Masks = the added part's silhouette from each view; poses in the dataset's data frame."""
        focal = 1.2 * size
        sketch_views = []
        for azimuth, elevation in views or self.sketch_views:
            pose = orbit_pose(azimuth, elevation, 2.4)
            hits = render(self.edit_sdf, pose, focal, size, size, edit_sdf=self.edit_sdf)["hit"].numpy()
            mask = cv2.dilate(hits.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            sketch_views.append(SketchView(mask=mask, camera_to_world=pose, fl_x=focal, fl_y=focal, cx=size / 2,
                                           cy=size / 2, name=f"{self.name}@{azimuth:g}"))
        return SketchSet(views=sketch_views, frame="data")


SCENES = {
    scene.name: scene
    for scene in (
        EditScene("hat", hat_sdf, ((20.0, 20.0), (110.0, 30.0)), "a wide cylinder on top; two views 90 deg apart"),
        EditScene("handle", handle_sdf, ((-30.0, 10.0), (20.0, 15.0), (60.0, 35.0)),
                  "a ring on the side; three views with a narrow 45 deg baseline"),
        EditScene("antenna", antenna_sdf, ((0.0, 15.0), (150.0, 40.0)), "a thin rod and ball; two views 150 deg apart"),
    )
}
"""Benchmark scenes: one base (the sphere), edits of different shapes, sizes and view baselines."""


def demo_sketch_set(size: int = 128, views=None) -> SketchSet:
    """The demo's sketches: the hat seen from two views."""
    return SCENES["hat"].sketch_set(size, views)
