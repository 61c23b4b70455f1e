"""Random training cameras for score distillation, aimed at the edit box (paper Sec. 3.3).

The paper says random views keep the edit region in view; the authors' code orbits the
origin instead. We orbit the edit box centre at the sketch cameras' distance, so the
edit is in every view whatever the scene. Angles and fields of view are the authors':
polar angle uniform in 0-150 deg from straight above (elevation 90 down to -60, uniform in
the angle, not over the sphere: a fifth of the views look from within 30 deg of the top,
the "overhead" ones) and field of view 40-80 deg. "Front" for directional prompts is the
first sketch view's side of the object (users sketch from where they look).

The authors edit whole objects; a part small beside the scene (a flower in a vase) spans a few
pixels of such a view (2-3 px of a 24 px render), where no guidance can shape it. So the field
of view range is narrowed, in proportion, until the edit box spans at least `edit_fill` of a view
at the range's middle (a box already that large keeps the authors' range).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

ELEVATION_RANGE_DEG = (-60.0, 90.0)
"""The authors' polar angle 0-150 deg, as elevation; sampled uniformly in the angle, as they do."""
FOV_RANGE_DEG = (40.0, 80.0)
"""The authors' field-of-view range."""


@dataclass
class RandomViewSampler:
    """Orbit cameras around `centre`; z is up (nerfstudio's model frame)."""

    centre: np.ndarray
    """World point every view looks at (the edit box centre)."""
    radius: float
    """Typical camera distance (the sketch cameras' mean distance to the centre)."""
    front_azimuth_deg: float = 0.0
    """Azimuth called 'front' in directional prompts."""
    radius_scale_range: Tuple[float, float] = (0.8, 1.2)
    elevation_range_deg: Tuple[float, float] = ELEVATION_RANGE_DEG
    azimuth_range_deg: Tuple[float, float] = (-180.0, 180.0)
    fov_range_deg: Tuple[float, float] = FOV_RANGE_DEG
    jitter: float = 0.0
    """Look-at jitter, as a fraction of the radius."""
    edit_radius: float = 0.0
    """Radius of the edit box's bounding sphere (0: the field of view is not fitted to it)."""
    edit_fill: float = 0.0
    """Least share of a view's width the edit box spans at the field of view range's middle (0: the range as given)."""

    @property
    def fov_scale(self) -> float:
        """How much the field of view range is narrowed (1: not at all) to frame the edit box."""
        if self.edit_fill <= 0 or self.edit_radius <= 0:
            return 1.0
        span = 2.0 * math.degrees(math.asin(min(self.edit_radius / self.radius, 1.0)))  # the box's angular diameter
        return min(1.0, span / (self.edit_fill * 0.5 * sum(self.fov_range_deg)))

    @classmethod
    def around_sketches(cls, centre: np.ndarray, camera_to_worlds: Sequence[np.ndarray], **kwargs) -> "RandomViewSampler":
        positions = np.stack([pose[:, 3] for pose in camera_to_worlds])
        offsets = positions - centre
        radius = float(np.linalg.norm(offsets, axis=1).mean())
        front = math.degrees(math.atan2(offsets[0, 0], -offsets[0, 1]))
        return cls(centre=np.asarray(centre, dtype=np.float64), radius=radius, front_azimuth_deg=front, **kwargs)

    def sample(self, generator: torch.Generator) -> Tuple[np.ndarray, float, str]:
        """One camera: 3x4 camera-to-world (OpenGL), horizontal field of view (deg), direction label."""
        u = torch.rand(7, generator=generator, dtype=torch.float64).numpy()
        lerp = lambda r, t: r[0] + (r[1] - r[0]) * t  # noqa: E731
        radius = self.radius * lerp(self.radius_scale_range, u[0])
        elevation = lerp(self.elevation_range_deg, u[1])
        azimuth = lerp(self.azimuth_range_deg, u[2])
        fov = lerp(self.fov_range_deg, u[3]) * self.fov_scale
        position = self.centre + orbit_position(azimuth + self.front_azimuth_deg, elevation, radius)
        target = self.centre + self.jitter * self.radius * (u[4:7] - 0.5)  # a point in a cube, not on its diagonal
        return look_at(position, target), fov, view_direction(azimuth, elevation)


def orbit_position(azimuth_deg: float, elevation_deg: float, radius: float) -> np.ndarray:
    """Point on a z-up sphere; azimuth 0 is the -y side, increasing towards +x."""
    azimuth, elevation = math.radians(azimuth_deg), math.radians(elevation_deg)
    return radius * np.array(
        [math.cos(elevation) * math.sin(azimuth), -math.cos(elevation) * math.cos(azimuth), math.sin(elevation)]
    )


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """3x4 OpenGL camera-to-world at `position` looking at `target`, z up."""
    backward = position - target
    backward = backward / np.linalg.norm(backward)
    up_hint = np.array([0.0, 0.0, 1.0]) if abs(backward[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    right = np.cross(up_hint, backward)
    right = right / np.linalg.norm(right)
    up = np.cross(backward, right)
    return np.stack([right, up, backward, position], axis=1)


def view_direction(azimuth_deg: float, elevation_deg: float, overhead_deg: float = 60.0, front_deg: float = 60.0) -> str:
    """Directional prompt suffix (DreamFusion): overhead/bottom by elevation, else by azimuth."""
    if elevation_deg > overhead_deg:
        return "overhead"
    if elevation_deg < -overhead_deg:
        return "bottom"
    azimuth = (azimuth_deg + 180.0) % 360.0 - 180.0
    if abs(azimuth) < front_deg / 2:
        return "front"
    if abs(azimuth) > 180.0 - front_deg / 2:
        return "back"
    return "side"


def focal_from_fov(fov_deg: float, width: int) -> float:
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2)


def stack_poses(poses: List[np.ndarray]) -> Tensor:
    return torch.tensor(np.stack(poses), dtype=torch.float32)
