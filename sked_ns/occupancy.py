"""Occupancy-grid ray marching (instant-ngp) that also runs where nerfacc's kernels cannot.

nerfacc's grid traversal and packed scans are CUDA-only. On CUDA they are used exactly as
nerfstudio uses them; elsewhere (CPU tests, the CPU demo) the same sampling runs in plain
torch: steps of `render_step_size` (growing with `cone_angle`), kept where the step's
midpoint falls in an occupied cell of the finest grid level containing it, then culled by
transmittance and alpha like nerfacc's `render_visibility_from_density`.
"""

from __future__ import annotations

import math
from typing import Callable, Optional, Tuple

import nerfacc
import torch
from torch import Tensor

from sked_ns.nerfacc_kernels import ensure_kernels

MAX_CANDIDATES = 1 << 22
"""Ray-step candidates examined at once by the torch marcher (bounds its memory)."""


class PortableOccGridEstimator(nerfacc.OccGridEstimator):
    """nerfacc's occupancy grid; `sampling` falls back to torch off CUDA."""

    @torch.no_grad()
    def sampling(self, rays_o: Tensor, rays_d: Tensor, sigma_fn: Optional[Callable] = None, alpha_fn=None,
                 near_plane: float = 0.0, far_plane: float = 1e10, t_min: Optional[Tensor] = None,
                 t_max: Optional[Tensor] = None, render_step_size: float = 1e-3, early_stop_eps: float = 1e-4,
                 alpha_thre: float = 0.0, stratified: bool = False, cone_angle: float = 0.0):
        if rays_o.is_cuda:
            ensure_kernels()
            return super().sampling(rays_o, rays_d, sigma_fn=sigma_fn, alpha_fn=alpha_fn, near_plane=near_plane,
                                    far_plane=far_plane, t_min=t_min, t_max=t_max, render_step_size=render_step_size,
                                    early_stop_eps=early_stop_eps, alpha_thre=alpha_thre, stratified=stratified,
                                    cone_angle=cone_angle)
        assert alpha_fn is None, "the torch marcher supports sigma_fn only (as nerfstudio uses it)"
        nears = torch.full_like(rays_o[:, 0], near_plane)
        fars = torch.full_like(rays_o[:, 0], far_plane)
        if t_min is not None:
            nears = torch.maximum(nears, t_min)
        if t_max is not None:
            fars = torch.minimum(fars, t_max)
        if stratified:
            nears = nears + torch.rand_like(nears) * render_step_size
        # The grid follows the rays: a CUDA grid can be checked against CPU rays.
        ray_indices, t_starts, t_ends = march_grid(
            self.binaries.to(rays_o.device), self.aabbs.to(rays_o.device), rays_o, rays_d, nears, fars,
            render_step_size, cone_angle,
        )
        if sigma_fn is not None and (alpha_thre > 0.0 or early_stop_eps > 0.0) and len(t_starts):
            alpha_thre = min(alpha_thre, self.occs.mean().item())
            sigmas = sigma_fn(t_starts, t_ends, ray_indices)
            alphas = -torch.expm1(-sigmas * (t_ends - t_starts))
            transmittance = packed_exclusive_transmittance(sigmas * (t_ends - t_starts), ray_indices, len(rays_o))
            keep = (transmittance >= early_stop_eps) & (alphas >= alpha_thre)
            ray_indices, t_starts, t_ends = ray_indices[keep], t_starts[keep], t_ends[keep]
        return ray_indices, t_starts, t_ends


def step_starts(t0: Tensor, count: int, step: float, cone_angle: float) -> Tensor:
    """t_k for k = 0..count per ray: t_{k+1} = t_k + max(step, cone_angle t_k) (nerfacc's calc_dt)."""
    k = torch.arange(count + 1, device=t0.device, dtype=t0.dtype)
    linear = t0[:, None] + k * step
    if cone_angle <= 0:
        return linear
    # Linear until cone_angle t reaches the step, geometric after.
    switch = step / cone_angle
    k_switch = torch.ceil(((switch - t0) / step).clamp_min(0))
    t_switch = t0 + k_switch * step
    geometric = t_switch[:, None] * (1 + cone_angle) ** (k - k_switch[:, None]).clamp_min(0)
    return torch.where(k < k_switch[:, None], linear, geometric)


def steps_needed(t0: Tensor, t1: Tensor, step: float, cone_angle: float) -> Tensor:
    """Number of steps from t0 past t1 (inverse of `step_starts`)."""
    span = (t1 - t0).clamp_min(0)
    if cone_angle <= 0:
        return torch.ceil(span / step)
    switch = step / cone_angle
    k_switch = torch.ceil(((switch - t0) / step).clamp_min(0))
    t_switch = t0 + k_switch * step
    linear = torch.ceil(span / step)
    geometric = k_switch + torch.ceil(torch.log(t1.clamp_min(1e-12) / t_switch.clamp_min(1e-12)).clamp_min(0)
                                      / math.log1p(cone_angle))
    return torch.where(t1 <= t_switch, linear, geometric)


def ray_aabb(rays_o: Tensor, rays_d: Tensor, aabb: Tensor) -> Tuple[Tensor, Tensor]:
    """Entry and exit distances of rays through a box (slab method); exit < entry when missed."""
    inverse = 1.0 / torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    t_a, t_b = (aabb[:3] - rays_o) * inverse, (aabb[3:] - rays_o) * inverse
    return torch.minimum(t_a, t_b).amax(-1), torch.maximum(t_a, t_b).amin(-1)


def occupied(binaries: Tensor, aabbs: Tensor, points: Tensor) -> Tensor:
    """Whether each point's cell is on, at the finest level whose box holds it (nerfacc's rule)."""
    levels, *resolution = binaries.shape
    resolution = torch.tensor(resolution, device=points.device)
    result = torch.zeros(points.shape[:-1], dtype=torch.bool, device=points.device)
    found = torch.zeros_like(result)
    for level in range(levels):
        low, high = aabbs[level, :3], aabbs[level, 3:]
        unit = (points - low) / (high - low)
        inside = ((unit >= 0) & (unit < 1)).all(-1) & ~found
        cell = (unit[inside] * resolution).long().clamp_max(resolution - 1)
        result[inside] = binaries[level][cell[:, 0], cell[:, 1], cell[:, 2]]
        found |= inside
    return result


def march_grid(binaries: Tensor, aabbs: Tensor, rays_o: Tensor, rays_d: Tensor, nears: Tensor, fars: Tensor,
               step: float, cone_angle: float = 0.0) -> Tuple[Tensor, Tensor, Tensor]:
    """Packed samples (ray_indices, t_starts, t_ends), sorted by ray then distance."""
    entry, exit_ = ray_aabb(rays_o, rays_d, aabbs[-1])
    t0 = torch.maximum(nears, entry.clamp_min(0))
    t1 = torch.minimum(fars, exit_)
    counts = torch.where(t1 > t0, steps_needed(t0, t1, step, cone_angle), torch.zeros_like(t0)).long()
    out_rays, out_starts, out_ends = [], [], []
    rays = torch.arange(len(rays_o), device=rays_o.device)
    begin = 0
    while begin < len(rays_o):
        # Take as many rays as fit the candidate budget (at least one).
        widest = counts[begin:].cummax(0).values
        fit = int(((torch.arange(1, len(widest) + 1, device=widest.device) * widest) <= MAX_CANDIDATES).sum())
        end = begin + max(fit, 1)
        width = int(counts[begin:end].max()) if end > begin else 0
        if width > 0:
            t = step_starts(t0[begin:end], width, step, cone_angle)
            starts, ends = t[:, :-1], t[:, 1:]
            valid = (torch.arange(width, device=t.device) < counts[begin:end, None]) & (starts < t1[begin:end, None])
            mids = rays_o[begin:end, None] + rays_d[begin:end, None] * ((starts + ends) / 2)[..., None]
            keep = valid & occupied(binaries, aabbs, mids)
            out_rays.append(rays[begin:end, None].expand_as(keep)[keep])
            out_starts.append(starts[keep])
            out_ends.append(ends[keep])
        begin = end
    if not out_rays:
        empty = rays_o.new_zeros(0)
        return empty.long(), empty, empty
    return torch.cat(out_rays), torch.cat(out_starts), torch.cat(out_ends)


def _padded_index(ray_indices: Tensor, n_rays: int) -> Tuple[Tensor, int]:
    """Each packed sample's slot within its ray (samples sorted by ray)."""
    counts = torch.bincount(ray_indices, minlength=n_rays)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(ray_indices), device=ray_indices.device) - first[ray_indices]
    return slot, int(counts.max()) if len(counts) else 0


def packed_exclusive_transmittance(optical_depth: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """exp(-sum of earlier samples' sigma*delta on the same ray), per packed sample.

    Scattered to a padded (rays, samples) grid so each ray sums on its own: a cumsum over all
    samples at once would lose precision subtracting large running totals.
    """
    if len(optical_depth) == 0:
        return optical_depth
    slot, width = _padded_index(ray_indices, n_rays)
    padded = optical_depth.new_zeros(n_rays, width + 1)
    padded = padded.index_put((ray_indices, slot + 1), optical_depth)
    exclusive = torch.cumsum(padded, dim=1)[ray_indices, slot]
    return torch.exp(-exclusive)


def render_weights(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """Volume-rendering weights T_i alpha_i of packed samples (nerfacc on CUDA, torch elsewhere)."""
    if sigmas.is_cuda:
        ensure_kernels()
        return nerfacc.render_weight_from_density(t_starts, t_ends, sigmas, ray_indices=ray_indices, n_rays=n_rays)[0]
    optical_depth = sigmas * (t_ends - t_starts)
    alphas = -torch.expm1(-optical_depth)
    return packed_exclusive_transmittance(optical_depth, ray_indices, n_rays) * alphas
