"""The 3D edit box: where the sketched region can be, from every view at once.

Each view's mask bounding box (all contours, not only the first as in the authors' code)
spans a frustum; the edit box is the world axis-aligned box around the intersection of
all frusta, found exactly with six linear programmes. It seeds the occupancy grid of
instant-ngp bases and aims the random training cameras.

A base holds content past its scene box when its field contracts space (nerfacto's and instant-ngp's default
scene contraction) or it has no box (splats): there the edit box is not clipped to the scene box, which a capture's
object may straddle. A bounded base (no contraction) holds nothing past it: the box is clipped, and a clip that cuts
the sketched region is warned.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Optional, Sequence

import numpy as np
import torch
from scipy.optimize import linprog
from torch import Tensor

from sked_ns.errors import SkedUserError, warn
from sked_ns.guide import guide
from sked_ns.sketches.placement import (
    check_camera_placement,
    frusta_meet,
    frustum_halfspaces,
    meeting_point,
    sketch_direction,
    view_label,
)
from sked_ns.sketches.sketch_set import SketchView

SAME_VIEW_DEG = 1.0
"""Two views whose rays to their sketches are closer than this are the same view twice."""
MIN_BASELINE_DEG = 5.0
"""Views all closer than this cannot bound the sketched region's depth: the box runs out to the scene's bounds."""
WIDE_BASELINE_DEG = 15.0
"""Views all closer than this bound the depth loosely (box depth ~ width / tan(angle)): warned."""
CLIP_SHARE = 0.05
"""A clip to the scene box that cuts more than this share of the edit box's size along an axis is warned."""


@dataclass(frozen=True)
class EditBox:
    """World-space axis-aligned box."""

    min: np.ndarray
    max: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return (self.min + self.max) / 2

    @property
    def size(self) -> np.ndarray:
        return self.max - self.min

    def contains(self, points: Tensor) -> Tensor:
        return in_box(points, torch.as_tensor(np.stack([self.min, self.max]), dtype=points.dtype, device=points.device))


def in_box(points: Tensor, bounds: Tensor) -> Tensor:
    """Whether points (..., 3) lie in the box `bounds` ([min, max], (2, 3)), faces included."""
    return ((points >= bounds[0]) & (points <= bounds[1])).all(dim=-1)


def _bounds(halfspaces: Sequence[tuple[np.ndarray, np.ndarray]], scene_box: Optional[np.ndarray]):
    a_ub = np.concatenate([a for a, _ in halfspaces])
    b_ub = np.concatenate([b for _, b in halfspaces])
    bounds = [(None, None)] * 3 if scene_box is None else list(zip(scene_box[0], scene_box[1]))
    low, high, status = np.zeros(3), np.zeros(3), []
    for axis in range(3):
        for sign, out in ((1.0, low), (-1.0, high)):
            cost = np.zeros(3)
            cost[axis] = sign
            result = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
            status.append(result.status)
            if result.status == 0:
                out[axis] = result.x[axis]
    return low, high, status


def check_view_baselines(views: Sequence[SketchView], quiet: bool = False) -> float:
    """The widest angle (degrees) between two views' lines of sight to their sketches: depth comes from it alone.

    The same view twice, or lines of sight all within MIN_BASELINE_DEG of one line (from one side or from opposite
    sides: frusta facing each other meet all along it), are refused (the edit box would run out to the scene's
    bounds); all within WIDE_BASELINE_DEG is warned (unless `quiet`: said already)."""
    directions = [sketch_direction(view) for view in views]
    name = lambda i: view_label(views, i)  # noqa: E731
    cosines = {(i, j): float(np.clip(directions[i] @ directions[j], -1.0, 1.0))
               for i, j in combinations(range(len(views)), 2)}
    same = [f"{name(i)} and {name(j)}" for (i, j), cosine in cosines.items() if np.degrees(np.arccos(cosine)) < SAME_VIEW_DEG]
    if same:
        raise SkedUserError(f"The same sketch view twice ({'; '.join(same)}: their rays to the sketch are under "
                         f"{SAME_VIEW_DEG:g} degree apart), which cannot place the edit in depth. Remove the copy and "
                         f"sketch the region from a second viewpoint at least {WIDE_BASELINE_DEG:g} degrees away.")
    widest = max(float(np.degrees(np.arccos(abs(cosine)))) for cosine in cosines.values())
    message = (f"The sketch views' lines of sight are at most {widest:.1f} degrees apart ({', '.join(map(name, range(len(views))))}): "
               "they look along nearly the same line (from one side, or across from each other), so the edit's depth is "
               "barely bounded and the edit box stretches far along that line. Sketch from viewpoints at least "
               f"{WIDE_BASELINE_DEG:g} degrees apart and as far from straight across from each other.")
    if widest < MIN_BASELINE_DEG:
        raise SkedUserError(message)
    if widest < WIDE_BASELINE_DEG and not quiet:
        warn(message)
    return widest


def refuse_apart(views: Sequence[SketchView], halfspaces, scene_box: Optional[np.ndarray]) -> None:
    """The sketches meet nowhere (inside the scene box, if given): say which views do not, and whether they meet
    outside the scene's box (poses read in the wrong frame, or a region outside the scene) or nowhere at all (the
    masks disagree: no frame mends that, as frames differ by a rotation, shift and scale)."""
    if scene_box is not None and frusta_meet(halfspaces):
        low, high = np.round(scene_box, 2).tolist()
        raise SkedUserError(
            f"The sketches meet only outside the scene's box (around {np.round(meeting_point(views), 2).tolist()}; "
            f"the box spans {low} to {high}). Check that sketches.json's \"frame\" says where its poses come from "
            "(\"data\": the base's transforms.json; \"model\": nerfstudio's viewer), and that the masks outline a "
            "region of this scene.")
    apart = [
        f"{view_label(views, i)} and {view_label(views, j)}"
        for i, j in combinations(range(len(views)), 2)
        if not frusta_meet([halfspaces[i], halfspaces[j]], scene_box)
    ]
    detail = "; ".join(apart) if apart else "no single region lies inside every view's sketch"
    raise SkedUserError(
        f"The sketches do not intersect in 3D ({detail}). Each mask must cover the same region seen "
        "from its own viewpoint: check that every mask outlines the same region."
    )


def check_sketches_meet(views: Sequence[SketchView]) -> None:
    """What compute_edit_box refuses whatever the scene's bounds: cameras inside the sketched region or facing away
    from it, views that cannot place the edit in depth, and sketches that meet nowhere (for a set saved without its
    scene)."""
    check_camera_placement(views)
    check_view_baselines(views)
    halfspaces = [frustum_halfspaces(view) for view in views]
    if not frusta_meet(halfspaces):
        refuse_apart(views, halfspaces, None)


def content_bounds(model_config, scene_box) -> tuple[np.ndarray, bool]:
    """(box, bounded): the box a base's content lies in (model frame, [min, max]) and whether it holds nothing past it,
    from nerfstudio's config fields. A field without scene contraction holds nothing past its scene box; an occupancy
    grid (instant-ngp's) samples nothing past its outermost level, the box enlarged 2^(levels-1) times about its
    centre; a contracted field without one (nerfacto), or a base with no field (splats), holds space past any box."""
    box = np.asarray(scene_box, dtype=np.float64)
    if getattr(model_config, "disable_scene_contraction", False):
        return box, True
    levels = getattr(model_config, "grid_levels", None)
    if levels is None:
        return box, False
    centre, half = box.mean(axis=0), (box[1] - box[0]) / 2 * 2 ** (int(levels) - 1)
    return np.stack([centre - half, centre + half]), True


UNBOUNDED = ("The sketch frusta meet in an unbounded region: some line of sight lies inside every sketch, as the "
             "sketches are wider than the angles between the views. Sketch from viewpoints further apart, or outline "
             "the region more tightly.")


def compute_edit_box(views: Sequence[SketchView], scene_box: Optional[np.ndarray] = None,
                     bounded: bool = True, quiet: bool = False) -> EditBox:
    """Axis-aligned box around the intersection of the views' mask-box frusta.

    `scene_box` ([[x0, y0, z0], [x1, y1, z1]]) is where the base's content lies (content_bounds). `bounded`: the base
    holds nothing past it, so it clips the result (warned where that cuts the sketched region); otherwise it bounds
    the box only where the frusta alone do not. Cameras inside the sketched region or facing away from it
    (check_camera_placement) and views that cannot bound the region's depth (the same view twice, near-parallel
    views: check_view_baselines) are an error. `quiet`: no warning (the edit's inputs were checked, and warned, before
    its model was built: engine/edit_inputs.py).
    """
    check_camera_placement(views)
    check_view_baselines(views, quiet)
    halfspaces = [frustum_halfspaces(view) for view in views]
    scene_box = None if scene_box is None else np.asarray(scene_box, dtype=np.float64)
    whole = _bounds(halfspaces, None)
    if 2 in whole[2]:
        refuse_apart(views, halfspaces, scene_box if bounded else None)
    if scene_box is None or (not bounded and all(s == 0 for s in whole[2])):
        low, high, status = whole
    else:
        low, high, status = _bounds(halfspaces, scene_box)
        if 2 in status:
            refuse_apart(views, halfspaces, scene_box)
        if not quiet and all(s == 0 for s in status):
            if any(s != 0 for s in whole[2]):
                warn(f"{UNBOUNDED[:-1]}: the edit box runs out to the scene's box.")
            else:
                warn_clipped(whole[:2], (low, high), scene_box)
    if any(s != 0 for s in status):
        raise SkedUserError(UNBOUNDED)
    return EditBox(min=low, max=high)


def warn_clipped(whole, clipped, scene_box: np.ndarray) -> None:
    """A bounded base's box cuts the sketched region (the edit box clipped by over CLIP_SHARE of its size): the far
    side of what was sketched cannot be edited. On a capture, the scene is centred off the object."""
    cut = ((whole[1] - whole[0]) - (clipped[1] - clipped[0])) / np.maximum(whole[1] - whole[0], 1e-12)
    if cut.max() <= CLIP_SHARE:
        return
    low, high = np.round(scene_box, 2).tolist()
    warn(f"The sketched region reaches past the scene's box ({low} to {high}), which this base cannot hold content "
         f"beyond: the edit box is clipped to it, {100 * cut.max():.0f}% of its size cut off along "
         f"{'xyz'[int(cut.argmax())]}. For a capture, train the base centred on the object (`nerfstudio-data "
         f"--center-method focus`, {guide('captures.md')}) and edit it with the same flag.")


def occupancy_grid_mask(
    edit_box: EditBox, roi_aabb: Sequence[float], resolution: int | Sequence[int] = 128, levels: int = 1
) -> Tensor:
    """Cells of a nerfacc `OccGridEstimator` that overlap the edit box, shaped like its `binaries`.

    Same layout as nerfacc 0.5: level l covers the roi box enlarged 2^l times about its
    centre; cell (i, j, k) spans [i, i+1)/res of that box along x (likewise y, z).
    """
    res = torch.tensor([resolution] * 3 if isinstance(resolution, int) else list(resolution), dtype=torch.float64)
    roi = torch.as_tensor(roi_aabb, dtype=torch.float64)
    centre, half = (roi[:3] + roi[3:]) / 2, (roi[3:] - roi[:3]) / 2
    low_box = torch.as_tensor(edit_box.min, dtype=torch.float64)
    high_box = torch.as_tensor(edit_box.max, dtype=torch.float64)
    masks = []
    for level in range(levels):
        low, high = centre - half * 2**level, centre + half * 2**level
        cell = (high - low) / res
        # Per axis: cells whose [start, end) interval overlaps [box min, box max].
        hits = []
        for axis in range(3):
            starts = low[axis] + cell[axis] * torch.arange(int(res[axis]), dtype=torch.float64)
            hits.append((starts <= high_box[axis]) & (starts + cell[axis] > low_box[axis]))
        masks.append(hits[0][:, None, None] & hits[1][None, :, None] & hits[2][None, None, :])
    return torch.stack(masks)
