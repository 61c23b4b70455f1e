"""A reference target any base can take: its own render with an analytic primitive set into the edit box.

For measuring an edit of a scene that has no analytic ground truth (a capture): the frozen base is rendered at
the view (colour and expected depth, through the model's `render_base`), a primitive (a cone, a ball or a box of
one colour, placed and sized inside the edit box, or the sketches' visual hull itself) is ray-cast at every pixel,
and shown only where it is nearer than the base's expected depth, so content in front of it hides it as it would
hide a real object. Not a way to edit a scene: the reference guidance pulls an edit towards it so that what the edit
keeps and what it changes can be measured without Stable Diffusion's weights. The base's own blur and floaters are
in the target as they are in its renders.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Callable, Dict, Sequence

import numpy as np
import torch
from torch import Tensor

from sked_ns.demo.scenes.capture import cone
from sked_ns.demo.scenes.objects import box, sphere
from sked_ns.demo.scenes.sphere import shade

PRIMITIVES = ("cone", "ball", "box", "hull")
OPAQUE = 0.5
"""A base pixel at least this opaque has a surface at its expected depth; a fainter one shows what lies behind."""
CAST_STEPS = 96
HULL_STEPS, HULL_BISECTIONS = 192, 10
"""SketchHull's march: samples along each ray's span of the edit box, then halvings of the step that entered it."""
HULL_CHUNK = 4096
"""Rays per march (bounds its transient memory: rays x steps points)."""


@dataclass(frozen=True)
class Primitive:
    """An analytic solid in the model frame: a cone standing along +z, a ball or an axis-aligned box."""

    kind: str
    colour: Sequence[float]
    centre: np.ndarray
    extent: np.ndarray
    """The box (3,) the primitive fills: a ball's diameter is its smallest side, a cone's base its smaller
    horizontal side."""

    @classmethod
    def in_edit_box(cls, kind: str, colour: Sequence[float], centre: Sequence[float], size: float, edit_box):
        """Centred at `centre` (fractions of the edit box along each axis), `size` times the box's extent."""
        low, high = np.asarray(edit_box.min, dtype=np.float64), np.asarray(edit_box.max, dtype=np.float64)
        return cls(kind, tuple(colour), low + np.asarray(centre, dtype=np.float64) * (high - low), size * (high - low))

    def sdf(self, points: Tensor) -> Tensor:
        centre, half = self.centre.tolist(), (self.extent / 2).tolist()
        if self.kind == "ball":
            return sphere(centre, min(half))(points)
        if self.kind == "box":
            return box(centre, half)(points)
        return cone((centre[0], centre[1], centre[2] - half[2]), (centre[0], centre[1], centre[2] + half[2]),
                    min(half[:2]))(points)

    def cast(self, origins: Tensor, directions: Tensor) -> Dict[str, Tensor]:
        """Sphere-trace unit-direction rays (..., 3): "hit", "distance" along each ray and shaded "rgb"."""
        scale = float(self.extent.max())
        travelled = torch.zeros(directions.shape[:-1], dtype=origins.dtype, device=origins.device)
        for _ in range(CAST_STEPS):
            travelled = travelled + self.sdf(origins + travelled[..., None] * directions).clamp_max(scale)
        points = origins + travelled[..., None] * directions
        hit = self.sdf(points).abs() < 1e-3 * scale
        colour = lambda p: p.new_tensor(self.colour).expand(*p.shape[:-1], 3)  # noqa: E731
        return {"hit": hit, "distance": travelled, "rgb": shade(points, self.sdf, colour)}


@dataclass(frozen=True)
class SketchHull:
    """The sketches' visual hull in the edit box as one solid of one colour, unlit (it has no smooth surface to light):
    the largest solid every sketch agrees on, so it fills each sketch as far as the other views let anything fill it.
    `inside`: the model's hull test on points (N, 3)."""

    colour: Sequence[float]
    low: np.ndarray
    high: np.ndarray
    inside: Callable[[Tensor], Tensor]

    def cast(self, origins: Tensor, directions: Tensor) -> Dict[str, Tensor]:
        """March rays (..., 3) through the edit box: "hit", "distance" to the hull's first point and "rgb"."""
        flat_o, flat_d = origins.reshape(-1, 3), directions.reshape(-1, 3)
        parts = [self._march(o, d) for o, d in zip(flat_o.split(HULL_CHUNK), flat_d.split(HULL_CHUNK))]
        hit, distance = (torch.cat([part[i] for part in parts]).reshape(origins.shape[:-1]) for i in range(2))
        rgb = origins.new_tensor(self.colour).expand(*origins.shape[:-1], 3)
        return {"hit": hit, "distance": distance, "rgb": rgb}

    def _march(self, origins: Tensor, directions: Tensor):
        low, high = origins.new_tensor(self.low), origins.new_tensor(self.high)
        away = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
        ends = torch.stack([(low - origins) / away, (high - origins) / away])
        near, far = ends.amin(dim=0).amax(dim=-1).clamp_min(0.0), ends.amax(dim=0).amin(dim=-1)
        t = near[:, None] + (far - near).clamp_min(0.0)[:, None] * torch.linspace(0, 1, HULL_STEPS).to(origins)
        inside = self._inside(origins[:, None] + t[..., None] * directions[:, None]) & (far > near)[:, None]
        hit = inside.any(dim=-1)
        first = inside.to(torch.uint8).argmax(dim=-1, keepdim=True)  # the first sample inside
        outer, inner = t.gather(-1, (first - 1).clamp_min(0))[:, 0], t.gather(-1, first)[:, 0]
        for _ in range(HULL_BISECTIONS):  # the hull's face between the last sample outside and the first inside
            middle = (outer + inner) / 2
            entered = self._inside(origins + middle[:, None] * directions)
            outer, inner = torch.where(entered, outer, middle), torch.where(entered, middle, inner)
        return hit, torch.where(hit, inner, torch.full_like(inner, torch.inf))

    def _inside(self, points: Tensor) -> Tensor:
        return self.inside(points.reshape(-1, 3)).reshape(points.shape[:-1]).to(points.device)


def target_primitive(model, kind: str, colour: Sequence[float], centre: Sequence[float], size: float):
    """The reference guidance's primitive in `model`'s edit box: an analytic one, or the sketches' hull."""
    if kind == "hull":
        def inside(points: Tensor) -> Tensor:
            return model.in_sketch_hull(points.to(model.device, torch.float32)).cpu()

        return SketchHull(tuple(colour), np.asarray(model.edit_box.min), np.asarray(model.edit_box.max), inside)
    return Primitive.in_edit_box(kind, colour, centre, size, model.edit_box)


def composite(base: Dict[str, Tensor], primitive: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The primitive over the base where it is nearer than the base's surface: "rgb" (..., 3) and "changed" (...).

    `base`: "rgb", "depth" (expected, along the same rays as the primitive's distance) and "accumulation"."""
    surface = torch.where(base["accumulation"] >= OPAQUE, base["depth"], torch.full_like(base["depth"], torch.inf))
    changed = primitive["hit"] & (primitive["distance"] < surface)
    return {"rgb": torch.where(changed[..., None], primitive["rgb"].to(base["rgb"]), base["rgb"]), "changed": changed}


def pinhole(camera_to_world: np.ndarray, focal: float, width: int, height: int):
    """A nerfstudio camera (model frame) centred on its image, as the guidance's random views are."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    pose = torch.as_tensor(np.asarray(camera_to_world), dtype=torch.float32)[None]
    return Cameras(camera_to_worlds=pose, fx=float(focal), fy=float(focal), cx=width / 2, cy=height / 2, width=width,
                   height=height, camera_type=CameraType.PERSPECTIVE)


def render_base_with_depth(model, camera) -> Dict[str, Tensor]:
    """A SKED model's frozen base at one nerfstudio camera (model frame; a photo's lens included): "rgb" (h, w, 3),
    "accumulation" (h, w), "depth" (h, w: expected distance along each unit ray) and the rays' "origins" and
    "directions" (h, w, 3)."""
    from sked_ns.models.registry import renders_cameras

    camera = camera.to(model.device)
    height, width = int(camera.height.reshape(-1)[0]), int(camera.width.reshape(-1)[0])
    rays = camera.generate_rays(camera_indices=0, keep_shape=True)
    # The base as the guidance's base render sees it: with its average appearance where it has per-photo ones.
    appearance = getattr(model, "_average_appearance", nullcontext)
    with torch.no_grad(), appearance():
        if renders_cameras(model):
            outputs = model.render_base(camera)
            # The rasterizer's depth is along the camera's axis; along each ray it is that over the ray's cosine.
            forward = -camera.camera_to_worlds.reshape(-1, 3, 4)[0, :, 2]
            depth = outputs["depth"][..., 0] / (rays.directions @ forward).clamp_min(1e-6)
        else:
            flat = rays.flatten()
            chunk = model.config.eval_num_rays_per_chunk
            parts = [model.render_base(model._collide(flat[i:i + chunk])) for i in range(0, len(flat), chunk)]
            outputs = {key: torch.cat([part[key] for part in parts]).reshape(height, width, -1)
                       for key in ("rgb", "accumulation", "expected_depth", "depth") if key in parts[0]}
            depth = outputs.get("expected_depth", outputs.get("depth"))[..., 0]
    return {"rgb": outputs["rgb"], "accumulation": outputs["accumulation"][..., 0], "depth": depth,
            "origins": rays.origins, "directions": rays.directions}


def composite_target(model, primitive, camera) -> Dict[str, Tensor]:
    """The frozen base at a nerfstudio camera with `primitive` set in, depth-tested: "rgb", "changed", and the
    base's "base" (its render) and "silhouette" (where the primitive is, hidden or not)."""
    base = render_base_with_depth(model, camera)
    # Cast on the CPU in float64, as the demo's analytic scenes are; a hit is a pixel-sized question.
    cast = primitive.cast(base["origins"].cpu().double(), base["directions"].cpu().double())
    cast = {"hit": cast["hit"].to(base["depth"].device), "distance": cast["distance"].to(base["depth"]),
            "rgb": cast["rgb"].to(base["rgb"])}
    return {**composite(base, cast), "base": base["rgb"], "silhouette": cast["hit"]}
