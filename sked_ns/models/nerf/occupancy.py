"""Occupancy-grid ray marching (instant-ngp) that also runs where nerfacc's kernels cannot.

nerfacc's grid traversal and packed scans are CUDA-only. On CUDA they are used exactly as
nerfstudio uses them; elsewhere (CPU tests, the CPU demo) the same sampling runs in plain
torch, by nerfacc 0.5.2's rules (`traverse_grids_kernel` in its cuda/csrc/grid.cu): steps
from the near plane of calc_dt(t) = clamp(t cone_angle, render_step_size, 1e10) through
occupied cells, and of a fixed calc_dt taken on entering through empty ones, kept where the
step's midpoint falls in an occupied cell of the finest grid level containing it, then culled
by transmittance and alpha like nerfacc's `render_visibility_from_density`.
"""

from __future__ import annotations

import math
from typing import Callable, Optional, Tuple

import nerfacc
import torch
from torch import Tensor

from sked_ns.models.nerf.nerfacc_kernels import ensure_kernels
from sked_ns.sketches.cameras import ray_aabb

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


NERFACC_EPS = 1e-6
"""nerfacc's traversal starts each grid segment at t_min + eps, so its cell exits fall eps early."""


def calc_dt(t: Tensor, step: float, cone_angle: float) -> Tensor:
    """nerfacc's `_calc_dt`: the step at distance t, clamp(t cone_angle, step, 1e10)."""
    return (t * cone_angle).clamp(min=step, max=1e10)


def step_starts(t0: Tensor, count: int, step: float, cone_angle: float) -> Tensor:
    """t_k for k = 0..count per ray, stepping t_{k+1} = t_k + calc_dt(t_k)."""
    k = torch.arange(count + 1, device=t0.device, dtype=t0.dtype)
    return t_after(t0[:, None], k, step, cone_angle)


def t_after(t0: Tensor, k: Tensor, step: float, cone_angle: float) -> Tensor:
    """t_k after k steps from t0 (broadcast): linear until cone_angle t reaches the step, geometric after."""
    linear = t0 + k * step
    if cone_angle <= 0:
        return linear
    k_switch = torch.ceil(((step / cone_angle - t0) / step).clamp_min(0))
    t_switch = t0 + k_switch * step
    return torch.where(k < k_switch, linear, t_switch * (1 + cone_angle) ** (k - k_switch).clamp_min(0))


def steps_before(t0: Tensor, t_exit: Tensor, step: float, cone_angle: float) -> Tensor:
    """How many steps from t0 have their midpoint before t_exit (nerfacc's walk through an occupied cell)."""
    linear = torch.ceil((t_exit - t0) / step - 0.5).clamp_min(0)
    if cone_angle <= 0:
        return linear
    k_switch = torch.ceil(((step / cone_angle - t0) / step).clamp_min(0))
    t_switch = t0 + k_switch * step
    # Past the switch each midpoint is t_k (1 + cone_angle / 2).
    geometric = k_switch + torch.ceil(
        torch.log((t_exit / (1 + cone_angle / 2)).clamp_min(1e-30) / t_switch.clamp_min(1e-30)) / math.log1p(cone_angle)
    ).clamp_min(0)
    return torch.where(linear <= k_switch, linear, geometric)


def skip_to(t: Tensor, t_exit: Tensor, step: float, cone_angle: float) -> Tensor:
    """nerfacc's walk through empty space: a fixed step, taken from t, until a midpoint passes t_exit."""
    dt = calc_dt(t, step, cone_angle)
    return t + torch.ceil((t_exit - t) / dt - 0.5).clamp_min(0) * dt


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


def level_segments(rays_o: Tensor, rays_d: Tensor, aabbs: Tensor, nears: Tensor, fars: Tensor):
    """nerfacc's order of traversal: per ray, the stretches between its sorted box crossings, each
    with the finest level holding it, clipped to [near, far]. Returns (level, t_min, t_max, valid), [rays, 2L-1]."""
    n_levels = len(aabbs)
    entries, exits = zip(*(ray_aabb(rays_o, rays_d, aabb) for aabb in aabbs))
    entry, exit_ = torch.stack(entries, -1), torch.stack(exits, -1)
    hits = (entry <= exit_) & (exit_ > 0)
    inf = torch.full_like(entry, math.inf)
    t_sorted, order = torch.sort(torch.cat([torch.where(hits, entry, inf), torch.where(hits, exit_, inf)], -1), -1)
    here, after = order[:, :-1], order[:, 1:]
    hit_here, hit_after = hits.gather(1, here % n_levels), hits.gather(1, after % n_levels)
    entering, next_entering = here < n_levels, after < n_levels
    # Entering level l: the stretch is l's; leaving it: the stretch belongs to the next box we leave.
    level = torch.where(entering, here % n_levels, after % n_levels)
    valid = hit_here & (entering | (~next_entering & hit_after))
    t_min = torch.maximum(t_sorted[:, :-1], nears[:, None])
    t_max = torch.minimum(t_sorted[:, 1:], fars[:, None])
    return level, t_min, t_max, valid & (t_min < t_max)


START, CROSS, END = 0, 1, 2
"""Kinds of traversal events: a stretch starts, the ray crosses a cell wall, a stretch ends."""


def traversal_events(binaries: Tensor, aabbs: Tensor, rays_o: Tensor, rays_d: Tensor, nears: Tensor,
                     fars: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Per ray, sorted: event distances, kinds, and whether the cell from each event to the next is on."""
    resolution = torch.tensor(binaries.shape[1:], device=rays_o.device)
    level, t_min, t_max, valid = level_segments(rays_o, rays_d, aabbs, nears, fars)
    low, high = aabbs[level][..., :3], aabbs[level][..., 3:]  # [rays, stretches, 3]
    size = (high - low) / resolution
    # Cell walls strictly inside each stretch, per axis: indices m of planes low + m size.
    u0 = (rays_o[:, None] + rays_d[:, None] * torch.where(valid, t_min, 0)[..., None] - low) / size
    u1 = (rays_o[:, None] + rays_d[:, None] * torch.where(valid, t_max, 0)[..., None] - low) / size
    first = torch.floor(torch.minimum(u0, u1)) + 1
    count = torch.where(valid[..., None], torch.ceil(torch.maximum(u0, u1)) - first, 0).clamp_min(0)
    width = int(count.max()) if count.numel() else 0
    m = first[..., None] + torch.arange(width, device=rays_o.device, dtype=rays_o.dtype)
    walls = (low[..., None] + m * size[..., None] - rays_o[:, None, :, None]) / rays_d[:, None, :, None]
    walls = (walls - NERFACC_EPS).clamp(t_min[..., None, None], t_max[..., None, None])
    walls = torch.where(torch.arange(width, device=rays_o.device) < count[..., None], walls, math.inf)
    n_rays, n_stretches = level.shape
    inf = torch.full_like(t_min, math.inf)
    times = torch.cat([torch.where(valid, t_min, inf)[..., None], walls.reshape(n_rays, n_stretches, -1),
                       torch.where(valid, t_max, inf)[..., None]], -1)
    kinds = torch.full(times.shape, CROSS, device=rays_o.device)
    kinds[..., 0], kinds[..., -1] = START, END
    levels = level[..., None].expand(times.shape)
    # Stretches follow each other along the ray: a stable sort keeps one's END before the next's START.
    times, order = torch.sort(times.reshape(n_rays, -1), stable=True, dim=-1)
    events = max(int(torch.isfinite(times).sum(1).max()), 1) if n_rays else 1  # the rest is padding
    times, order = times[:, :events], order[:, :events]
    kinds, levels = kinds.reshape(n_rays, -1).gather(1, order), levels.reshape(n_rays, -1).gather(1, order)
    # The cell between two events: looked up at its midpoint, in its stretch's level.
    mids = (times[:, :-1] + times[:, 1:]) / 2
    points = rays_o[:, None] + rays_d[:, None] * torch.nan_to_num(mids, posinf=0.0)[..., None]
    box = aabbs[levels[:, :-1]]
    cell = ((points - box[..., :3]) / (box[..., 3:] - box[..., :3]) * resolution).floor().long()
    cell = cell.clamp(torch.zeros_like(resolution), resolution - 1)
    on = binaries[levels[:, :-1], cell[..., 0], cell[..., 1], cell[..., 2]]
    return times, kinds, on


def march_grid(binaries: Tensor, aabbs: Tensor, rays_o: Tensor, rays_d: Tensor, nears: Tensor, fars: Tensor,
               step: float, cone_angle: float = 0.0) -> Tuple[Tensor, Tensor, Tensor]:
    """Packed samples (ray_indices, t_starts, t_ends), sorted by ray then distance, as nerfacc's
    `traverse_grids` makes them: steps from the near plane, of calc_dt(t) through occupied cells
    and of a fixed calc_dt (taken on entering) through empty ones; kept where the midpoint is in an
    occupied cell."""
    out_rays, out_starts, out_ends = [], [], []
    # Rays in chunks: the events of a chunk are [rays, (2 levels - 1) (3 resolution + 2)].
    per_ray = (2 * len(aabbs) - 1) * (int(sum(binaries.shape[1:])) + 2)
    chunk = max(1, MAX_CANDIDATES // per_ray)
    for begin in range(0, len(rays_o), chunk):
        rays = slice(begin, begin + chunk)
        ray_ids, starts, ends = _march_chunk(binaries, aabbs, rays_o[rays], rays_d[rays], nears[rays], fars[rays],
                                             step, cone_angle)
        out_rays.append(ray_ids + begin)
        out_starts.append(starts)
        out_ends.append(ends)
    if not out_rays:
        empty = rays_o.new_zeros(0)
        return empty.long(), empty, empty
    return torch.cat(out_rays), torch.cat(out_starts), torch.cat(out_ends)


def _march_chunk(binaries, aabbs, rays_o, rays_d, nears, fars, step, cone_angle):
    times, kinds, on = traversal_events(binaries, aabbs, rays_o, rays_d, nears, fars)
    n_rays, n_cells = on.shape
    t_last = nears.clone()
    continuous = torch.zeros(n_rays, dtype=torch.bool, device=rays_o.device)
    first_t = torch.zeros_like(on, dtype=times.dtype)
    counts = torch.zeros_like(on, dtype=times.dtype)
    for j in range(n_cells):  # one cell per ray at a time: each cell's steps depend on where the last ended
        cell = (kinds[:, j] != END) & torch.isfinite(times[:, j + 1])
        t_exit = times[:, j + 1]
        # A new stretch after empty space: walk from t_last to its start.
        walk = cell & (kinds[:, j] == START) & ~continuous
        t_last = torch.where(walk, skip_to(t_last, times[:, j], step, cone_angle), t_last)
        empty, full = cell & ~on[:, j], cell & on[:, j]
        t_last = torch.where(empty, skip_to(t_last, t_exit, step, cone_angle), t_last)
        count = torch.where(full, steps_before(t_last, t_exit, step, cone_angle), torch.zeros_like(t_last))
        first_t[:, j], counts[:, j] = t_last, count
        t_last = torch.where(count > 0, t_after(t_last, count, step, cone_angle), t_last)
        continuous = (continuous & ~empty) | (count > 0)
    keep = counts > 0
    ray_ids = torch.arange(n_rays, device=rays_o.device)[:, None].expand_as(keep)[keep]
    first_t, counts = first_t[keep], counts[keep].long()
    width = int(counts.max()) if len(counts) else 0
    t = step_starts(first_t, width, step, cone_angle)
    valid = torch.arange(width, device=t.device) < counts[:, None]
    return ray_ids[:, None].expand_as(valid)[valid], t[:, :-1][valid], t[:, 1:][valid]


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


def marcher_rtol(cone_angle: float) -> float:
    """The relative tolerance at which two float32 marchers' samples match (`sample_agreement`).

    With fixed steps the kernels drift by a few ulps per step. With a cone angle the steps grow geometrically over
    hundreds of steps, and nerfacc's kernel (which adds each step to t in float32) and the torch marcher (which
    takes powers of 1 + cone_angle in float32) round that sequence differently: their t drift apart by more than
    1e-4 of t on long rays, though the samples and their counts are the same.
    """
    return 1e-3 if cone_angle > 0 else 1e-4


def sample_agreement(reference: Tuple[Tensor, Tensor, Tensor], other: Tuple[Tensor, Tensor, Tensor],
                     rtol: float = 1e-4) -> dict:
    """How far two marchers' packed samples (ray_indices, t_starts, t_ends) agree, sample by sample.

    A sample is matched when the other set has one on the same ray whose start and end are both
    within rtol * t (float32 kernels drift by a few ulps per step); counts alone would hide shifts.
    """
    def matched(a, b) -> Tuple[Tensor, Tensor]:
        rays_a, starts_a, ends_a = (x.double().cpu() for x in a)
        rays_b, starts_b, ends_b = (x.double().cpu() for x in b)
        if len(starts_b) == 0:
            return torch.zeros(len(starts_a), dtype=torch.bool), torch.full((len(starts_a),), math.inf)
        span = float(torch.cat([starts_a, starts_b]).abs().max()) * 4 + 1
        key_a, key_b = rays_a * span + starts_a, rays_b * span + starts_b  # sorted by ray, then start
        index = torch.searchsorted(key_b, key_a).clamp(1, len(key_b) - 1)
        best = torch.full((len(starts_a),), math.inf, dtype=torch.float64)
        for candidate in (index - 1, index, (index + 1).clamp_max(len(key_b) - 1)):
            gap = torch.maximum((starts_b[candidate] - starts_a).abs(), (ends_b[candidate] - ends_a).abs())
            best = torch.where(rays_b[candidate] == rays_a, torch.minimum(best, gap), best)
        return best <= rtol * ends_a.abs() + 1e-7, best

    ours, gap = matched(reference, other)
    theirs, _ = matched(other, reference)
    return {
        "matched_reference": float(ours.float().mean()) if len(ours) else 1.0,
        "matched_other": float(theirs.float().mean()) if len(theirs) else 1.0,
        "max_matched_difference": float(gap[ours].max()) if ours.any() else 0.0,
    }


GRID_CHANGES = ("changed_cells", "changed_occs", "changed_binaries")
"""A local edit's occupancy grid as saved: the cells where it differs from its frozen base's grid."""


@torch.no_grad()
def grid_changes(grid: nerfacc.OccGridEstimator, base: nerfacc.OccGridEstimator) -> dict:
    """The cells where `grid` differs from `base` (same layout): flat indices as `occs` counts them, their
    occupancies and their bits."""
    occs, binaries = grid.occs, grid.binaries.reshape(-1)
    changed = ((occs != base.occs) | (binaries != base.binaries.reshape(-1))).nonzero()[:, 0]
    return dict(zip(GRID_CHANGES, (changed.int(), occs[changed], binaries[changed])))


@torch.no_grad()
def grid_with_changes(base: nerfacc.OccGridEstimator, changes: dict) -> Tuple[Tensor, Tensor]:
    """(occs, binaries) of `base` with the saved changes (`grid_changes`) written over it."""
    occs, binaries = base.occs.clone(), base.binaries.clone().reshape(-1)
    cells = changes["changed_cells"].to(occs.device).long()
    occs[cells] = changes["changed_occs"].to(occs)
    binaries[cells] = changes["changed_binaries"].to(binaries)
    return occs, binaries.reshape(base.binaries.shape)
