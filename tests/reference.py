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


def splat_render_brute_force(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                             sh_degree=None, backgrounds=None, render_mode="RGB", near_plane=0.01,
                             far_plane=1e10, eps2d=0.3, rasterize_mode="classic", tile_size=16):
    """Gaussian splatting by brute force: every visible Gaussian at every pixel, one sort per camera.

    Projection and SH are gsplat's torch references; compositing follows gsplat's kernel
    (alpha = min(0.999, o exp(-sigma)), skipped below 1/255, stop before T <= 1e-4), and a Gaussian
    reaches a pixel only inside the 16x16 tiles its 3-sigma square touches (gsplat's tile rule,
    here tested pixel by pixel). Returns (render (C,H,W,D), alpha (C,H,W,1), means2d (C,N,2)).
    """
    import torch
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci, _spherical_harmonics

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    radii, means2d, depths, conics, compensations = _fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
        calc_compensations=rasterize_mode == "antialiased",
    )
    C = len(viewmats)
    opacities = opacities[None].expand(C, -1) if compensations is None else opacities * compensations
    if sh_degree is not None:
        centres = torch.inverse(viewmats)[:, :3, 3]
        coeffs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
        colors = torch.clamp_min(_spherical_harmonics(sh_degree, means[None] - centres[:, None], coeffs) + 0.5, 0.0)
    elif colors.dim() == 2:
        colors = colors.expand(C, -1, -1)
    if render_mode in ("D", "ED"):
        colors = depths[..., None]
    elif render_mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat([colors, depths[..., None]], dim=-1)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2).to(means.dtype) + 0.5
    pixel_tiles = (pixels - 0.5).long() // tile_size
    renders, alphas = [], []
    for cam in range(C):
        visible = torch.nonzero(radii[cam] > 0)[:, 0]
        visible = visible[torch.sort(depths[cam, visible], stable=True).indices]
        mean, conic = means2d[cam, visible], conics[cam, visible]
        radius = radii[cam, visible].to(means.dtype)[:, None]
        tile_min = torch.floor((mean - radius) / tile_size)
        tile_max = torch.ceil((mean + radius) / tile_size)
        in_tiles = ((pixel_tiles[:, None] >= tile_min[None]) & (pixel_tiles[:, None] < tile_max[None])).all(-1)
        delta = mean[None] - pixels[:, None]  # (HW, M, 2)
        sigma = 0.5 * (conic[:, 0] * delta[..., 0] ** 2 + conic[:, 2] * delta[..., 1] ** 2) + conic[:, 1] * delta[..., 0] * delta[..., 1]
        alpha = torch.clamp_max(opacities[cam, visible] * torch.exp(-sigma), 0.999)
        alpha = torch.where(in_tiles & (sigma >= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            counted = torch.cumprod(1 - alpha, dim=-1) > 1e-4
        alpha = torch.where(counted, alpha, torch.zeros_like(alpha))
        transmittance = torch.cumprod(1 - alpha, dim=-1)
        before = torch.cat([torch.ones_like(alpha[:, :1]), transmittance[:, :-1]], dim=-1)
        final = transmittance[:, -1:] if alpha.shape[1] else torch.ones_like(pixels[:, :1])
        render = (alpha * before) @ colors[cam, visible]
        if backgrounds is not None and render_mode not in ("D", "ED"):
            background = backgrounds[cam]
            if render_mode in ("RGB+D", "RGB+ED"):
                background = torch.cat([background, background.new_zeros(1)])
            render = render + final * background
        if render_mode in ("ED", "RGB+ED"):
            render = torch.cat([render[:, :-1], render[:, -1:] / (1 - final).clamp(min=1e-10)], dim=-1)
        renders.append(render.reshape(height, width, -1))
        alphas.append((1 - final).reshape(height, width, 1))
    return torch.stack(renders), torch.stack(alphas), means2d
