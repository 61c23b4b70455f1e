"""SKED's losses as plain functions over tensors (paper Sec. 3.2).

Choices where the paper and the authors' code differ:
- L_pres is a MEAN over samples (paper), not the code's sum: the weight then does not
  depend on rays per batch or samples per ray. The code's sum with lambda_pres = 5e-6 over
  ~16k rays x ~64 samples is about 5 x this mean, hence our default lambda_pres = 5.
- The colour term is gated by base occupancy and w (paper): colour in empty space is
  unconstrained and fitting it only fights the density term.
- alpha_e uses a fixed delta (code, 0.07): the sampler's step sizes vary by orders of
  magnitude along a proposal-sampled ray, and a fixed delta keeps the term a density
  classifier independent of the sampler.
- Probabilities are squashed affinely into [eps, 1 - eps] instead of clamped (code:
  clamp to [0.01, 0.99]), so an empty region still gets a gradient from L_pres and L_sil.
All maths runs in float32 whatever the input dtype, so fp16 renders stay finite.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

PROBABILITY_EPS = 1e-2
"""Bounds for occupancy probabilities in L_pres (the authors' clamp range)."""
ALPHA_EPS = 1e-4
"""Smallest accumulation L_sil and L_sp take the log of."""


def occupancy_log_probabilities(density: Tensor, delta: float, eps: float = PROBABILITY_EPS) -> tuple[Tensor, Tensor]:
    """log p and log(1 - p) for p = eps + (1 - 2 eps) alpha, alpha = 1 - exp(-density delta).

    Written with exp(-x) and expm1 so neither underflows to log(0) for density 0 or 1e6.
    """
    density = density.float()
    # where() rather than clamp: keeps the gradient at exactly zero density.
    x = torch.where(density >= 0, density, torch.zeros_like(density)) * delta
    transmittance = torch.exp(-x)
    log_p = torch.log(eps + (1.0 - 2.0 * eps) * -torch.expm1(-x))
    log_not_p = torch.log(eps + (1.0 - 2.0 * eps) * transmittance)
    return log_p, log_not_p


def preservation_loss(
    density_edit: Float[Tensor, "*bs num_samples 1"],
    rgb_edit: Float[Tensor, "*bs num_samples 3"],
    density_base: Float[Tensor, "*bs num_samples 1"],
    rgb_base: Float[Tensor, "*bs num_samples 3"],
    preservation_weight: Float[Tensor, "*bs num_samples 1"],
    occupancy_threshold: float = 5.0,
    delta: float = 0.07,
    lambda_colour: float = 5.0,
    target: str = "occupancy",
) -> Tensor:
    """L_pres = mean_i w_i [CE(alpha_e,i, occ_o,i) + lambda_c occ_o,i ||c_e,i - c_o,i||^2] (paper Eq. 3).

    target "occupancy" (paper): occ_o = 1[sigma_o > threshold]. "density": occ_o = the base's own squashed alpha
    at delta, so the minimum is sigma_e = sigma_o and a soft base is kept soft, not sharpened to binary occupancy.
    """
    if target == "occupancy":
        occupied = (density_base.float() > occupancy_threshold).float()
    elif target == "density":
        occupied = occupancy_log_probabilities(density_base.detach(), delta)[0].exp()
    else:
        raise ValueError(f"preservation_target must be 'occupancy' or 'density', not {target!r}")
    log_p, log_not_p = occupancy_log_probabilities(density_edit, delta)
    cross_entropy = -(occupied * log_p + (1.0 - occupied) * log_not_p)
    colour = occupied * (rgb_edit.float() - rgb_base.float()).pow(2).sum(dim=-1, keepdim=True)
    per_sample = preservation_weight.float() * (cross_entropy + lambda_colour * colour)
    return per_sample.mean() if per_sample.numel() else per_sample.sum()


# Under "sketch" normalisation L_sil weighs every sketch as image normalisation weighs one covering this
# fraction of its frame (the authors' published sketches cover 2.4% and 5%, the demo's 5-6%): lambda_sil keeps its scale.
REFERENCE_SKETCH_COVERAGE = 0.05


def silhouette_loss(
    accumulation: Float[Tensor, "num_views height width"], masks: Float[Tensor, "num_views height width"],
    normalisation: str = "image",
) -> Tensor:
    """L_sil = -1/(HWN) sum_j sum_x M_j(x) log alpha_j(x) (paper Eq. 5): fill the sketches.

    normalisation "sketch": the sum over the sketches' area instead of the images' (times
    REFERENCE_SKETCH_COVERAGE), so small sketches pull as hard in total as large ones. Any shapes: the
    datamanager passes its views' pixels concatenated.
    """
    # log of an affine squash into [eps, 1]: finite with a gradient at alpha = 0, exactly 0 at alpha = 1.
    alpha = accumulation.float()
    alpha = alpha + (alpha.clamp(0.0, 1.0) - alpha).detach()  # clamp the value, keep the gradient at 0
    per_pixel = -(masks.float() * torch.log(ALPHA_EPS + (1.0 - ALPHA_EPS) * alpha))
    if normalisation == "image":
        return per_pixel.mean()
    if normalisation != "sketch":
        raise ValueError(f"silhouette normalisation must be 'image' or 'sketch', got {normalisation!r}.")
    # Views may differ in size (the datamanager concatenates their pixels): one mean over all sketch pixels.
    return REFERENCE_SKETCH_COVERAGE * per_pixel.sum() / masks.float().sum().clamp_min(1.0)  # empty: 0, not NaN


def sparsity_loss(accumulation: Tensor) -> Tensor:
    """Mean binary entropy of the accumulation, in bits: pushes every pixel to fully empty or full.

    Bits (log2) as the authors' code: their lambda_sp = 5e-4 applies to it (nats would be ln 2 = 0.69x as strong).
    """
    alpha = accumulation.float().clamp(ALPHA_EPS, 1.0 - ALPHA_EPS)
    return -(alpha * torch.log(alpha) + (1.0 - alpha) * torch.log1p(-alpha)).mean() / math.log(2.0)


def new_mass_loss(
    density_edit: Float[Tensor, "*bs num_samples 1"],
    density_base: Float[Tensor, "*bs num_samples 1"],
    preservation_weight: Float[Tensor, "*bs num_samples 1"],
    delta: float = 0.07,
    gate: Optional[Float[Tensor, "*bs num_samples 1"]] = None,
) -> Tensor:
    """L_new = sum_i (1 - w_i) g_i relu(alpha_e,i - alpha_o,i) / sum_i (1 - w_i): the opacity the edit adds over
    the base, per unit of the region it may change (ours).

    L_sil asks each sketch ray for one opaque point but pulls every point of the ray's stretch of the visual
    hull alike, so it fills the whole hull; nothing then removes mass no loss asks for. This does: once the
    guidance has made a sketch ray opaque at its part, L_sil's pull on the rest of that ray vanishes and the
    bulk fades. alpha at the fixed delta saturates, so solid parts feel it little and haze the most. A mean
    over the editable samples: its scale does not depend on how much of a view the region covers. `gate` g
    (default 1): how far the sketches already have what they ask for at each sample
    (hull_carving.SketchRayOpacity), so L_new does not compete with L_sil for an empty sketch ray.
    """
    density_edit = density_edit.float()
    positive = torch.where(density_edit >= 0, density_edit, torch.zeros_like(density_edit))  # gradient at 0 kept
    alpha_edit = -torch.expm1(-positive * delta)
    alpha_base = -torch.expm1(-density_base.detach().float().clamp_min(0) * delta)
    editable = (1.0 - preservation_weight.float()).clamp(0.0, 1.0)
    added = torch.relu(alpha_edit - alpha_base)
    if gate is not None:
        added = added * gate.detach().float().clamp(0.0, 1.0)
    return (editable * added).sum() / editable.sum().clamp_min(1e-6)  # no editable sample: 0, not NaN
