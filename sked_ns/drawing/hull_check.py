"""Do the sketches pin the part down? The visual hull's bulk against what each sketch shows.

The region the sketches allow is their visual hull, the points inside every view's mask. L_sil fills
it before the guidance carves it, so where the hull is much bulkier than the intended part the edit
comes out bulky from other viewpoints. With two views that is common: two side views of a flat or
thin part say nothing of its outline from above, and the hull takes the largest outline they allow.

The measure. A(d) is the area of the hull's silhouette seen along direction d (orthographic, scene
units squared). Sketch j shows the part as A(d_j), d_j its line of sight to the sketch (= the mask's
area where the sketches agree). Over a fixed set of directions (the 13 of a cube's faces, edges and
corners, and every sketch's own), the hull looks largest along d*; the ratio of view j is

    A(d*) / A(d_j):  how much larger the hull looks from its most revealing side than sketch j shows it,

and the set's ratio is the smallest of these, the one against the largest sketch. Measured on true
silhouettes (two side views 90 degrees apart, 10 degrees up): a ball 1.25, a box 1.4, the demo hat 1.4,
its antenna 2.7, all below HULL_RATIO_WARN; a square plate on a table 3.3 and a stick lying diagonally
on it 5-6, above: say so and suggest the direction no sketch covers. Adding a view from above brings
both to 1.0-1.4.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch
from scipy.ndimage import binary_closing

from sked_ns.method.edit_box import EditBox, compute_edit_box
from sked_ns.method.preservation import SketchDistanceField
from sked_ns.sketches.placement import sketch_direction
from sked_ns.sketches.sketch_set import SketchView

HULL_RATIO_WARN = 3.0
"""The hull looks this many times larger from some side than the largest sketch shows: the part is underdetermined."""
GRID_SAMPLES = 48
"""Hull samples along the edit box's longest side."""
MIN_AXIS_SAMPLES = 8
"""At least this many samples along each side of the box, however thin."""
SIDE_TURNS_DEG = (0.0, 45.0, 90.0, 135.0)
"""Candidate side views: horizontal lines of sight turned this far from the first sketch's."""


@dataclass(frozen=True)
class HullCheck:
    """How much larger the sketches' visual hull looks than the sketches show it (module docstring)."""

    view_names: List[str]
    view_ratios: List[float]
    """A(d*) / A(d_j) per sketch view."""
    widest_direction: np.ndarray
    """d*: the line of sight along which the hull looks largest (unit, in the sketches' frame)."""
    suggestion: str
    """Where a further sketch would help most: 'from above' or 'from the side, turned N degrees from <view>'."""
    suggestion_direction: np.ndarray
    """Its line of sight (unit, in the sketches' frame; looking down for 'from above')."""
    threshold: float = HULL_RATIO_WARN
    empty: bool = False
    """No hull sample lies inside every mask: the sketches barely agree (the ratios are then undefined)."""

    @property
    def ratio(self) -> float:
        """The set's ratio: against the largest sketch."""
        return min(self.view_ratios)

    @property
    def underdetermined(self) -> bool:
        return not self.empty and self.ratio > self.threshold

    def message(self) -> str:
        """What a user reads: the ratios and, when the part is underdetermined, the view to add."""
        if self.empty:
            return (f"Sketch coverage: no point of the edit box lies inside all {len(self.view_names)} sketches "
                    "(at this sampling): they barely overlap in 3D. Check that every mask outlines the same region.")
        per_view = ", ".join(f"{name} {ratio:.1f}x" for name, ratio in zip(self.view_names, self.view_ratios))
        if not self.underdetermined:
            return (f"Sketch coverage: from any side the region the {len(self.view_names)} sketches allow looks at most "
                    f"{self.ratio:.1f}x larger than the largest sketch shows it (per view: {per_view}; warned above "
                    f"{self.threshold:g}x).")
        return (f"Sketch coverage: the {len(self.view_names)} sketches underdetermine the part. Seen along "
                f"{np.round(self.widest_direction, 2).tolist()}, the region they allow (their visual hull) looks "
                f"{self.ratio:.1f}x larger than the largest sketch shows it (per view: {per_view}; warned above "
                f"{self.threshold:g}x), and the edit fills that whole region before it carves it. Add a sketch "
                f"{self.suggestion} (line of sight {np.round(self.suggestion_direction, 2).tolist()}), the direction "
                "the existing views cover least.")


def _probe_directions(sketch_directions: Sequence[np.ndarray]) -> np.ndarray:
    """Lines of sight the hull is measured along: a cube's 13 symmetry axes and every sketch's own."""
    cube = [np.array(v, dtype=np.float64) for v in product((-1, 0, 1), repeat=3) if any(v)]
    cube = [v for v in cube if next(c for c in v if c) > 0]  # one of each opposite pair: silhouettes are equal
    directions = np.stack(cube + list(sketch_directions))
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def hull_samples(field: SketchDistanceField, box: EditBox, samples: int = GRID_SAMPLES):
    """Grid points of the edit box inside every sketch, and the grid's spacing per axis."""
    counts = np.maximum(MIN_AXIS_SAMPLES, np.ceil(samples * box.size / box.size.max())).astype(int)
    spacing = box.size / counts
    axes = [box.min[k] + spacing[k] * (np.arange(counts[k]) + 0.5) for k in range(3)]
    points = torch.tensor(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3), dtype=torch.float32)
    inside = torch.cat([field.hull_distance(chunk) <= 0 for chunk in points.split(1 << 18)])
    return points[inside].double().numpy(), spacing


def silhouette_area(points: np.ndarray, direction: np.ndarray, pixel: float) -> float:
    """Area of the points' silhouette along `direction`: occupied pixels of side `pixel`, one-pixel gaps closed."""
    helper = np.eye(3)[np.argmin(np.abs(direction))]
    first = np.cross(direction, helper)
    first /= np.linalg.norm(first)
    second = np.cross(direction, first)
    plane = points @ np.stack([first, second]).T
    index = np.floor((plane - plane.min(axis=0)) / pixel).astype(int) + 1
    image = np.zeros(index.max(axis=0) + 2, dtype=bool)
    image[index[:, 0], index[:, 1]] = True
    # Samples of a thin slab seen at a slant land a pixel apart: close those gaps, not the shape's outline.
    return float(binary_closing(image, structure=np.ones((3, 3), dtype=bool)).sum()) * pixel**2


def _suggestion(sketch_directions: Sequence[np.ndarray], names: Sequence[str], up: np.ndarray):
    """The candidate line of sight (from above, or a side one) farthest from every sketch's."""
    horizontal = None
    for direction, name in zip(sketch_directions, names):
        flat = direction - (direction @ up) * up
        if np.linalg.norm(flat) > 0.2:  # the first sketch not looking (nearly) straight down or up
            horizontal, reference = flat / np.linalg.norm(flat), name
            break
    candidates = [("from above", -up)]
    if horizontal is not None:
        side = np.cross(up, horizontal)
        for turn in np.radians(SIDE_TURNS_DEG):
            candidates.append((f"from the side, turned {np.degrees(turn):.0f} degrees from {reference}",
                               np.cos(turn) * horizontal + np.sin(turn) * side))

    def separation(direction):  # degrees to the nearest sketch line of sight; opposite sights see the same outline
        return min(np.degrees(np.arccos(np.clip(abs(direction @ d), 0.0, 1.0))) for d in sketch_directions)

    return max(candidates, key=lambda candidate: separation(candidate[1]))  # first (above) wins ties


def check_hull(views: Sequence[SketchView], up: Optional[np.ndarray] = None, box: Optional[EditBox] = None,
               scene_box: Optional[np.ndarray] = None, threshold: float = HULL_RATIO_WARN) -> HullCheck:
    """The hull check of a sketch set (module docstring), in the views' own frame.

    `up`: the frame's up direction (nerfstudio's model frame: +z); default the mean of the cameras' up
    vectors, as nerfstudio's 'up' orientation finds it. `box`: the views' edit box, if already computed.
    """
    views = list(views)
    box = box if box is not None else compute_edit_box(views, scene_box=scene_box)
    if up is None:
        up = np.mean([view.camera_to_world[:, 1] for view in views], axis=0)
        up = up if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    field = SketchDistanceField(views)
    points, spacing = hull_samples(field, box)
    if len(points) < 8:  # a hull thinner than the grid: sample it finer once
        points, spacing = hull_samples(field, box, 2 * GRID_SAMPLES)
    # A saved view's name is its mask's path: the file name is enough (and keeps the viewer panel narrow).
    names = [Path(view.name).name if view.name else f"view {index}" for index, view in enumerate(views)]
    sights = [sketch_direction(view) for view in views]
    directions = _probe_directions(sights)
    pixel = float(spacing.max())
    suggestion, suggestion_direction = _suggestion(sights, names, up)
    if not len(points):
        return HullCheck(names, [float("nan")] * len(views), directions[0], suggestion, suggestion_direction,
                         threshold, empty=True)
    areas = np.array([silhouette_area(points, direction, pixel) for direction in directions])
    widest = int(np.argmax(areas))
    ratios = [float(areas[widest] / area) for area in areas[-len(views):]]  # > 0: every sample shows in every view
    return HullCheck(view_names=names, view_ratios=ratios, widest_direction=directions[widest],
                     suggestion=suggestion, suggestion_direction=suggestion_direction, threshold=threshold)
