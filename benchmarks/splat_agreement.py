"""How closely SKED's torch rasterizer agrees with gsplat's CUDA kernels on a random scene (used by gpu_check)."""

from __future__ import annotations

from typing import Dict

import torch
from torch import Tensor

from sked_ns.models.splat.torch_rasterizer import rasterize_torch_defaults


def random_scene(n_gaussians=2000, width=96, height=64, n_cameras=2, sh_degree=3, seed=0, device="cpu"):
    """A random splat scene in front of `n_cameras` cameras: kwargs for `rasterize` (float32)."""
    generator = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=generator)  # noqa: E731
    spacing = 2.0 / n_gaussians ** (1 / 3)
    viewmats = torch.eye(4).repeat(n_cameras, 1, 1)
    viewmats[:, 2, 3] = 3.5
    viewmats[:, 0, 3] = torch.linspace(-0.3, 0.3, n_cameras)
    focal = 0.9 * width
    Ks = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]]).repeat(n_cameras, 1, 1)
    scene = {
        "means": rand(n_gaussians, 3) * 2 - 1,
        "quats": torch.randn(n_gaussians, 4, generator=generator),
        "scales": spacing * torch.exp(0.3 * torch.randn(n_gaussians, 3, generator=generator)) * 0.7,
        "opacities": rand(n_gaussians) * 0.9 + 0.05,
        "colors": (rand(n_gaussians, (sh_degree + 1) ** 2, 3) - 0.5) * 0.6 if sh_degree is not None else rand(n_gaussians, 3),
        "viewmats": viewmats,
        "Ks": Ks,
        "width": width,
        "height": height,
        "sh_degree": sh_degree,
        "backgrounds": rand(n_cameras, 3),
    }
    return {k: v.to(device) if isinstance(v, Tensor) else v for k, v in scene.items()}


def compare_with_gsplat(device="cuda", n_gaussians=2000, width=96, height=64, sh_degree=3, seed=0) -> Dict[str, float]:
    """Render one random scene with gsplat's `rasterization` on `device` and with the CPU path.

    Returns the largest absolute differences ("image", "alpha", "absgrad" and "grad_<input>" for means,
    quats, scales, opacities, colors, backgrounds, means2d) and, under "<key>_scale", the largest
    magnitude of gsplat's value, so a caller can judge relative error (float32: expect ~1e-5 relative;
    a Gaussian that lands exactly on a skip or stop threshold can differ more at one pixel).
    """
    from gsplat.rendering import rasterization

    scene = random_scene(n_gaussians, width, height, sh_degree=sh_degree, seed=seed)
    inputs = ("means", "quats", "scales", "opacities", "colors", "backgrounds")
    weights = torch.rand(len(scene["viewmats"]), height, width, 4, generator=torch.Generator().manual_seed(seed + 1))

    def run(target, render_fn, **extra):
        leaves = {k: scene[k].to(target).clone().requires_grad_() for k in inputs}
        rest = {k: (v.to(target) if isinstance(v, Tensor) else v) for k, v in scene.items() if k not in inputs}
        render, alpha, info = render_fn(**leaves, **rest, absgrad=True, **extra)
        info["means2d"].retain_grad()
        # a loss that weights every pixel and channel differently, so every gradient is exercised
        loss = (torch.cat([render, alpha], dim=-1) * weights.to(target)).sum()
        loss.backward()
        values = {"image": render, "alpha": alpha, "grad_means2d": info["means2d"].grad, "absgrad": info["means2d"].absgrad}
        values.update({f"grad_{k}": leaves[k].grad for k in inputs})
        # compare only where both project the Gaussian (gsplat leaves other means2d entries unwritten)
        visible = (info["radii"] > 0)[..., None]
        for key in ("grad_means2d", "absgrad"):
            values[key] = torch.where(visible, values[key], torch.zeros_like(values[key]))
        return {k: v.detach().float().cpu().clone() for k, v in values.items()}

    theirs = run(device, rasterization, packed=False)
    ours = run("cpu", rasterize_torch_defaults)
    result = {}
    for key in theirs:
        result[key] = float((theirs[key] - ours[key]).abs().max())
        result[f"{key}_scale"] = float(theirs[key].abs().max())
    return result
