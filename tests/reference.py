"""Plain, slow reference implementations the fast paths are held against."""

from __future__ import annotations

import math

import numpy as np


def project_one(point, camera_to_world, fx, fy, cx, cy):
    """Pixel position (u, v) and depth of one point, via the inverse 4x4 pose (OpenGL axes)."""
    pose = np.eye(4)
    pose[:3] = camera_to_world
    x, y, z, _ = np.linalg.inv(pose) @ np.append(point, 1.0)
    depth = -z
    if depth <= 1e-6:
        return None, depth
    return (cx + fx * x / depth, cy - fy * y / depth), depth


def sketch_distance_one(point, view):
    """d_j(p) by brute force: min over mask pixels, clamped position plus the way to the border."""
    pixel, _ = project_one(point, view.camera_to_world, view.fl_x, view.fl_y, view.cx, view.cy)
    if pixel is None:
        return math.inf
    col, row = math.floor(pixel[0]), math.floor(pixel[1])
    col_in, row_in = min(max(col, 0), view.width - 1), min(max(row, 0), view.height - 1)
    mask_rows, mask_cols = np.nonzero(view.mask)
    nearest = np.sqrt((mask_cols - col_in) ** 2 + (mask_rows - row_in) ** 2).min()
    return (nearest + math.hypot(col - col_in, row - row_in)) / view.width


def exact_distance_one(point, view):
    """The true distance from the (unclamped) pixel to the nearest mask pixel."""
    pixel, _ = project_one(point, view.camera_to_world, view.fl_x, view.fl_y, view.cx, view.cy)
    if pixel is None:
        return math.inf
    col, row = math.floor(pixel[0]), math.floor(pixel[1])
    mask_rows, mask_cols = np.nonzero(view.mask)
    return np.sqrt((mask_cols - col) ** 2 + (mask_rows - row) ** 2).min() / view.width


def near_pixel_edge(point, view, tolerance=1e-3):
    """True where float32 and float64 projections could floor to different pixels."""
    pixel, _ = project_one(point, view.camera_to_world, view.fl_x, view.fl_y, view.cx, view.cy)
    if pixel is None:
        return False
    return any(abs(c - round(c)) < tolerance * max(1.0, abs(c)) for c in pixel)


def file_digests(folder):
    """sha256 of every file under `folder`: proves a run folder was only read."""
    import hashlib
    from pathlib import Path

    folder = Path(folder)
    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}
