"""The paper's evaluation protocol on sketch views: base fidelity outside, Intersection-over-Sketch."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from torch import Tensor

# Nine thresholds spread over [25, 225] / 255 (paper, Sec. 4.2).
IOS_THRESHOLDS = tuple(np.linspace(25, 225, 9) / 255.0)
SSIM_MIN_SIDE = 6
"""torchmetrics' SSIM reflect-pads an image by half its 11-pixel window, which needs a side longer than that."""


def intersection_over_sketch(alpha: Tensor, mask: Tensor, thresholds: Sequence[float] = IOS_THRESHOLDS) -> float:
    """|M and alpha > tau| / |M|, averaged over the thresholds: how much of the sketch is filled."""
    mask = mask.bool()
    if not mask.any():
        raise ValueError("Intersection-over-Sketch of an empty mask is undefined.")
    alpha = alpha.reshape(mask.shape).float()
    return float(np.mean([((alpha > tau) & mask).sum().item() / mask.sum().item() for tau in thresholds]))


def ssim_outside(edited: Tensor, base: Tensor, mask: Tensor) -> float:
    """Mean of the SSIM map (11x11 Gaussian windows) over the pixels outside the sketch."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    keep = ~mask.bool().reshape(edited.shape[:2])
    if not keep.any():
        raise ValueError("The sketch covers the whole image: nothing outside it to compare.")
    if min(edited.shape[:2]) < SSIM_MIN_SIDE:
        raise ValueError(f"SSIM of a {edited.shape[1]}x{edited.shape[0]} image is undefined (its 11-pixel window "
                         f"needs at least {SSIM_MIN_SIDE} pixels a side).")
    to_nchw = lambda image: image.float().permute(2, 0, 1)[None]  # noqa: E731
    _, ssim_map = structural_similarity_index_measure(
        to_nchw(edited), to_nchw(base), data_range=1.0, return_full_image=True
    )
    return float(ssim_map[0].mean(dim=0)[keep].mean())


def psnr_outside(edited: Tensor, base: Tensor, mask: Tensor) -> float:
    """PSNR between edited and base renders over the pixels outside the sketch (images in [0, 1])."""
    keep = ~mask.bool().reshape(edited.shape[:2])
    if not keep.any():
        raise ValueError("The sketch covers the whole image: nothing outside it to compare.")
    mse = ((edited.float() - base.float()) ** 2)[keep].mean().item()
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def psnr_inside(edited: Tensor, target: Tensor, mask: Tensor) -> float:
    """PSNR over the sketched pixels only: the edit against a known target (benchmark scenes)."""
    mask = mask.bool().reshape(edited.shape[:2])
    if not mask.any():
        raise ValueError("The sketch is empty: no pixel inside it to compare.")
    return psnr_outside(edited, target, ~mask)
