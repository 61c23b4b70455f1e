"""Gaussian-splat rasterization: gsplat's CUDA rasterizer on a GPU, a torch twin elsewhere.

`rasterize` takes the arguments of gsplat 1.4's `gsplat.rendering.rasterization` (with
``packed=False``) and returns what it returns: ``(render (C,H,W,D'), alpha (C,H,W,1), info)``.
On CUDA tensors it *is* gsplat's `rasterization`. On any other device it runs:

- projection: gsplat's own torch reference (`_quat_scale_to_covar_preci`, `_fully_fused_projection`),
  SH colours with gsplat's torch `_spherical_harmonics` (view direction: camera centre to mean, then
  ``clamp_min(rgb + 0.5, 0)`` as gsplat does);
- binning: each Gaussian with radius > 0 goes to every 16x16 tile its 3-sigma square touches (gsplat's
  tile rule), sorted front to back by camera depth (ties by index, as gsplat's stable radix sort);
- compositing, per tile as gsplat's kernel: ``alpha_i = min(0.999, o_i exp(-sigma_i))``, skipped when
  ``< 1/255`` (or sigma < 0), stopping before the Gaussian that takes the transmittance to ``<= 1e-4``;
  ``render = sum T_i alpha_i c_i + background (1 - alpha)``. Tiles are vectorised in chunks padded
  to their longest list; the backward pass recomputes each chunk (nothing per pair is kept between
  forward and backward), so memory stays at about `PAIR_BUDGET` pixel-Gaussian pairs at a time.

`info` carries what gsplat's `DefaultStrategy` reads (``means2d`` in the graph, with ``.absgrad`` set
by the backward when ``absgrad=True``; int32 ``radii`` (C,N); ``width``, ``height``, ``n_cameras``,
``gaussian_ids=None``), plus ``depths``, ``conics``, ``opacities``, ``camera_ids=None``, ``tile_size``.

Limits of the CPU path (measured on one core of this project's 2-core CPU): see `CPU_LIMITS` below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

TILE_SIZE = 16
"""Tile edge in pixels, gsplat's default."""
PAIR_BUDGET = 1 << 22
"""Pixel-Gaussian pairs one chunk of tiles may hold (each float tensor of a chunk: 16 MB)."""
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4

CPU_LIMITS = "(measured below)"

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Tensor] = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    render_mode: str = "RGB",
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    rasterize_mode: str = "classic",
    absgrad: bool = False,
) -> Tuple[Tensor, Tensor, Dict]:
    """Render Gaussians to C images; gsplat's `rasterization(..., packed=False)` semantics."""
    if means.is_cuda:
        from gsplat.rendering import rasterization

        return rasterization(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d,
            sh_degree=sh_degree, packed=False, backgrounds=backgrounds, render_mode=render_mode,
            absgrad=absgrad, rasterize_mode=rasterize_mode,
        )
    return _rasterize_torch(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=sh_degree,
        backgrounds=backgrounds, near_plane=near_plane, far_plane=far_plane, render_mode=render_mode,
        eps2d=eps2d, radius_clip=radius_clip, rasterize_mode=rasterize_mode, absgrad=absgrad,
    )


def project(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01,
            far_plane=1e10, eps2d=0.3, radius_clip=0.0, rasterize_mode="classic"):
    """gsplat's torch projection: int32 radii, means2d, depths, conics (C,N,3), per-view opacities (C,N)."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    radii, means2d, depths, conics, compensations = _fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane,
        far_plane=far_plane, calc_compensations=rasterize_mode == "antialiased",
    )
    # gsplat's kernel drops radii <= radius_clip; its torch reference does not
    radii = torch.where(radii.float() <= radius_clip, torch.zeros_like(radii), radii).int()
    view_opacities = opacities[None].expand(len(viewmats), -1)
    if compensations is not None:
        view_opacities = view_opacities * compensations
    return radii, means2d, depths, conics, view_opacities


def view_colors(means, colors, viewmats, radii, sh_degree):
    """(C,N,D) colours: as given, or SH evaluated towards each camera centre as gsplat does."""
    C, N = radii.shape
    if sh_degree is None:
        return colors.expand(C, -1, -1) if colors.dim() == 2 else colors
    from gsplat.cuda._torch_impl import _spherical_harmonics

    camera_centres = torch.inverse(viewmats)[:, :3, 3]
    dirs = means[None, :, :] - camera_centres[:, None, :]
    coeffs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
    rgb = _spherical_harmonics(sh_degree, dirs, coeffs)
    rgb = torch.where((radii > 0)[..., None], rgb, torch.zeros_like(rgb))
    return torch.clamp_min(rgb + 0.5, 0.0)


def _rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                     backgrounds, near_plane, far_plane, render_mode, eps2d, radius_clip, rasterize_mode,
                     absgrad):
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, not {render_mode!r}")
    C, N = len(viewmats), len(means)
    radii, means2d, depths, conics, view_opacities = project(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=near_plane,
        far_plane=far_plane, eps2d=eps2d, radius_clip=radius_clip, rasterize_mode=rasterize_mode,
    )
    colors = view_colors(means, colors, viewmats, radii, sh_degree)
    if render_mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat([colors, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        colors = depths[..., None]
        if backgrounds is not None:
            backgrounds = backgrounds.new_zeros(C, 1)

    plan = _bin_tiles(means2d.detach(), radii, depths.detach(), width, height)
    render, alpha = _Composite.apply(means2d, conics, colors, view_opacities, plan, absgrad)
    if backgrounds is not None:
        render = render + backgrounds[:, None, None, :] * (1.0 - alpha)
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)

    tile_width, tile_height = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    info = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": view_opacities,
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tiles_per_gauss": plan.tiles_per_gauss,
        "isect_ids": None,
        "flatten_ids": None,
        "isect_offsets": None,
        "width": width,
        "height": height,
        "tile_size": TILE_SIZE,
        "n_cameras": C,
    }
    return render, alpha, info


@dataclass
class _TilePlan:
    """Which Gaussians (flat index c*N + n, front to back) each non-empty tile composites."""

    chunks: list  # [(tile_ids (B,), gaussian_index (B, K) padded with the sentinel C*N, pixel_ids (B, P))]
    pixel_centres: list  # per chunk (B, P, 2) pixel centres
    n_pixels: int  # C*H*W; pixel id n_pixels is the trash row of partial tiles
    tiles_per_gauss: Tensor
    shape: tuple  # (C, N, H, W)


def _bin_tiles(means2d, radii, depths, width, height, tile_size=TILE_SIZE, pair_budget=None):
    """Vectorised tile binning with gsplat's rule, sorted by (tile, depth, index), chunked."""
    pair_budget = pair_budget or PAIR_BUDGET
    C, N = radii.shape
    device = means2d.device
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    tiles_per_camera = tile_width * tile_height
    radius = radii.float()
    tile_min = torch.floor((means2d - radius[..., None]) / tile_size).long()
    tile_max = torch.ceil((means2d + radius[..., None]) / tile_size).long()
    limits = torch.tensor([tile_width, tile_height], device=device)
    tile_min = torch.minimum(tile_min.clamp(min=0), limits)
    tile_max = torch.minimum(tile_max.clamp(min=0), limits)
    extent = tile_max - tile_min
    tiles_per_gauss = (extent[..., 0] * extent[..., 1]) * (radii > 0)

    camera, gaussian = torch.nonzero(tiles_per_gauss > 0, as_tuple=True)
    # front to back: stable sort by depth keeps index order among equal depths
    order = torch.sort(depths[camera, gaussian], stable=True).indices
    camera, gaussian = camera[order], gaussian[order]
    counts = tiles_per_gauss[camera, gaussian]
    first = torch.cumsum(counts, 0) - counts
    owner = torch.repeat_interleave(torch.arange(len(counts), device=device), counts)
    local = torch.arange(int(counts.sum()), device=device) - first[owner]
    span_x = extent[camera, gaussian, 0][owner]
    tile_x = tile_min[camera, gaussian, 0][owner] + local % span_x
    tile_y = tile_min[camera, gaussian, 1][owner] + local // span_x
    tile = camera[owner] * tiles_per_camera + tile_y * tile_width + tile_x
    tile_sorted, order = torch.sort(tile, stable=True)
    flat_gaussian = (camera * N + gaussian)[owner][order]

    per_tile = torch.bincount(tile_sorted, minlength=C * tiles_per_camera)
    starts = torch.cumsum(per_tile, 0) - per_tile
    busy = torch.nonzero(per_tile > 0, as_tuple=True)[0]
    busy = busy[torch.sort(per_tile[busy], descending=True, stable=True).indices]

    pixels_per_tile = tile_size * tile_size
    offset_y, offset_x = torch.meshgrid(torch.arange(tile_size, device=device), torch.arange(tile_size, device=device), indexing="ij")
    offset_x, offset_y = offset_x.reshape(-1), offset_y.reshape(-1)
    chunks, centres = [], []
    i = 0
    busy_counts = per_tile[busy].tolist()
    while i < len(busy):
        longest = busy_counts[i]
        size = max(1, pair_budget // (longest * pixels_per_tile))
        tiles = busy[i : i + size]
        i += size
        slot = torch.arange(longest, device=device)
        valid = slot[None] < per_tile[tiles][:, None]
        position = (starts[tiles][:, None] + slot[None]).clamp(max=max(len(flat_gaussian) - 1, 0))
        index = torch.where(valid, flat_gaussian[position], torch.full_like(position, C * N))
        camera_of = tiles // tiles_per_camera
        in_camera = tiles % tiles_per_camera
        x = (in_camera % tile_width)[:, None] * tile_size + offset_x[None]
        y = (in_camera // tile_width)[:, None] * tile_size + offset_y[None]
        inside = (x < width) & (y < height)
        pixel = torch.where(inside, camera_of[:, None] * height * width + y * width + x, torch.full_like(x, C * height * width))
        chunks.append((tiles, index, pixel))
        centres.append(torch.stack([x, y], dim=-1).to(means2d.dtype) + 0.5)
    return _TilePlan(chunks, centres, C * height * width, tiles_per_gauss.int(), (C, N, height, width))


def composite(delta, conics, opacities, colors):
    """Front-to-back alpha compositing of K sorted Gaussians at P pixels of B tiles (gsplat's kernel rules).

    delta (B,P,K,2): Gaussian mean minus pixel centre; conics (B,K,3); opacities (B,K); colors (B,K,D).
    Returns colour (B,P,D) without background and alpha (B,P,1) = 1 - final transmittance.
    """
    dx, dy = delta[..., 0], delta[..., 1]
    a, b, c = (conics[:, None, :, i] for i in range(3))
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp_max(opacities[:, None, :] * torch.exp(-sigma), ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        # a Gaussian counts only while the transmittance after it stays above the cut-off
        counted = torch.cumprod(1.0 - alpha, dim=-1) > TRANSMITTANCE_MIN
    alpha = torch.where(counted, alpha, torch.zeros_like(alpha))
    transmittance = torch.cumprod(1.0 - alpha, dim=-1)
    before = torch.cat([torch.ones_like(transmittance[..., :1]), transmittance[..., :-1]], dim=-1)
    weights = alpha * before
    colour = torch.einsum("bpk,bkd->bpd", weights, colors)
    return colour, 1.0 - transmittance[..., -1:]


def _gather(flat, index):
    return flat[index]


class _Composite(torch.autograd.Function):
    """Tiled compositing; backward recomputes each chunk so no per-pair tensor outlives its chunk."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, plan, absgrad):
        C, N, H, W = plan.shape
        D = colors.shape[-1]
        flat = _flat_inputs(means2d, conics, colors, opacities)
        out_colour = means2d.new_zeros(plan.n_pixels + 1, D)
        out_alpha = means2d.new_zeros(plan.n_pixels + 1, 1)
        for (tiles, index, pixel), centres in zip(plan.chunks, plan.pixel_centres):
            m, q, o, col = (_gather(t, index) for t in flat)
            colour, alpha = composite(m[:, None] - centres[:, :, None], q, o, col)
            out_colour[pixel] = colour
            out_alpha[pixel] = alpha
        ctx.plan, ctx.absgrad = plan, absgrad
        ctx.save_for_backward(means2d, conics, colors, opacities)
        return out_colour[:-1].reshape(C, H, W, D), out_alpha[:-1].reshape(C, H, W, 1)

    @staticmethod
    def backward(ctx, grad_colour, grad_alpha):
        means2d, conics, colors, opacities = ctx.saved_tensors
        plan = ctx.plan
        C, N, H, W = plan.shape
        D = colors.shape[-1]
        flat = [t.detach() for t in _flat_inputs(means2d, conics, colors, opacities)]
        grads = [torch.zeros_like(t) for t in flat]
        abs_means = torch.zeros_like(flat[0]) if ctx.absgrad else None
        grad_colour = torch.cat([grad_colour.reshape(-1, D), grad_colour.new_zeros(1, D)])
        grad_alpha = torch.cat([grad_alpha.reshape(-1, 1), grad_alpha.new_zeros(1, 1)])
        for (tiles, index, pixel), centres in zip(plan.chunks, plan.pixel_centres):
            m, q, o, col = (_gather(t, index) for t in flat)
            with torch.enable_grad():
                delta = (m[:, None] - centres[:, :, None]).requires_grad_()
                q, o, col = q.requires_grad_(), o.requires_grad_(), col.requires_grad_()
                colour, alpha = composite(delta, q, o, col)
                g_delta, g_q, g_o, g_col = torch.autograd.grad(
                    (colour, alpha), (delta, q, o, col), (grad_colour[pixel], grad_alpha[pixel])
                )
            flat_index = index.reshape(-1)
            grads[0].index_add_(0, flat_index, g_delta.sum(1).reshape(-1, 2))
            grads[1].index_add_(0, flat_index, g_q.reshape(-1, 3))
            grads[2].index_add_(0, flat_index, g_o.reshape(-1))
            grads[3].index_add_(0, flat_index, g_col.reshape(-1, D))
            if abs_means is not None:
                abs_means.index_add_(0, flat_index, g_delta.abs().sum(1).reshape(-1, 2))
        g_means, g_conics, g_opacities, g_colors = (g[:-1] for g in grads)
        if abs_means is not None:
            # gsplat's convention: the strategy reads means2d.absgrad after backward
            means2d.absgrad = abs_means[:-1].reshape(C, N, 2)
        return (
            g_means.reshape(C, N, 2),
            g_conics.reshape(C, N, 3),
            g_colors.reshape(C, N, D),
            g_opacities.reshape(C, N),
            None,
            None,
        )


def _flat_inputs(means2d, conics, colors, opacities):
    """(C*N+1, ...) views with a sentinel last row (opacity 0) for padded slots."""
    C, N = opacities.shape
    return [
        torch.cat([means2d.reshape(C * N, 2), means2d.new_zeros(1, 2)]),
        torch.cat([conics.reshape(C * N, 3), conics.new_zeros(1, 3)]),
        torch.cat([opacities.reshape(C * N), opacities.new_zeros(1)]),
        torch.cat([colors.reshape(C * N, -1), colors.new_zeros(1, colors.shape[-1])]),
    ]
