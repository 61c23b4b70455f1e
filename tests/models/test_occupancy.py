"""The torch occupancy-grid marcher and packed rendering against plain per-ray loops."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from sked_ns.models.nerf.occupancy import (
    PortableOccGridEstimator,
    grid_changes,
    grid_with_changes,
    march_grid,
    marcher_rtol,
    packed_exclusive_transmittance,
    render_weights,
    sample_agreement,
)

DATA = Path(__file__).resolve().parents[1] / "data"


def _grid(rng: np.random.Generator, resolution=(6, 5, 4), levels=2, fill=0.3) -> PortableOccGridEstimator:
    grid = PortableOccGridEstimator(roi_aabb=[-1.0, -0.5, -1.0, 1.0, 1.5, 0.5], resolution=list(resolution), levels=levels)
    grid.binaries = torch.from_numpy(rng.random(grid.binaries.shape) < fill)
    return grid


def _nerfacc_walk(grid, origin, direction, near, far, step, cone_angle, eps=1e-6):
    """nerfacc 0.5.2's traverse_grids_kernel (cuda/csrc/grid.cu) for one ray, transcribed line by line."""
    aabbs, res, binaries = grid.aabbs.numpy().astype(np.float64), grid.resolution.numpy(), grid.binaries.numpy()
    n_levels = len(aabbs)

    def calc_dt(t):
        return min(max(t * cone_angle, step), 1e10)

    inverse = 1.0 / direction
    t_mins, t_maxs, hits = [], [], []
    for box in aabbs:  # ray_aabb_intersect (near -inf, far inf, misses at inf)
        t_a, t_b = (box[:3] - origin) * inverse, (box[3:] - origin) * inverse
        low, high = np.minimum(t_a, t_b).max(), np.maximum(t_a, t_b).min()
        hit = low <= high and high > 0
        t_mins.append(low if hit else np.inf)
        t_maxs.append(high if hit else np.inf)
        hits.append(hit)
    order = np.argsort(t_mins + t_maxs, kind="stable")
    t_sorted = np.array(t_mins + t_maxs)[order]
    samples, t_last, continuous = [], near, False
    for i in range(2 * n_levels - 1):
        level = order[i] % n_levels
        if not hits[level]:
            continue
        if order[i] >= n_levels:  # leaving a box: the stretch is the next box's, if we are inside it
            if order[i + 1] < n_levels or not hits[order[i + 1] % n_levels]:
                continue
            level = order[i + 1] % n_levels
        t_min, t_max = max(t_sorted[i], near), min(t_sorted[i + 1], far)
        if t_min >= t_max:
            continue
        if not continuous:
            dt = calc_dt(t_last)
            while t_last + dt * 0.5 < t_min:
                t_last += dt
        box = aabbs[level]
        voxel = (box[3:] - box[:3]) / res
        start, end = origin + direction * (t_min + eps), origin + direction * (t_max - eps)
        current = np.clip(((start - box[:3]) / (box[3:] - box[:3]) * res).astype(int), 0, res - 1)
        final = np.clip(((end - box[:3]) / (box[3:] - box[:3]) * res).astype(int), 0, res - 1)
        step_index = np.sign(direction).astype(int)
        tdist = (box[:3] + (current + (direction > 0)) * voxel - start) * inverse + t_min
        delta = voxel * inverse * step_index
        overflow = final + step_index
        for _ in range(10_000):
            t_traverse = min(tdist.min(), t_max)
            if not binaries[level][tuple(current)]:
                dt = calc_dt(t_last)
                while t_last + dt * 0.5 < t_traverse:
                    t_last += dt
                continuous = False
            else:
                while True:
                    dt = calc_dt(t_last)
                    if t_last + dt * 0.5 >= t_traverse:
                        break
                    samples.append((t_last, t_last + dt))
                    continuous, t_last = True, t_last + dt
                    if t_last >= t_traverse:
                        break
            axis = 0 if tdist[0] < tdist[1] and tdist[0] < tdist[2] else (1 if tdist[1] < tdist[2] else 2)
            current[axis] += step_index[axis]
            tdist[axis] += delta[axis]
            if current[axis] == overflow[axis]:
                break
    return samples


@pytest.mark.parametrize("step, cone_angle", [(0.07, 0.0), (0.005, 0.004), (0.02, 0.05)])
def test_march_grid_steps_as_nerfacc(rng, step, cone_angle):
    """Same samples as nerfacc's kernel: from the near plane (not the box), cone-angle steps, fixed steps over empty cells."""
    grid = _grid(rng)
    n = 40
    origins = rng.uniform(-3, 3, size=(n, 3))
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    nears, fars = rng.uniform(0, 0.5, size=n), rng.uniform(2, 8, size=n)
    rays, starts, ends = march_grid(
        grid.binaries, grid.aabbs.double(), torch.from_numpy(origins), torch.from_numpy(directions),
        torch.from_numpy(nears), torch.from_numpy(fars), step, cone_angle,
    )
    assert torch.all(rays[1:] >= rays[:-1]), "samples are packed ray by ray"
    total = 0
    for i in range(n):
        expected = _nerfacc_walk(grid, origins[i], directions[i], nears[i], fars[i], step, cone_angle)
        ours = list(zip(starts[rays == i].tolist(), ends[rays == i].tolist()))
        assert len(ours) == len(expected), f"ray {i}"
        if expected:
            np.testing.assert_allclose(np.array(ours), np.array(expected), rtol=1e-9, atol=1e-9)
        total += len(expected)
    assert total > 50  # the rays really cross occupied cells
    if cone_angle > 0:
        assert (ends - starts).max() > 1.5 * step, "steps grow with distance"


def test_march_grid_with_a_small_candidate_budget(rng, monkeypatch):
    """Rays processed in chunks give the same samples."""
    import sked_ns.models.nerf.occupancy as occupancy

    grid = _grid(rng)
    origins = torch.from_numpy(rng.uniform(-3, 3, size=(30, 3)))
    directions = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(30, 3))), dim=-1)
    nears, fars = torch.zeros(30, dtype=torch.float64), torch.full((30,), 9.0, dtype=torch.float64)
    whole = march_grid(grid.binaries, grid.aabbs.double(), origins, directions, nears, fars, 0.05)
    monkeypatch.setattr(occupancy, "MAX_CANDIDATES", 50)
    chunked = march_grid(grid.binaries, grid.aabbs.double(), origins, directions, nears, fars, 0.05)
    for a, b in zip(whole, chunked):
        assert torch.equal(a, b)


def _packed(rng, n_rays=7):
    counts = rng.integers(0, 6, size=n_rays)
    rays = torch.from_numpy(np.repeat(np.arange(n_rays), counts))
    starts = torch.from_numpy(np.concatenate([np.sort(rng.uniform(0, 3, size=c)) for c in counts]))
    ends = starts + torch.from_numpy(rng.uniform(0.01, 0.2, size=len(starts)))
    sigmas = torch.from_numpy(rng.uniform(0, 20, size=len(starts)))
    return rays, starts, ends, sigmas, n_rays


def _reference_weights(rays, starts, ends, sigmas, n_rays):
    weights = []
    for i in range(n_rays):
        transmittance = torch.ones((), dtype=sigmas.dtype)
        for s, e, sigma in zip(starts[rays == i], ends[rays == i], sigmas[rays == i]):
            alpha = 1 - torch.exp(-sigma * (e - s))
            weights.append(transmittance * alpha)
            transmittance = transmittance * (1 - alpha)
    return torch.stack(weights)


def test_render_weights_and_gradients_match_a_per_ray_loop(rng):
    rays, starts, ends, sigmas, n_rays = _packed(rng)
    ours_sigmas = sigmas.clone().requires_grad_(True)
    reference_sigmas = sigmas.clone().requires_grad_(True)
    ours = render_weights(starts, ends, ours_sigmas, rays, n_rays)
    reference = _reference_weights(rays, starts, ends, reference_sigmas, n_rays)
    torch.testing.assert_close(ours, reference, rtol=1e-10, atol=1e-12)
    target = torch.from_numpy(rng.uniform(size=len(sigmas)))
    (ours * target).sum().backward()
    (reference * target).sum().backward()
    torch.testing.assert_close(ours_sigmas.grad, reference_sigmas.grad, rtol=1e-8, atol=1e-10)


def test_packed_transmittance_is_finite_for_extreme_densities():
    rays = torch.tensor([0, 0, 0, 1, 1])
    optical_depth = torch.tensor([0.0, float("inf"), 1e30, 1e-30, 0.0])
    transmittance = packed_exclusive_transmittance(optical_depth, rays, 2)
    assert torch.equal(transmittance, torch.tensor([1.0, 1.0, 0.0, 1.0, math.exp(-1e-30)]))
    weights = render_weights(torch.zeros(5), torch.ones(5), optical_depth, rays, 2)
    assert torch.isfinite(weights).all() and weights.sum() <= 2 + 1e-6


def test_visibility_culling_follows_nerfacc_rule(rng):
    """With a density function, samples behind an opaque one or with tiny alpha are dropped."""
    grid = _grid(rng, fill=1.0, levels=1)
    grid.occs.fill_(1.0)  # mean occupancy high, so alpha_thre applies as given
    origins = torch.tensor([[-3.0, 0.5, -0.25], [-3.0, 0.2, -0.25]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])

    def sigma_fn(t_starts, t_ends, ray_indices):
        # Ray 0: a wall at x > 0 (t > 3); ray 1: almost empty everywhere.
        x = origins[ray_indices, 0] + (t_starts + t_ends) / 2
        return torch.where((ray_indices == 0) & (x > 0), 1e4, 1e-3)

    rays, starts, ends = grid.sampling(origins, directions, sigma_fn=sigma_fn, render_step_size=0.1, alpha_thre=0.01)
    all_rays, all_starts, _ = grid.sampling(origins, directions, render_step_size=0.1)
    assert (all_rays == 1).any() and not (rays == 1).any(), "alpha below alpha_thre everywhere"
    x_kept = -3.0 + starts[rays == 0]
    assert x_kept.max() < 0.1, "nothing behind the first opaque sample survives"
    assert (rays == 0).sum() < (all_rays == 0).sum()


def test_sample_agreement_sees_shifts_not_only_counts():
    rays = torch.tensor([0, 0, 1])
    starts, ends = torch.tensor([1.0, 1.1, 2.0]), torch.tensor([1.1, 1.2, 2.1])
    same = sample_agreement((rays, starts, ends), (rays, starts + 1e-6, ends))
    assert same["matched_reference"] == same["matched_other"] == 1.0 and same["max_matched_difference"] < 2e-6
    shifted = sample_agreement((rays, starts, ends), (rays, starts + 0.01, ends + 0.01))
    assert shifted["matched_reference"] == shifted["matched_other"] == 0.0, "same counts, other positions"
    extra = sample_agreement((rays, starts, ends), (torch.tensor([0, 0, 1, 1]), torch.tensor([1.0, 1.1, 2.0, 2.1]),
                                                    torch.tensor([1.1, 1.2, 2.1, 2.2])))
    assert extra["matched_reference"] == 1.0 and extra["matched_other"] == 0.75


def test_torch_marcher_agrees_with_recorded_nerfacc_cuda_samples():
    """nerfacc's CUDA kernel's own samples (tests/data/nerfacc_cuda_march.npz: the CUDA test's setup, cone angle
    0.004, recorded on a GPU) against the torch marcher on the CPU: the same samples per ray, within the float32
    drift of cone-angle steps."""
    recorded = np.load(DATA / "nerfacc_cuda_march.npz")
    shape = tuple(recorded["binaries_shape"])
    binaries = torch.from_numpy(np.unpackbits(recorded["binaries"])[: int(np.prod(shape))].reshape(shape).astype(bool))
    origins, directions = torch.from_numpy(recorded["origins"]), torch.from_numpy(recorded["directions"])
    n, cone_angle = len(origins), float(recorded["cone_angle"])
    ours = march_grid(binaries, torch.from_numpy(recorded["aabbs"]), origins, directions,
                      torch.full((n,), float(recorded["near"])), torch.full((n,), 1e10),
                      float(recorded["render_step_size"]), cone_angle)
    cuda = (torch.from_numpy(recorded["rays"].astype(np.int64)), torch.from_numpy(recorded["starts"]),
            torch.from_numpy(recorded["ends"]))
    agreement = sample_agreement(ours, cuda, rtol=marcher_rtol(cone_angle))
    assert agreement["matched_reference"] > 0.995 and agreement["matched_other"] > 0.995, agreement
    counts = torch.bincount(ours[0], minlength=n), torch.bincount(cuda[0], minlength=n)
    assert (counts[0] != counts[1]).float().mean() < 0.02, "a sample more or less on only a few rays"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="nerfacc's kernels need CUDA")
@pytest.mark.parametrize("cone_angle", [0.0, 0.004])
def test_torch_path_agrees_with_nerfacc_on_cuda(rng, cone_angle):
    grid = _grid(rng, resolution=(32, 32, 32), levels=2).cuda()
    origins = torch.from_numpy(rng.uniform(-3, 3, size=(512, 3))).float().cuda()
    directions = torch.nn.functional.normalize(torch.randn(512, 3, device="cuda"), dim=-1)
    options = dict(render_step_size=0.002, near_plane=0.05, cone_angle=cone_angle)
    nerfacc_samples = grid.sampling(origins, directions, **options)
    torch_samples = grid.sampling(origins.cpu(), directions.cpu(), **options)
    # Same rules: the same samples, up to float32 rounding (a few near cell walls may differ).
    agreement = sample_agreement(torch_samples, nerfacc_samples, rtol=marcher_rtol(cone_angle))
    assert agreement["matched_reference"] > 0.995 and agreement["matched_other"] > 0.995, agreement
    rays, starts, ends, sigmas, n_rays = _packed(rng)
    on_gpu = render_weights(starts.float().cuda(), ends.float().cuda(), sigmas.float().cuda(), rays.cuda(), n_rays)
    torch.testing.assert_close(on_gpu.cpu(), render_weights(starts.float(), ends.float(), sigmas.float(), rays, n_rays))


def test_a_grid_saved_as_its_changes_is_rebuilt_bit_for_bit_over_its_base(rng):
    base = _grid(rng)
    base.occs = torch.from_numpy(rng.random(base.occs.shape).astype(np.float32))
    edited = _grid(rng)
    edited.occs, edited.binaries = base.occs.clone(), base.binaries.clone()
    cells = torch.tensor([0, 7, 100, 200])
    edited.occs[cells[:3]] *= 0.5  # three occupancies move, one of them and one more cell flip their bit
    flat = edited.binaries.view(-1)
    flat[cells[2:]] = ~flat[cells[2:]]
    changes = grid_changes(edited, base)
    assert changes["changed_cells"].tolist() == cells.tolist(), "the changed cells and only those"
    assert changes["changed_cells"].dtype == torch.int32
    occs, binaries = grid_with_changes(base, changes)
    assert torch.equal(occs, edited.occs) and torch.equal(binaries, edited.binaries)
    assert binaries.shape == base.binaries.shape and torch.equal(base.binaries.view(-1)[cells[:2]], flat[cells[:2]])
