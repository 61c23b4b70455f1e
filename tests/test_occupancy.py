"""The torch occupancy-grid marcher and packed rendering against plain per-ray loops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sked_ns.occupancy import PortableOccGridEstimator, march_grid, packed_exclusive_transmittance, render_weights


def _grid(rng: np.random.Generator, resolution=(6, 5, 4), levels=2, fill=0.3) -> PortableOccGridEstimator:
    grid = PortableOccGridEstimator(roi_aabb=[-1.0, -0.5, -1.0, 1.0, 1.5, 0.5], resolution=list(resolution), levels=levels)
    grid.binaries = torch.from_numpy(rng.random(grid.binaries.shape) < fill)
    return grid


def _cell_on(grid, point: np.ndarray) -> bool:
    """nerfacc's rule, one point at a time: the finest level whose box holds the point."""
    for level, box in enumerate(grid.aabbs.numpy().astype(np.float64)):
        unit = (point - box[:3]) / (box[3:] - box[:3])
        if np.all(unit >= 0) and np.all(unit < 1):
            cell = np.minimum((unit * grid.resolution.numpy()).astype(int), grid.resolution.numpy() - 1)
            return bool(grid.binaries[level][tuple(cell)])
    return False


def _reference_march(grid, origin, direction, near, far, step, cone_angle):
    """Walk one ray: t += max(step, cone_angle t); keep steps whose midpoint's cell is on."""
    box = grid.aabbs[-1].numpy().astype(np.float64)
    with np.errstate(divide="ignore"):
        t_a, t_b = (box[:3] - origin) / direction, (box[3:] - origin) / direction
    t0, t1 = max(near, max(np.minimum(t_a, t_b).max(), 0.0)), min(far, np.maximum(t_a, t_b).min())
    samples, t = [], t0
    while t < t1:
        t_next = t + max(step, cone_angle * t)
        if _cell_on(grid, origin + direction * (t + t_next) / 2):
            samples.append((t, t_next))
        t = t_next
    return samples


@pytest.mark.parametrize("cone_angle", [0.0, 0.05])
def test_march_grid_matches_a_per_ray_walk(rng, cone_angle):
    grid = _grid(rng)
    n = 40
    origins = rng.uniform(-3, 3, size=(n, 3))
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    nears, fars = rng.uniform(0, 0.5, size=n), rng.uniform(2, 8, size=n)
    step = 0.07
    rays, starts, ends = march_grid(
        grid.binaries, grid.aabbs.double(), torch.from_numpy(origins), torch.from_numpy(directions),
        torch.from_numpy(nears), torch.from_numpy(fars), step, cone_angle,
    )
    assert torch.all(rays[1:] >= rays[:-1]), "samples are packed ray by ray"
    total = 0
    for i in range(n):
        expected = _reference_march(grid, origins[i], directions[i], nears[i], fars[i], step, cone_angle)
        ours = list(zip(starts[rays == i].tolist(), ends[rays == i].tolist()))
        assert len(ours) == len(expected), f"ray {i}"
        if expected:
            np.testing.assert_allclose(np.array(ours), np.array(expected), rtol=1e-9, atol=1e-9)
        total += len(expected)
    assert total > 50  # the rays really cross occupied cells


def test_march_grid_with_a_small_candidate_budget(rng, monkeypatch):
    """Rays processed in chunks give the same samples."""
    import sked_ns.occupancy as occupancy

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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="nerfacc's kernels need CUDA")
def test_torch_path_agrees_with_nerfacc_on_cuda(rng):
    grid = _grid(rng, resolution=(32, 32, 32), levels=2).cuda()
    origins = torch.from_numpy(rng.uniform(-3, 3, size=(512, 3))).float().cuda()
    directions = torch.nn.functional.normalize(torch.randn(512, 3, device="cuda"), dim=-1)
    nerfacc_samples = grid.sampling(origins, directions, render_step_size=0.01)
    torch_samples = grid.sampling(origins.cpu(), directions.cpu(), render_step_size=0.01)
    # Same grid, same steps: the sample counts agree to within rounding at cell edges.
    assert abs(len(nerfacc_samples[0]) - len(torch_samples[0])) <= 0.02 * len(torch_samples[0])
    rays, starts, ends, sigmas, n_rays = _packed(rng)
    on_gpu = render_weights(starts.float().cuda(), ends.float().cuda(), sigmas.float().cuda(), rays.cuda(), n_rays)
    torch.testing.assert_close(on_gpu.cpu(), render_weights(starts.float(), ends.float(), sigmas.float(), rays, n_rays))
