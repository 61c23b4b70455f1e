"""Where the sketch cameras stand towards the region their sketches mark, in any frame.

Each view's mask bounding box spans a frustum; the sketched region lies inside all of them. Two readings of a
set's poses ("frame": "data" or "model") differ by one rotation, shift and scale, which keep every frustum,
their intersection and the side of a camera a point lies on: a camera inside the sketched region, or one facing
away from where the others' sketches meet, is so in either frame, and no "frame" mends it. These checks name the
camera so, before anything blames the masks or the frame.
"""

from __future__ import annotations

from itertools import combinations
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch
from scipy.optimize import linprog

from sked_ns.errors import SkedUserError, warn
from sked_ns.sketches.cameras import pixel_directions, project
from sked_ns.sketches.sketch_set import SketchView

NEAR = 1e-3
"""Frusta start this far in front of each camera (scene units)."""
PARALLEL_SIN = 1e-6
"""Lines of sight closer to parallel than this meet nowhere in particular (the baseline check speaks for them)."""
OPENGL_HINT = ("\"transform_matrix\" is camera-to-world with OpenGL axes (the camera looks along -z): a world-to-camera "
               "or OpenCV-axes pose faces the other way")


def view_label(views: Sequence[SketchView], index: int) -> str:
    return views[index].name or f"view {index}"


def frustum_halfspaces(view: SketchView) -> Tuple[np.ndarray, np.ndarray]:
    """Half-spaces A p <= b whose intersection is the frustum of the view's mask bounding box."""
    u0, v0, u1, v1 = view.bounding_box()
    pose = torch.as_tensor(view.camera_to_world, dtype=torch.float64)
    corners = torch.tensor([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=torch.float64)
    rays = pixel_directions(corners, pose, torch.as_tensor(view.intrinsics)).numpy()
    centre_ray = rays.mean(axis=0)
    origin = view.camera_to_world[:, 3]
    normals = []
    for a, b in zip(rays, np.roll(rays, -1, axis=0)):
        normal = np.cross(a, b)
        normals.append(normal if normal @ centre_ray < 0 else -normal)  # outward
    forward = -view.camera_to_world[:, 2]
    normals.append(-forward)  # in front of the near plane
    normals = np.stack(normals)
    offsets = normals @ origin
    offsets[-1] -= NEAR
    return normals, offsets


def frusta_meet(halfspaces: Sequence[Tuple[np.ndarray, np.ndarray]], scene_box: Optional[np.ndarray] = None) -> bool:
    """Whether some point lies in every frustum (and in `scene_box`, [min, max], if given)."""
    a_ub = np.concatenate([a for a, _ in halfspaces])
    b_ub = np.concatenate([b for _, b in halfspaces])
    bounds = [(None, None)] * 3 if scene_box is None else list(zip(scene_box[0], scene_box[1]))
    return linprog(np.zeros(3), A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs").status != 2


def sketch_direction(view: SketchView) -> np.ndarray:
    """Unit direction from the camera to the centre of its sketch's bounding box."""
    u0, v0, u1, v1 = view.bounding_box()
    centre = torch.tensor([[(u0 + u1) / 2, (v0 + v1) / 2]], dtype=torch.float64)
    ray = pixel_directions(centre, torch.as_tensor(view.camera_to_world, dtype=torch.float64),
                           torch.as_tensor(view.intrinsics)).numpy()[0]
    return ray / np.linalg.norm(ray)


def sketch_half_angle(view: SketchView) -> float:
    """Angle (radians) from the line of sight to the sketch to its bounding box's farthest corner."""
    u0, v0, u1, v1 = view.bounding_box()
    corners = torch.tensor([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=torch.float64)
    rays = pixel_directions(corners, torch.as_tensor(view.camera_to_world, dtype=torch.float64),
                            torch.as_tensor(view.intrinsics)).numpy()
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return float(np.arccos(np.clip(rays @ sketch_direction(view), -1.0, 1.0)).max())


def meeting_point(views: Sequence[SketchView]) -> np.ndarray:
    """The point nearest every view's line of sight to its sketch (least squares): where the sketches meet."""
    system, target = np.zeros((3, 3)), np.zeros(3)
    for view in views:
        direction = sketch_direction(view)
        across = np.eye(3) - np.outer(direction, direction)
        system += across
        target += across @ view.camera_to_world[:, 3]
    return np.linalg.lstsq(system, target, rcond=None)[0]


def cameras_inside(views: Sequence[SketchView]) -> List[int]:
    """Views whose camera lies inside every other view's sketch (in front of it): the region the sketches allow
    then reaches that camera's lens, whether it stands inside the sketched part or on another view's line of sight."""
    positions = torch.tensor(np.stack([view.camera_to_world[:, 3] for view in views]), dtype=torch.float64)
    seen = np.ones((len(views), len(views)), dtype=bool)  # seen[i, j]: camera i inside view j's sketch
    for j, view in enumerate(views):
        pixels, depth = project(positions, torch.as_tensor(view.camera_to_world[None], dtype=torch.float64),
                                torch.as_tensor(view.intrinsics[None]))
        u, v = np.floor(pixels[0].numpy()).astype(np.int64).T
        valid = (depth[0].numpy() > NEAR) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
        seen[valid.nonzero()[0], j] = view.mask[v[valid], u[valid]]
        seen[~valid, j] = False
        seen[j, j] = True
    return [i for i in range(len(views)) if seen[i].all()]


def lines_crossing_behind(views: Sequence[SketchView]) -> List[Tuple[int, int, float]]:
    """(i, j, depth): view i's and view j's lines of sight to their sketches cross within both sketches' width
    (extended behind the cameras too), at `depth` <= NEAR along view i's line: behind or at camera i."""
    rays = [(view.camera_to_world[:, 3], sketch_direction(view), np.tan(min(sketch_half_angle(view), 1.5)))
            for view in views]
    found = []
    for i, j in combinations(range(len(views)), 2):
        (origin_i, dir_i, spread_i), (origin_j, dir_j, spread_j) = rays[i], rays[j]
        cosine = dir_i @ dir_j
        if 1.0 - cosine**2 < PARALLEL_SIN**2:
            continue
        offset = origin_j - origin_i
        # Closest points origin_i + t_i dir_i and origin_j + t_j dir_j of the two lines.
        t_i = (offset @ dir_i - cosine * (offset @ dir_j)) / (1.0 - cosine**2)
        t_j = (cosine * (offset @ dir_i) - offset @ dir_j) / (1.0 - cosine**2)
        gap = np.linalg.norm(origin_i + t_i * dir_i - origin_j - t_j * dir_j)
        if gap > abs(t_i) * spread_i + abs(t_j) * spread_j:
            continue  # the sketches' lines pass each other: the masks disagree, the cameras may stand well
        found += [(a, b, t) for a, b, t in ((i, j, t_i), (j, i, t_j)) if t <= NEAR]
    return found


def _it(count: int) -> str:
    return "them" if count > 1 else "it"


def _the_cameras(count: int) -> str:
    return "the cameras are" if count > 1 else "the camera is"


def check_camera_placement(views: Sequence[SketchView], where: str = "") -> None:
    """Refuse a camera inside the sketched region, and (where the sketches meet nowhere) one facing away from where
    the other sketches meet; `where` (the sketch set's file) starts the message."""
    views = list(views)
    prefix = f"{where}: " if where else ""
    inside = cameras_inside(views)
    if inside:
        names = " and ".join(view_label(views, i) for i in inside)
        if len(views) > 2:
            where_seen = "every other view's sketch"
        else:
            where_seen = "the other's sketch" if len(inside) == 2 else f"{view_label(views, 1 - inside[0])}'s sketch"
        raise SkedUserError(
            f"{prefix}{names}: {_the_cameras(len(inside))} inside the sketched region (inside {where_seen}), so the "
            "region the edit fills reaches the lens. Move the camera out so it looks at the region from outside.")
    if frusta_meet([frustum_halfspaces(view) for view in views]):
        return
    behind = lines_crossing_behind(views)
    if behind:
        i, j, depth = behind[0]
        faced = [view_label(views, a) for a in sorted({a for a, _, _ in behind})]
        spot = "at the camera" if depth > -NEAR else f"{-depth:.3g} behind the camera"
        raise SkedUserError(
            f"{prefix}{' and '.join(faced)}: {_the_cameras(len(faced))} facing away from the sketched region ({view_label(views, i)}'s "
            f"line of sight to its sketch meets {view_label(views, j)}'s {spot}), so the sketches meet nowhere in front "
            f"of {_it(len(faced))}. Turn {_it(len(faced))} towards the region, or move {_it(len(faced))} out of the "
            "region to look at it from outside; "
            f"check that {OPENGL_HINT}.")


PHOTO_REACH_DEG = 60.0
"""A sketch view further than this from every photo, as seen from the sketched region, looks at a side of it no photo
saw: a base reconstructed from photos holds floaters or nothing there (a capture's photos span an arc)."""


def views_off_photos(views: Sequence[SketchView], photo_origins: np.ndarray, centre: np.ndarray,
                     limit_deg: float = PHOTO_REACH_DEG) -> List[Tuple[int, float]]:
    """(index, degrees to the nearest photo) of each view whose camera is more than `limit_deg` from every photo's
    camera, the angles taken at `centre` (the sketched region's)."""
    def unit(points: np.ndarray) -> np.ndarray:
        offsets = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(centre, dtype=np.float64)
        return offsets / np.maximum(np.linalg.norm(offsets, axis=1, keepdims=True), 1e-12)

    photos = unit(photo_origins)
    if len(photos) == 0:
        return []
    off = []
    for index, view in enumerate(views):
        nearest = float(np.degrees(np.arccos(np.clip(photos @ unit(view.camera_to_world[:, 3])[0], -1.0, 1.0)).min()))
        if nearest > limit_deg:
            off.append((index, nearest))
    return off


def warn_views_off_photos(views: Sequence[SketchView], photo_origins: np.ndarray, centre: np.ndarray,
                          where: str = "") -> None:
    """One warning naming the sketch views no photo looked from (views_off_photos)."""
    off = views_off_photos(views, photo_origins, centre)
    if off:
        named = ", ".join(f"{view_label(views, i)} ({angle:.0f} degrees)" for i, angle in off)
        warn(f"{where + ': ' if where else ''}{named}: {'this view looks' if len(off) == 1 else 'these views look'} at "
             f"the sketched region from further than {PHOTO_REACH_DEG:.0f} degrees from every photo of the base, from a "
             "side no photo saw, where the base holds floaters or nothing. Sketch from viewpoints among the photos "
             "(the viewer shows their cameras).")
