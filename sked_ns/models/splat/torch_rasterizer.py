"""The torch twin of gsplat 1.4's rasterizer, for any device: what `rasterize` runs off CUDA.

- projection (projection.py): gsplat's own torch reference (`_quat_scale_to_covar_preci`, `_fully_fused_projection`, step by step,
  with gsplat's kernel's `radius_clip` and a guard against NaN gradients at z = 0),
  SH colours with gsplat's torch `_spherical_harmonics` (view direction: camera centre to mean, then
  ``clamp_min(rgb + 0.5, 0)`` as gsplat does);
- binning: a Gaussian with radius > 0 may reach the pixels of the 16x16 tiles its 3-sigma square
  touches (gsplat's tile rule) where its alpha can reach 1/255; those pixels are binned into 4x4
  tiles (`COMPOSITE_TILE`), each tile's list sorted front to back by camera depth (ties by index, as
  gsplat's stable radix sort);
- compositing, per pixel as gsplat's kernel: ``alpha_i = min(0.999, o_i exp(-sigma_i))``, skipped when
  ``< 1/255``, stopping before the Gaussian that takes the transmittance to ``<= 1e-4``;
  ``render = sum T_i alpha_i c_i + background (1 - alpha)``, ``alpha = 1 - T_final``. Chunks of tiles
  walk their padded lists `K_BLOCK` Gaussians at a time (log alpha of a whole block is one matmul of
  per-pixel features with per-Gaussian quadratic coefficients) and stop when every pixel is done; the
  backward pass is analytic (gsplat's, vectorised) and walks the same blocks again, so nothing per
  pixel-Gaussian pair is kept between the passes. No gradient flows through a clamped (0.999) or
  skipped alpha, as in gsplat. gsplat's own sigma < 0 skip is dropped: a positive-definite conic
  gives sigma >= 0 up to rounding.

Meant for small renders (tests, CPU edits at 64-128 px): its cost grows with the pixel-Gaussian pairs
evaluated; memory stays bounded (PAIR_BUDGET pairs per block). Timings: benchmarks/results and docs/benchmarks.md.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from sked_ns.models.splat.projection import project, view_colors

TILE_SIZE = 16
"""gsplat's tile edge in pixels: which pixels a Gaussian may reach."""
COMPOSITE_TILE = 4
"""Tile edge of the CPU compositor: smaller tiles waste fewer pairs on pixels a Gaussian cannot reach."""
PAIR_BUDGET = 1 << 21
"""Pixel-Gaussian pairs one block of a chunk of tiles holds (each float tensor of a block: 8 MB)."""
K_BLOCK = 256
"""Gaussians per tile composited at a time; a chunk stops after the block where all its pixels are done."""
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                     backgrounds, near_plane, far_plane, render_mode, eps2d, radius_clip, rasterize_mode,
                     absgrad):
    C = len(viewmats)
    _check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, render_mode, rasterize_mode)
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

    plan = _bin_tiles(means2d.detach(), radii, depths.detach(), conics.detach(), view_opacities.detach(), width, height)
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


def _check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, render_mode, rasterize_mode):
    """gsplat's argument checks, as ValueErrors."""
    C, N = len(viewmats), len(means)
    expected = {"means": (means, (N, 3)), "quats": (quats, (N, 4)), "scales": (scales, (N, 3)),
                "opacities": (opacities, (N,)), "viewmats": (viewmats, (C, 4, 4)), "Ks": (Ks, (C, 3, 3))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"rasterize: {name} has shape {tuple(tensor.shape)}, expected {shape}")
    if sh_degree is None:
        good = (colors.dim() == 2 and colors.shape[0] == N) or (colors.dim() == 3 and colors.shape[:2] == (C, N))
        form = "(N, D) or (C, N, D) colours"
    else:
        good = ((colors.dim() == 3 and colors.shape[0] == N) or (colors.dim() == 4 and colors.shape[:2] == (C, N))) and (
            colors.shape[-1] == 3 and colors.shape[-2] >= (sh_degree + 1) ** 2
        )
        form = f"(N, K, 3) or (C, N, K, 3) SH coefficients with K >= {(sh_degree + 1) ** 2}"
    if not good:
        raise ValueError(f"rasterize: colors has shape {tuple(colors.shape)}, expected {form}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"rasterize: render_mode must be one of {RENDER_MODES}, not {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize: rasterize_mode must be 'classic' or 'antialiased', not {rasterize_mode!r}")


@dataclass
class _TilePlan:
    """Which Gaussians (flat index c*N + n, front to back) each non-empty tile composites, in chunks."""

    chunks: list  # [(gaussian_index (B,K) padded with the sentinel C*N, pixel_ids (B,P), tile_centres (B,2), lengths)]
    n_pixels: int  # C*H*W; pixel id n_pixels is the trash row for the parts of edge tiles outside the image
    tiles_per_gauss: Tensor
    shape: tuple  # (C, N, H, W)
    tile_size: int


def _bin_tiles(means2d, radii, depths, conics, opacities, width, height, tile_size=None, pair_budget=None):
    """Vectorised binning into small tiles, sorted by (tile, depth, index), chunked.

    A Gaussian reaches a pixel only inside gsplat's 16x16 tiles its 3-sigma square touches (gsplat's
    rule, which `rasterize` must keep to match gsplat), and only where its alpha can reach 1/255 (the
    bounding box of the ellipse o exp(-sigma) = 1/255, widened a little): pairs outside both would be
    skipped anyway, so the smaller tiles change no pixel, only how many pairs are evaluated.
    """
    tile_size = tile_size or COMPOSITE_TILE
    pair_budget = pair_budget or PAIR_BUDGET
    C, N = radii.shape
    device = means2d.device
    # gsplat's rule: the 16x16 tiles of the square mean +- radius
    gsplat_width, gsplat_height = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    radius = radii.to(means2d.dtype)
    gsplat_min = torch.floor((means2d - radius[..., None]) / TILE_SIZE).long()
    gsplat_max = torch.ceil((means2d + radius[..., None]) / TILE_SIZE).long()
    limits = torch.tensor([gsplat_width, gsplat_height], device=device)
    gsplat_min = torch.minimum(gsplat_min.clamp(min=0), limits)
    gsplat_max = torch.minimum(gsplat_max.clamp(min=0), limits)
    gsplat_extent = gsplat_max - gsplat_min
    tiles_per_gauss = (gsplat_extent[..., 0] * gsplat_extent[..., 1]) * (radii > 0)
    # where alpha >= 1/255: 0.5 d^T conic d <= log(255 o), a box of half-size sqrt(2 log(255 o) cov_ii)
    a, b, c = conics.unbind(-1)
    det = a * c - b * b
    level = torch.log((255.0 * opacities).clamp(min=1e-30))
    safe_det = torch.where(det > 0, det, torch.ones_like(det))
    half = torch.sqrt((2.0 * level.clamp(min=0))[..., None] * torch.stack([c, a], dim=-1) / safe_det[..., None])
    half = torch.where((det > 0)[..., None], half * 1.001 + 0.01, torch.full_like(half, float(max(width, height))))
    size = torch.tensor([width, height], device=device, dtype=means2d.dtype)
    # pixel j (centre j + 0.5) is in reach when |j + 0.5 - mean| <= half
    first_pixel = torch.maximum(torch.ceil(means2d - half - 0.5), (gsplat_min * TILE_SIZE).to(means2d.dtype)).clamp(min=0)
    last_pixel = torch.minimum(torch.floor(means2d + half - 0.5), (gsplat_max * TILE_SIZE - 1).to(means2d.dtype))
    last_pixel = torch.minimum(last_pixel, size - 1)
    reachable = (radii > 0) & (level > 0) & (last_pixel >= first_pixel).all(-1)
    tile_min = (first_pixel.clamp(min=0, max=max(width, height)) // tile_size).long()
    tile_max = (last_pixel.clamp(min=0, max=max(width, height)) // tile_size).long() + 1
    extent = (tile_max - tile_min) * reachable[..., None]
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    tiles_per_camera = tile_width * tile_height
    small_tiles = extent[..., 0] * extent[..., 1]

    camera, gaussian = torch.nonzero(small_tiles > 0, as_tuple=True)
    # front to back: a stable sort keeps index order among equal depths, as gsplat's radix sort
    order = torch.sort(depths[camera, gaussian], stable=True).indices
    camera, gaussian = camera[order], gaussian[order]
    counts = small_tiles[camera, gaussian]
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
    # longest lists first, so each chunk pads little
    busy = busy[torch.sort(per_tile[busy], descending=True, stable=True).indices]
    busy_counts = per_tile[busy].tolist()

    pixels_per_tile = tile_size * tile_size
    offset_y, offset_x = (
        g.reshape(-1) for g in torch.meshgrid(torch.arange(tile_size, device=device), torch.arange(tile_size, device=device), indexing="ij")
    )
    chunks = []
    i = 0
    while i < len(busy):
        longest = busy_counts[i]
        size = max(1, pair_budget // (min(longest, K_BLOCK) * pixels_per_tile))
        tiles = busy[i : i + size]
        i += size
        slot = torch.arange(longest, device=device)
        valid = slot[None] < per_tile[tiles][:, None]
        position = (starts[tiles][:, None] + slot[None]).clamp(max=len(flat_gaussian) - 1)
        index = torch.where(valid, flat_gaussian[position], torch.full_like(position, C * N))
        camera_of, in_camera = tiles // tiles_per_camera, tiles % tiles_per_camera
        corner_x = (in_camera % tile_width) * tile_size
        corner_y = (in_camera // tile_width) * tile_size
        x, y = corner_x[:, None] + offset_x[None], corner_y[:, None] + offset_y[None]
        inside = (x < width) & (y < height)
        pixel = torch.where(inside, camera_of[:, None] * height * width + y * width + x, torch.full_like(x, C * height * width))
        tile_centres = torch.stack([corner_x, corner_y], dim=-1).to(means2d.dtype) + tile_size / 2
        chunks.append((index, pixel, tile_centres, busy_counts[i - size : i]))
    return _TilePlan(chunks, C * height * width, tiles_per_gauss.int(), (C, N, height, width), tile_size)


def _pixel_features(tile_size, dtype, device):
    """(P,6) features of each pixel of a tile, (u, v) from the tile centre: log(o e^-sigma) = features @ coefficients."""
    offsets = torch.arange(tile_size, device=device, dtype=dtype) + 0.5 - tile_size / 2
    v, u = (g.reshape(-1) for g in torch.meshgrid(offsets, offsets, indexing="ij"))
    return torch.stack([0.5 * u * u, u * v, 0.5 * v * v, -u, -v, torch.ones_like(u)], dim=-1)


def _log_alpha_coefficients(means2d, conics, opacities, tile_centres):
    """(B,6,K) coefficients of log(o) - sigma(u, v) as a quadratic in the pixel's (u, v).

    sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 with dx = mean - pixel (gsplat's kernel); tile-centred
    coordinates keep the expanded terms small, so float32 loses little against the direct formula (the
    rasterizer's tests compare them). A matmul with the pixel features then gives every pixel's value.
    """
    mx, my = (means2d - tile_centres[:, None, :]).unbind(-1)
    a, b, c = conics.unbind(-1)
    constant = 0.5 * (a * mx * mx + c * my * my) + b * mx * my
    # opacity 0 (the padding) gives a vanishing alpha, and a zero gradient through the clamp
    log_opacity = torch.log(opacities.clamp(min=1e-30))
    return torch.stack([-a, -b, -c, -(a * mx + b * my), -(b * mx + c * my), log_opacity - constant], dim=1)


def _block_weights(features, coefficients, carry, live):
    """One block of Gaussians at every pixel of a chunk's tiles, with gsplat's skip and stop rules.

    Returns o e^-sigma, alpha (0 where skipped), transmittance before each, whether each counts, the
    blending weights, and the transmittance and still-open pixels after the block.
    """
    raw = torch.exp(torch.matmul(features, coefficients))  # (B,P,Kb)
    alpha = torch.clamp_max(raw, ALPHA_MAX) * (raw >= ALPHA_MIN)
    start = carry * live
    after = torch.cumprod(1.0 - alpha, dim=-1) * start[..., None]
    # a Gaussian counts only while the transmittance after it stays above the cut-off (exclusive);
    # a pixel's open flag (live) makes start 0, so nothing counts once it is done
    counted = after > TRANSMITTANCE_MIN
    before = torch.cat([start[..., None], after[..., :-1]], dim=-1)
    weight = torch.where(counted, alpha * before, torch.zeros_like(alpha))
    carry = torch.where(counted, after, carry[..., None]).amin(-1)
    live = live * counted[..., -1]
    return raw, alpha, before, counted, weight, carry, live


class _Composite(torch.autograd.Function):
    """Tiled front-to-back compositing (gsplat's kernel rules) with an analytic backward pass.

    Each chunk of tiles (sorted by list length) walks its lists K_BLOCK Gaussians at a time, dropping
    tiles whose list has ended, and stops when all its pixels are done; the backward pass walks the
    same blocks again, so nothing per pixel-Gaussian pair is kept between the passes.
    """

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, plan, absgrad):
        C, N, H, W = plan.shape
        D = colors.shape[-1]
        flat = _flat_inputs(means2d, conics, colors, opacities)
        features = _pixel_features(plan.tile_size, means2d.dtype, means2d.device)
        P = features.shape[0]
        out_colour = means2d.new_zeros(plan.n_pixels + 1, D)
        out_transmittance = means2d.new_ones(plan.n_pixels + 1)
        blocks = []
        for index, pixel, tile_centres, lengths in plan.chunks:
            means, conic, opacity, colour_of = (t[index] for t in flat)
            coefficients = _log_alpha_coefficients(means, conic, opacity, tile_centres)
            B, K = index.shape
            carry, live = means2d.new_ones(B, P), means2d.new_ones(B, P)
            colour = means2d.new_zeros(B, P, D)
            n_blocks = 0
            for begin in range(0, K, K_BLOCK):
                end = min(begin + K_BLOCK, K)
                b = _tiles_longer_than(lengths, begin)
                *_, weight, carry[:b], live[:b] = _block_weights(features, coefficients[:b, :, begin:end], carry[:b], live[:b])
                colour[:b] += torch.bmm(weight, colour_of[:b, begin:end])
                n_blocks += 1
                if not bool(live.any()):
                    break
            blocks.append(n_blocks)
            out_colour[pixel] = colour
            out_transmittance[pixel] = carry
        ctx.plan, ctx.absgrad, ctx.blocks = plan, absgrad, blocks
        out_colour, out_transmittance = out_colour[:-1], out_transmittance[:-1]
        ctx.save_for_backward(means2d, conics, colors, opacities, out_colour, out_transmittance)
        return out_colour.reshape(C, H, W, D), (1.0 - out_transmittance).reshape(C, H, W, 1)

    @staticmethod
    def backward(ctx, grad_colour, grad_alpha):
        means2d, conics, colors, opacities, out_colour, out_transmittance = ctx.saved_tensors
        plan = ctx.plan
        C, N, H, W = plan.shape
        D = colors.shape[-1]
        flat = [t.detach() for t in _flat_inputs(means2d, conics, colors, opacities)]
        grads = [torch.zeros_like(t) for t in flat]
        abs_means = torch.zeros_like(flat[0]) if ctx.absgrad else None
        features = _pixel_features(plan.tile_size, means2d.dtype, means2d.device)
        P = features.shape[0]
        pad = lambda t: torch.cat([t, t.new_zeros(1, *t.shape[1:])])  # noqa: E731
        grad_colour = pad(grad_colour.reshape(-1, D))
        grad_alpha = pad(grad_alpha.reshape(-1))
        # sum_j w_j (c_j . g) over a pixel's whole list, and T_final (alpha = 1 - T_final)
        total = pad((out_colour * grad_colour[:-1]).sum(-1))
        final = torch.cat([out_transmittance, out_transmittance.new_ones(1)])
        for (index, pixel, tile_centres, lengths), n_blocks in zip(plan.chunks, ctx.blocks):
            means, conic, opacity, colour_of = (t[index] for t in flat)
            B, K = index.shape
            with torch.enable_grad():
                leaves = (means.requires_grad_(), conic.requires_grad_(), opacity.requires_grad_())
                coefficients = _log_alpha_coefficients(*leaves, tile_centres)
            g_colour = grad_colour[pixel]  # (B,P,D)
            # what the successors of a Gaussian and the final transmittance add to the loss
            residual = total[pixel] - grad_alpha[pixel] * final[pixel]
            carry, live = means2d.new_ones(B, P), means2d.new_ones(B, P)
            prefix = means2d.new_zeros(B, P)
            g_coefficients = torch.zeros_like(coefficients)
            g_colour_of = torch.zeros_like(colour_of)
            g_abs = means2d.new_zeros(B, K, 2) if abs_means is not None else None
            for begin in range(0, min(n_blocks * K_BLOCK, K), K_BLOCK):
                end = min(begin + K_BLOCK, K)
                b = _tiles_longer_than(lengths, begin)
                coefficient = coefficients[:b, :, begin:end].detach()
                raw, alpha, before, counted, weight, carry[:b], live[:b] = _block_weights(
                    features, coefficient, carry[:b], live[:b]
                )
                colour_dot = torch.bmm(g_colour[:b], colour_of[:b, begin:end].transpose(1, 2))  # (b,P,Kb)
                through = torch.cumsum(weight * colour_dot, dim=-1) + prefix[:b, :, None]
                prefix[:b] = through[..., -1]
                # d/d alpha_i of sum_j w_j c_j.g + (1 - T_final) g_alpha, T_final = prod_j (1 - alpha_j)
                g_alpha = before * colour_dot - (residual[:b, :, None] - through) / (1.0 - alpha)
                # clamped (> 0.999) or skipped alphas pass no gradient, as in gsplat's backward kernel
                differentiable = counted & (raw >= ALPHA_MIN) & (raw <= ALPHA_MAX)
                g_log = torch.where(differentiable, g_alpha * raw, torch.zeros_like(raw))
                g_coefficients[:b, :, begin:end] = torch.matmul(features.T, g_log)
                g_colour_of[:b, begin:end] = torch.bmm(weight.transpose(1, 2), g_colour[:b])
                if g_abs is not None:
                    na, nb, nc, nax, nbx, _ = coefficient.unbind(1)  # negated conic terms
                    u, v = -features[:, 3:4], -features[:, 4:5]  # (P,1)
                    # per pixel, d sigma / d mean = conic @ (mean - pixel)
                    d_x = (na[:, None] * u + nb[:, None] * v) - nax[:, None]
                    d_y = (nb[:, None] * u + nc[:, None] * v) - nbx[:, None]
                    g_abs[:b, begin:end, 0] = (g_log * d_x).abs().sum(1)
                    g_abs[:b, begin:end, 1] = (g_log * d_y).abs().sum(1)
            g_means, g_conic, g_opacity = torch.autograd.grad(coefficients, leaves, g_coefficients)
            flat_index = index.reshape(-1)
            for total_grad, g in zip(grads, (g_means, g_conic, g_opacity, g_colour_of)):
                total_grad.index_add_(0, flat_index, g.reshape(len(flat_index), *total_grad.shape[1:]))
            if g_abs is not None:
                abs_means.index_add_(0, flat_index, g_abs.reshape(-1, 2))
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


def _tiles_longer_than(lengths, begin):
    """How many of a chunk's tiles (longest list first) still have Gaussians at position `begin`."""
    return bisect.bisect_left([-n for n in lengths], -begin)


def _flat_inputs(means2d, conics, colors, opacities):
    """(C*N+1, ...) copies with a sentinel last row (opacity 0) for padded slots."""
    C, N = opacities.shape
    D = colors.shape[-1]
    return [
        torch.cat([means2d.reshape(C * N, 2), means2d.new_zeros(1, 2)]),
        torch.cat([conics.reshape(C * N, 3), conics.new_zeros(1, 3)]),
        torch.cat([opacities.reshape(C * N), opacities.new_zeros(1)]),
        torch.cat([colors.reshape(C * N, D), colors.new_zeros(1, D)]),
    ]


def rasterize_torch_defaults(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options):
    """The CPU path with `rasterize`'s defaults, whatever the tensors' device."""
    defaults = dict(sh_degree=None, backgrounds=None, near_plane=0.01, far_plane=1e10, render_mode="RGB",
                    eps2d=0.3, radius_clip=0.0, rasterize_mode="classic", absgrad=False)
    defaults.update(options)
    return rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **defaults)
