"""What a NeRF edit step dispatches: the pieces that used to wait on the device are branch-free and equal to the
masked implementations they replace; the frozen base's proposal densities are read from a grid."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.fields.density_fields import HashMLPDensityField

from sked_ns.models.nerf.colour_residual import LOGIT_EPS, ColourResidual
from sked_ns.models.nerf.density_grid import BaseDensityGrid, density_at_normalised, normalised_positions

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from dispatch_census import DispatchCensus, module_tensors  # noqa: E402


def _masked_residual(residual: ColourResidual, rgb, positions, weight):
    """The residual as it was applied with a boolean mask (a sync and a data-dependent shape per call)."""
    editable = (1.0 - weight.float()).clamp(0.0, 1.0)
    near = editable[..., 0] > 0
    if not bool(near.any()):
        return rgb
    out = rgb.float().clone()
    logit = torch.logit(out[near].clamp(LOGIT_EPS, 1.0 - LOGIT_EPS))
    out[near] = out[near] + (torch.sigmoid(logit + editable[near] * residual(positions[near])) - torch.sigmoid(logit))
    return out.to(rgb.dtype)


@pytest.mark.parametrize("near_share", [0.0, 0.4, 1.0])
def test_branch_free_colour_residual_equals_the_masked_one(near_share):
    torch.manual_seed(0)
    residual = ColourResidual(np.zeros(3), np.ones(3), num_levels=4, max_res=32, log2_hashmap_size=10)
    torch.nn.init.normal_(residual.linear.weight)  # a residual that moves colours
    positions = torch.rand(6, 9, 3) * 1.4 - 0.2
    weight = torch.where(torch.rand(6, 9, 1) < near_share, torch.rand(6, 9, 1) * 0.9, torch.ones(6, 9, 1))
    weight[0, 0] = 0.0  # w = 0 and w = 1 exactly
    colours = torch.rand(6, 9, 3)
    colours[0, :2] = torch.tensor([0.0, 1.0])[:, None]  # saturated colours
    results = []
    for apply in (residual.apply, lambda *a: _masked_residual(residual, *a)):
        rgb = colours.clone().requires_grad_(True)
        residual.zero_grad()
        out = apply(rgb, positions, weight)
        (out * torch.linspace(-1, 1, out.numel()).reshape(out.shape)).sum().backward()
        results.append((out.detach(), rgb.grad, residual.linear.weight.grad, residual.encoding.hash_table.grad))
    (out, rgb_grad, linear_grad, table_grad), reference = results
    far = weight[..., 0] == 1.0
    assert torch.equal(out[far], reference[0][far])  # kept colours bit for bit
    # Near the sketches the residual's matrix products run over another batch: float32 rounding of colours in [0, 1].
    torch.testing.assert_close(out, reference[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(rgb_grad, reference[1], rtol=1e-6, atol=1e-7)
    for got, want in ((linear_grad, reference[2]), (table_grad, reference[3])):
        want = torch.zeros_like(got) if want is None else want
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6 * float(want.abs().max().clamp_min(1.0)))


def test_branch_free_colour_residual_waits_on_nothing():
    residual = ColourResidual(np.zeros(3), np.ones(3), num_levels=4, max_res=32, log2_hashmap_size=10)
    rgb, positions, weight = torch.rand(50, 3), torch.rand(50, 3), torch.rand(50, 1)
    census = DispatchCensus(module_tensors(residual) + [rgb, positions, weight])
    with census:
        residual.apply(rgb, positions, weight)
    assert census.census.syncs == 0, census.census.sync_lines


def _proposal_network(distortion: bool) -> HashMLPDensityField:
    torch.manual_seed(1)
    network = HashMLPDensityField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), num_levels=4, max_res=16,
                                  log2_hashmap_size=10, implementation="torch",
                                  spatial_distortion=SceneContraction(order=float("inf")) if distortion else None)
    with torch.no_grad():
        network.encoding.hash_table.uniform_(-1, 1)
    return network.eval().requires_grad_(False)


@pytest.mark.parametrize("distortion", [True, False])
def test_the_base_density_grid_is_the_network_at_its_points_and_zero_outside(distortion):
    network = _proposal_network(distortion)
    resolution = 16
    grid = BaseDensityGrid(network, resolution)
    # At the cell centres the grid is the network, wherever they are in world space.
    index = torch.randint(0, resolution, (200, 3), generator=torch.Generator().manual_seed(0))
    unit = (index.float() + 0.5) / resolution
    network_density = density_at_normalised(network, unit)
    torch.testing.assert_close(grid.grid[0, 0, index[:, 2], index[:, 1], index[:, 0]][:, None], network_density)
    # World points mapped to the same normalised positions read the same values.
    world = torch.rand(300, 3) * 1.8 - 0.9
    unit_world = normalised_positions(network, world)
    inside = ((unit_world > 0) & (unit_world < 1)).all(-1)
    exact = network.density_fn(world)
    read = grid(world)
    assert read.shape == exact.shape and torch.isfinite(read).all()
    # Between the points: a trilinear blend of the network's values, within the network's own variation.
    scale = float(exact.abs().max())
    assert float((read - exact).abs().max()) <= scale
    if not distortion:
        outside = torch.tensor([[1.5, 0.0, 0.0], [0.0, -3.0, 0.0]])
        assert torch.equal(grid(outside), torch.zeros(2, 1))
    assert inside.any()


def test_the_base_density_grid_is_read_without_a_sync():
    network = _proposal_network(True)
    grid = BaseDensityGrid(network, 8)
    positions = torch.randn(40, 7, 3)
    census = DispatchCensus(module_tensors(grid) + [positions])
    with census:
        grid(positions)
    assert census.census.syncs == 0, census.census.sync_lines
    assert census.census.compute_ops <= 40


def test_the_census_sees_what_would_wait_on_a_gpu():
    """The counter itself: a scalar read, a boolean mask, a host-built tensor, a host copy; none for plain math."""
    x = torch.rand(10)
    cases = {
        "scalar read": lambda: bool(x.any()),
        "boolean-mask index": lambda: x[x > 0.5],
        "host-to-device copy": lambda: x * torch.tensor([2.0] * 10).to(x.device),
        "device-to-host copy": lambda: x.cpu(),
    }
    for kind, case in cases.items():
        census = DispatchCensus([x])
        with census:
            case()
        assert census.census.syncs == 1 and kind in " ".join(census.census.sync_kinds), (kind, census.census)
    census = DispatchCensus([x])
    with census:
        torch.where(x > 0.5, x * 2, x).sum()
    assert census.census.syncs == 0 and census.census.compute_ops == 4


def _step_losses(pipeline, masked: bool):
    """One SKED step's losses and (all but the interlevel loss's) gradients, with the sketch views rendered at the
    masks' pixels or whole; the samplers without jitter, so both see the same samples on the same rays."""
    model = pipeline.model
    pipeline.prepare_guidance()
    model.zero_grad(set_to_none=True)
    data = pipeline.datamanager.next_sked(3, photo_rays=model.photo_anchor_acts())
    if not masked:
        data = {key: value for key, value in data.items() if key not in ("masked_sketch_rays", "sketch_pixels")}
    model.proposal_sampler.eval()
    torch.manual_seed(0)
    _, losses, metrics = model.get_sked_loss_dict(data, 3)
    sum(value for key, value in losses.items() if key != "interlevel_loss").backward()
    gradients = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return {k: v.detach() for k, v in losses.items()}, metrics, gradients


def test_sketch_views_rendered_at_the_masks_pixels_give_the_same_losses_and_gradients(scene, tmp_path):
    """L_sil, L_new's gate and every other term from the masks' pixels alone equal those of the whole views; only
    the interlevel loss changes, by design (it sees the sketch rays under the masks, not all of them)."""
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.engine.trainer import resolve_edit

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=10,
                         guidance_resolution=8, silhouette_resolution=16)
    config.pipeline.model.lambda_new_mass = 1.0  # L_new's gate reads the sketch views too
    resolve_edit(config)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    pipeline.train()
    datamanager = pipeline.datamanager
    assert 0 < len(datamanager.masked_sketch_rays) < len(datamanager.sketch_rays)
    whole = _step_losses(pipeline, masked=False)
    pipeline.model._base_sketch_opacity_cache = None
    masked = _step_losses(pipeline, masked=True)
    for name, value in whole[0].items():
        if name != "interlevel_loss":
            torch.testing.assert_close(masked[0][name], value, rtol=1e-5, atol=1e-7, msg=name)
    assert float(whole[0]["silhouette_loss"]) > 0 and float(whole[0]["new_mass_loss"]) >= 0
    torch.testing.assert_close(masked[1]["sketch_coverage"], whole[1]["sketch_coverage"])
    assert masked[2].keys() == whole[2].keys()
    for name, expected in whole[2].items():
        # The MLPs' matrix products run at other batch sizes: float32 rounding, amplified through compositing.
        scale = float(expected.abs().max())
        assert float((masked[2][name] - expected).abs().max()) <= 1e-4 * scale + 1e-8, name
