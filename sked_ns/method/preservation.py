"""Distance of 3D points to multi-view sketches, and the preservation weight (paper Eq. 1-4).

Per view j, d_j(p) is the Euclidean distance from the pixel p projects into to the nearest
mask pixel, in image widths (0 inside the mask). The authors take a brute-force min over
mask pixels (or a KD-tree) for every sample; we compute one exact Euclidean distance
transform per view at load time and look it up, O(1) per point on any device.

Points that project outside the image get the distance transform at the clamped pixel
plus the distance from the clamped to the true pixel (an upper bound of the true distance,
by the triangle inequality). Points behind a camera get +inf. D(p) is the mean over views
(the paper's choice: it tolerates misaligned sketches) and the weight is
w = 1 - exp(-D^2 / (2 beta^2)).
"""

from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor, nn

from sked_ns.sketches.cameras import pixel_lookup, projection_rows
from sked_ns.sketches.sketch_set import SketchView

# Points per lookup call: keeps temporaries in cache and out of the allocator's page-fault path.
_CHUNK = 1 << 16


def check_beta(beta: float) -> float:
    """beta is the falloff width of the preservation weight, in image widths."""
    if not (isinstance(beta, (int, float)) and math.isfinite(beta) and beta > 0):
        raise ValueError(f"beta must be a finite number > 0 (in image widths, default 0.025), got {beta!r}.")
    return float(beta)


def sketch_distance_transform(mask: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance, in pixels, from every pixel to the nearest mask pixel (0 inside)."""
    from scipy.ndimage import distance_transform_edt  # here, not at import: every ns-* command imports this module

    if not mask.any():
        raise ValueError("Cannot measure distances to an empty mask.")
    return distance_transform_edt(~mask).astype(np.float32)


def preservation_weight(distance: Tensor, beta: float) -> Tensor:
    """w = 1 - exp(-D^2 / (2 beta^2)) (paper Eq. 4): 0 on the sketches, 1 far away.

    Written as -expm1(-(D/beta)^2 / 2) in float32 so it stays finite and in [0, 1] for any
    beta > 0 and any D >= 0, +inf included.
    """
    ratio = distance.float() / check_beta(beta)
    return -torch.expm1(-0.5 * ratio * ratio)


def _sketch_distance(
    points: Tensor, rows: Tensor, distance_maps: Tensor, offsets: Tensor, sizes: Tensor, mean_scale: Tensor
) -> Tensor:
    """D(p) for every point: project into all views, look up, add the way back from off-image.

    rows: (3, V, 4) projection rows; distance_maps: flat, in pixels; offsets: (V, 1) starts;
    sizes: (2, V, 1) widths and heights; mean_scale: (V, 1) = 1 / (V * width).
    """
    pixel, pixel_in, index, in_front = pixel_lookup(points, rows, sizes, offsets)
    distance = distance_maps.take(index)
    off_image = pixel - pixel_in
    # sqrt of squares, not hypot: libm's hypot is scalar and slow, and |off| <= 1e7 cannot overflow.
    distance = distance + off_image.square().sum(dim=0).sqrt()
    distance = torch.where(in_front, distance * mean_scale, torch.full_like(distance, math.inf))
    return distance.sum(dim=0)


class SketchDistanceField(nn.Module):
    """Precomputed per-view distance transforms with batched projection and lookup.

    Buffers follow the module's device, so `.to("cuda")` moves the lookup to the GPU.
    `compile=True` fuses the lookup with torch.compile (benchmarks/preservation_lookup.py measures it, after a
    one-time compile); it falls back to the eager path if compilation is unavailable.
    """

    def __init__(self, views: Sequence[SketchView], compile: bool = False) -> None:
        super().__init__()
        if len(views) < 1:
            raise ValueError("SketchDistanceField needs at least one view.")
        widths = [view.width for view in views]
        heights = [view.height for view in views]
        # One flat buffer for maps of different sizes; offsets say where each view starts.
        maps = [sketch_distance_transform(view.mask).ravel() for view in views]
        offsets = np.cumsum([0] + [m.size for m in maps[:-1]])
        self.register_buffer("distance_maps", torch.from_numpy(np.concatenate(maps)), persistent=False)
        self.register_buffer("offsets", torch.as_tensor(offsets, dtype=torch.long)[:, None], persistent=False)
        self.register_buffer("sizes", torch.tensor([widths, heights], dtype=torch.float32)[..., None], persistent=False)
        camera_to_worlds = torch.tensor(np.stack([view.camera_to_world for view in views]), dtype=torch.float64)
        intrinsics = torch.tensor(np.stack([view.intrinsics for view in views]), dtype=torch.float64)
        self.register_buffer("camera_to_worlds", camera_to_worlds.float(), persistent=False)
        self.register_buffer("intrinsics", intrinsics.float(), persistent=False)
        # Built in float64, so the fused projection rounds no worse than the plain one.
        self.register_buffer("projection_rows", projection_rows(camera_to_worlds, intrinsics).float(), persistent=False)
        self._lookup = _sketch_distance
        if compile:
            try:
                self._lookup = torch.compile(_sketch_distance, dynamic=True)
            except Exception as error:  # no compiler toolchain: stay eager, just slower
                warnings.warn(f"torch.compile unavailable for the sketch lookup ({error}); using eager mode.")

    @property
    def num_views(self) -> int:
        return int(self.offsets.shape[0])

    @torch.no_grad()
    def per_view_distance(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_views num_points"]:
        """d_j(p) in image widths for every view j; +inf behind a camera (one view at a time)."""
        points = points.to(self.projection_rows)
        with torch.autocast(device_type=points.device.type, enabled=False):  # pixels need float32
            return torch.stack(
                [
                    _sketch_distance(points, self.projection_rows[:, j : j + 1], self.distance_maps,
                                     self.offsets[j : j + 1], self.sizes[:, j : j + 1], 1.0 / self.sizes[0, j : j + 1])
                    for j in range(self.num_views)
                ]
            )

    @torch.no_grad()
    def hull_distance(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, " num_points"]:
        """max_j d_j(p): 0 exactly inside the sketches' visual hull (every view's mask agrees), in image widths."""
        return self.per_view_distance(points).amax(dim=0)

    @torch.no_grad()
    def distance(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, " num_points"]:
        """D(p): the mean of the per-view distances (paper, after Eq. 1), in image widths."""
        mean_scale = 1.0 / (self.num_views * self.sizes[0])
        points = points.to(self.projection_rows)
        buffers = (self.projection_rows, self.distance_maps, self.offsets, self.sizes, mean_scale)
        try:
            # Pixel coordinates need float32: under mixed precision fp16/bf16 would move them by pixels.
            with torch.autocast(device_type=points.device.type, enabled=False):
                if points.shape[0] <= _CHUNK or points.is_cuda:
                    return self._lookup(points, *buffers)
                return torch.cat([self._lookup(chunk, *buffers) for chunk in points.split(_CHUNK)])
        except Exception as error:
            if self._lookup is _sketch_distance:
                raise
            warnings.warn(f"compiled sketch lookup failed ({error}); using eager mode.")
            self._lookup = _sketch_distance
            return self.distance(points)

    def preservation_weight(self, points: Float[Tensor, "*batch 3"], beta: float) -> Float[Tensor, "*batch"]:
        """Preservation weight of points of any batch shape."""
        flat = points.reshape(-1, 3)
        return preservation_weight(self.distance(flat), beta).reshape(points.shape[:-1])
