"""Held-out unbounded benchmark scenes: objects on a textured ground that runs to the horizon, under a sky.

Defined before any tuning of the edit and reported apart from the object scenes
(`benchmark_scenes`): a capture as users make one outdoors, with cameras among the objects that
see the horizon and the sky, so that `ns-train nerfacto` with its defaults (scene contraction,
appearance embeddings) has a far, contracted field to fill, where floaters would go.

- `lawn`: a grey stone block, a tree (trunk and canopy), a checkered ball on a grass ground plane
  (infinite, its texture fading to its mean with distance from the origin, as a mip-mapped
  texture would), a distant tower, and a sky coloured by ray direction for rays that hit nothing;
  the edit is a lamp on the block: a thin stem standing on the block's top (it touches an
  existing surface) under a yellow ball, sketched from three views.

Analytic like the object scenes (the same primitives, shading and sphere tracer), so every figure
has exact ground truth; the ground plane is intersected exactly, not sphere-traced (grazing rays
would need thousands of steps). `write_benchmark(name, folder)` writes `data/`, `target/` and
`sketches/` like `benchmark_scenes.write_benchmark`. The definitions are frozen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch
from torch import Tensor

from sked_ns.demo.scenes.objects import (
    IMAGE_SIZE,
    TRACE_STEPS,
    BenchmarkScene,
    Part,
    box,
    capsule,
    cylinder,
    solid,
    sphere,
    two_tone,
    union,
    write_scene_dataset,
)
from sked_ns.demo.scenes.sphere import camera_rays, shade
from sked_ns.sketches.random_views import look_at, orbit_position

CAMERA_RADIUS = 2.2
FOCAL = 1.1 * IMAGE_SIZE
CAPTURE_ELEVATIONS = (2.0, 10.0, 20.0)
"""Low cameras, as a person holds one among the objects: the horizon and the sky are in most photos."""
HORIZON_SKY, ZENITH_SKY = (0.86, 0.9, 0.95), (0.38, 0.56, 0.88)
LOOK_AT = (0.0, 0.0, 0.3)
"""Cameras look at the objects' middle, not the ground under them: the horizon crosses the photos' middle."""
TEXTURE_FADE = 3.0
"""Distance from the origin over which the ground's texture fades to its mean (no aliasing at the horizon)."""


def sky(directions: Tensor) -> Tensor:
    """The sky's colour for unit ray directions (..., 3): pale at the horizon, blue overhead."""
    up = directions[..., 2:3].clamp(0, 1).sqrt()
    return (1 - up) * directions.new_tensor(HORIZON_SKY) + up * directions.new_tensor(ZENITH_SKY)


def grass(points: Tensor) -> Tensor:
    """Two greens in an uneven pattern, fading with distance from the origin to their mean."""
    light, dark = points.new_tensor((0.42, 0.62, 0.25)), points.new_tensor((0.24, 0.42, 0.16))
    pattern = torch.sin(points[..., 0] * 9.0 + 2.0 * torch.sin(points[..., 1] * 4.0)) * torch.sin(points[..., 1] * 7.0)
    mix = 0.5 + 0.5 * torch.tanh(4.0 * pattern) * torch.exp(-points[..., :2].norm(dim=-1) / TEXTURE_FADE)
    return mix[..., None] * light + (1 - mix[..., None]) * dark


def ground_sdf(points: Tensor) -> Tensor:
    return points[..., 2]


def trace_unbounded(parts: Tuple[Part, ...], camera_to_world: np.ndarray, focal: float, width: int, height: int,
                    steps: int = TRACE_STEPS) -> Dict[str, Tensor]:
    """One view of objects on the ground plane z = 0 under the sky: rgb (h, w, 3), hit (h, w), points (h, w, 3).

    The objects are sphere-traced (their SDF clamps a step to 1, as `scene.trace`), the plane intersected
    exactly; the nearer wins. Rays that hit neither show the sky (their points are far along the ray).
    """
    sdf, albedo = union(parts)
    everything, everything_albedo = union(parts + (Part(ground_sdf, grass),))
    origin, directions = camera_rays(camera_to_world, focal, width, height)
    travelled = torch.zeros(directions.shape[:-1])
    for _ in range(steps):
        travelled = travelled + sdf(origin + travelled[..., None] * directions).clamp_max(1.0)
    on_object = sdf(origin + travelled[..., None] * directions).abs() < 1e-3
    down = directions[..., 2] < -1e-6
    plane = torch.where(down, -origin[..., 2] / directions[..., 2].clamp_max(-1e-6), torch.full_like(travelled, math.inf))
    depth = torch.where(on_object, torch.minimum(travelled, plane), plane)
    hit = on_object | down
    depth = torch.where(hit, depth, torch.full_like(depth, 1e4))
    points = origin + depth[..., None] * directions
    rgb = torch.where(hit[..., None], shade(points, everything, everything_albedo), sky(directions))
    return {"rgb": rgb.clamp(0, 1), "hit": hit, "points": points}


STONE = two_tone(lambda p: torch.sin(p[..., 2] * 31.0 + 3.0 * torch.sin(p[..., 0] * 11.0)), (0.66, 0.64, 0.6),
                 (0.5, 0.49, 0.47))
BALL = two_tone(lambda p: torch.sin(p[..., 0] * 25) * torch.sin(p[..., 1] * 25) * torch.sin(p[..., 2] * 25),
                (0.85, 0.2, 0.2), (0.95, 0.93, 0.88))
BLOCK_TOP = 0.5


@dataclass(frozen=True)
class UnboundedScene(BenchmarkScene):
    """Objects on an endless ground under a sky, an added part (the edit), and the views it is sketched from
    ((azimuth, elevation) in degrees: capture_pose)."""

    def render_base(self, pose: np.ndarray, focal: float, width: int, height: int) -> Dict[str, Tensor]:
        return trace_unbounded(self.base_parts, pose, focal, width, height)

    def render_target(self, pose: np.ndarray, focal: float, width: int, height: int) -> Dict[str, Tensor]:
        return trace_unbounded(self.base_parts + self.edit_parts, pose, focal, width, height)

    def sketch_pose(self, azimuth: float, elevation: float) -> np.ndarray:
        return capture_pose(azimuth, elevation)


SCENES: Dict[str, UnboundedScene] = {
    scene.name: scene
    for scene in (
        UnboundedScene(
            "lawn",
            base_parts=(
                Part(box((0.1, 0.0, BLOCK_TOP / 2), (0.22, 0.18, BLOCK_TOP / 2)), STONE),
                Part(cylinder((-0.6, 0.45, 0.3), 0.06, 0.3), solid((0.42, 0.3, 0.18))),
                Part(sphere((-0.6, 0.45, 0.78), 0.28), solid((0.2, 0.48, 0.22))),
                Part(sphere((0.55, -0.5, 0.15), 0.15), BALL),
                Part(cylinder((-3.5, 3.0, 0.75), 0.3, 0.75), solid((0.75, 0.7, 0.62))),
            ),
            edit_parts=(
                Part(capsule((0.1, 0.0, BLOCK_TOP), (0.1, 0.0, BLOCK_TOP + 0.22), 0.02), solid((0.15, 0.15, 0.17))),
                Part(sphere((0.1, 0.0, BLOCK_TOP + 0.3), 0.09), solid((0.95, 0.8, 0.15))),
            ),
            sketch_views=((-30.0, 10.0), (20.0, 18.0), (75.0, 12.0)),
            description="a lamp (thin stem, yellow ball) on a stone block on a lawn to the horizon, three views over 105 deg",
        ),
    )
}


def capture_pose(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """3x4 camera-to-world at CAMERA_RADIUS from LOOK_AT, seen at `elevation_deg` above it."""
    centre = np.asarray(LOOK_AT)
    return look_at(centre + orbit_position(azimuth_deg, elevation_deg, CAMERA_RADIUS), centre)


# ---- datasets --------------------------------------------------------------------------------
def capture_poses(count: int = 48) -> List[np.ndarray]:
    """A hand-held-like capture among the objects: three low rings, staggered in azimuth."""
    return [capture_pose(360.0 * index / count + 7.0 * (index % 3), CAPTURE_ELEVATIONS[index % 3])
            for index in range(count)]


def write_benchmark(name: str, folder: Path, count: int = 48, size: int = IMAGE_SIZE) -> Dict[str, Path]:
    """data/ (the base's photos), target/ (the edit's ground truth at the eval cameras) and sketches/."""
    return write_scene_dataset(SCENES[name], capture_poses(count), folder, size, sketch_size=size)
