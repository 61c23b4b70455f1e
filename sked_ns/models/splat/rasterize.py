"""Gaussian-splat rasterization: gsplat's CUDA rasterizer on a GPU, a torch twin elsewhere.

`rasterize` takes the arguments of gsplat 1.4's `gsplat.rendering.rasterization` (with
``packed=False``) and returns what it returns: ``(render (C,H,W,D'), alpha (C,H,W,1), info)``.
On CUDA tensors it *is* gsplat's `rasterization`; on any other device it runs the torch twin
(torch_rasterizer.py: gsplat's projection and compositing rules, analytic backward).

`info` carries what gsplat's `DefaultStrategy` reads (``means2d`` in the graph, with ``.absgrad`` set
by the backward when ``absgrad=True``; int32 ``radii`` (C,N); ``width``, ``height``, ``n_cameras``,
``gaussian_ids=None``), plus ``depths``, ``conics``, ``opacities``, ``camera_ids=None``, ``tile_size``.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

from torch import Tensor

from sked_ns.models.splat.torch_rasterizer import rasterize_torch


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
    return rasterize_torch(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=sh_degree,
        backgrounds=backgrounds, near_plane=near_plane, far_plane=far_plane, render_mode=render_mode,
        eps2d=eps2d, radius_clip=radius_clip, rasterize_mode=rasterize_mode, absgrad=absgrad,
    )


