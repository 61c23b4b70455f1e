"""gsplat's projection of Gaussians to a camera and their SH colours towards it, in torch (any device)."""

from __future__ import annotations

import torch


def project(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01,
            far_plane=1e10, eps2d=0.3, radius_clip=0.0, rasterize_mode="classic"):
    """gsplat's projection (its torch reference, step by step): int32 radii (C,N), means2d, depths,
    conics (C,N,3), per-view opacities (C,N).

    One change: a Gaussian outside the near/far range is projected from a stand-in point, so one on a
    camera's plane (z = 0) gets zero gradients instead of NaN from gsplat's division by z.
    """
    from gsplat.cuda._torch_impl import _persp_proj, _quat_scale_to_covar_preci, _world_to_cam

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    means_c, covars_c = _world_to_cam(means, covars, viewmats)
    depths = means_c[..., 2]
    in_range = (depths > near_plane) & (depths < far_plane)
    stand_in = torch.tensor([0.0, 0.0, 1.0], dtype=means.dtype, device=means.device)
    means_c = torch.where(in_range[..., None], means_c, stand_in)
    means2d, covars2d = _persp_proj(means_c, covars_c, Ks, width, height)

    det_orig = covars2d[..., 0, 0] * covars2d[..., 1, 1] - covars2d[..., 0, 1] * covars2d[..., 1, 0]
    covars2d = covars2d + torch.eye(2, device=means.device, dtype=means.dtype) * eps2d
    det = (covars2d[..., 0, 0] * covars2d[..., 1, 1] - covars2d[..., 0, 1] * covars2d[..., 1, 0]).clamp(min=1e-10)
    conics = torch.stack(
        [covars2d[..., 1, 1] / det, -(covars2d[..., 0, 1] + covars2d[..., 1, 0]) / 2.0 / det, covars2d[..., 0, 0] / det],
        dim=-1,
    )
    # take 3 sigma of the major axis as the radius (non differentiable), as gsplat
    b = (covars2d[..., 0, 0] + covars2d[..., 1, 1]) / 2
    radius = torch.ceil(3.0 * torch.sqrt(b + torch.sqrt(torch.clamp(b**2 - det, min=0.01)))).detach()
    inside = (
        (means2d[..., 0] + radius > 0) & (means2d[..., 0] - radius < width)
        & (means2d[..., 1] + radius > 0) & (means2d[..., 1] - radius < height)
    )
    # gsplat's kernel also drops radii <= radius_clip (its torch reference does not)
    keep = (det > 0) & in_range & inside & (radius > radius_clip)
    radii = torch.where(keep, radius, torch.zeros_like(radius)).int()

    view_opacities = opacities[None].expand(len(viewmats), -1)
    if rasterize_mode == "antialiased":
        view_opacities = view_opacities * torch.sqrt(torch.clamp(det_orig / det, min=0.0))
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
