"""The local NeRF edit's field (local_field.LocalField): the base's own networks moved over the edit's box."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.fields.nerfacto_field import NerfactoField

from sked_ns.models.nerf.density_grid import LOG_SCALE_BOUND, MISSED_OPACITY, PROPOSAL_RATE, AddedMassGrid, HullProposal
from sked_ns.models.nerf.local_field import LocalField, box_grid_shape, splits_grid_and_mlp

LOW, HIGH = np.array([-0.3, -0.3, -0.3]), np.array([0.3, 0.3, 0.3])
SHAPE = {"num_levels": 4, "min_res": 2, "max_res": 32, "log2_hashmap_size": 12, "features_per_level": 2}
DELTA = 0.07  # the step the edit's losses turn density into occupancy at (preservation_delta's default)


def _field(seed: int = 0) -> NerfactoField:
    torch.manual_seed(seed)
    field = NerfactoField(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), num_images=3, num_levels=4,
                          base_res=4, max_res=32, log2_hashmap_size=12, implementation="torch",
                          spatial_distortion=SceneContraction(order=float("inf")))
    with torch.no_grad():  # a trained grid's features, not nerfstudio's +-1e-4 start
        field.mlp_base.model[0].hash_table.uniform_(-1.0, 1.0)
    return field.requires_grad_(False)


def _local(field: NerfactoField) -> LocalField:
    local = LocalField(LOW, HIGH, SHAPE, field)
    local.take_base_networks(field)
    return local


def _samples(count: int = 2048, seed: int = 1) -> RaySamples:
    generator = torch.Generator().manual_seed(seed)
    origins = torch.rand(count, 3, generator=generator) * 1.6 - 0.8  # about a third in the box
    directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1)
    frustums = Frustums(origins=origins, directions=directions, starts=torch.zeros(count, 1),
                        ends=torch.full((count, 1), 1e-3), pixel_area=torch.ones(count, 1))
    return RaySamples(frustums=frustums, camera_indices=torch.randint(0, 3, (count, 1), generator=generator))


@pytest.mark.parametrize("training", [True, False])
def test_the_base_outputs_it_gives_beside_its_own_are_the_bases_bit_for_bit(training):
    field = _field().train(training)
    local, samples = _local(field), _samples()
    with torch.no_grad():
        for parameter in local.parameters():  # the edit moved: the base's outputs must not move with it
            parameter.add_(0.3 * torch.randn(parameter.shape, generator=torch.Generator().manual_seed(3)))
    outputs, inside, base = local(field, samples, with_base=True)
    truth = field(samples)
    for key in (FieldHeadNames.DENSITY, FieldHeadNames.RGB):
        assert torch.equal(base[key], truth[key]), key
        assert not base[key].requires_grad
        assert not torch.equal(outputs[key][inside[..., 0]], truth[key][inside[..., 0]]), key


@pytest.mark.parametrize("training", [True, False])
def test_the_local_field_starts_as_the_base_bit_for_bit(training):
    field = _field().train(training)
    local, samples = _local(field), _samples()
    outputs, inside, _ = local(field, samples)
    base = field(samples)
    assert inside.any() and (~inside).any()
    for key in (FieldHeadNames.DENSITY, FieldHeadNames.RGB):
        assert torch.equal(outputs[key], base[key]), key


def test_its_grid_of_changes_acts_inside_the_box_alone():
    field = _field()
    local, samples = _local(field), _samples()
    with torch.no_grad():
        local.encoding.hash_table.uniform_(-1.0, 1.0)
    outputs, inside, _ = local(field, samples)
    base = field(samples)
    outside = ~inside[:, 0]
    assert torch.equal(outputs[FieldHeadNames.DENSITY][outside], base[FieldHeadNames.DENSITY][outside])
    assert not torch.equal(outputs[FieldHeadNames.DENSITY][~outside], base[FieldHeadNames.DENSITY][~outside])
    # Gradients reach the grid of changes and the copies, never the base.
    outputs[FieldHeadNames.DENSITY].sum().backward()
    assert local.encoding.hash_table.grad.any() and local.density_mlp.layers[0].weight.grad.any()
    assert all(parameter.grad is None for parameter in field.parameters())


def _fit(local: LocalField, field: NerfactoField, target: float, steps: int) -> torch.Tensor:
    # The trainer's groups: the grid at the hash grids' rate, the MLP copies at the fields' (engine/presets.py).
    grid = list(local.encoding.parameters())
    mlps = [p for p in local.parameters() if all(p is not g for g in grid)]
    optimiser = torch.optim.Adam([{"params": grid, "lr": 1e-1}, {"params": mlps, "lr": 1e-2}], eps=1e-15)
    points = torch.rand(512, 3, generator=torch.Generator().manual_seed(3)) * 0.5 - 0.25  # all inside
    wanted = -np.expm1(-target * DELTA)
    for _ in range(steps):
        density = local.density(field, points)[0]
        loss = ((-torch.expm1(-density * DELTA) - wanted) ** 2).mean()  # L_pres-like squashed opacity at delta
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        return -torch.expm1(-local.density(field, points)[0] * DELTA)


def test_the_local_field_adds_mass_in_empty_space_and_carves_what_the_base_holds():
    field = _field()
    with torch.no_grad():  # an empty base (density e^-8) and a solid one (e^4)
        field.mlp_base.model[1].layers[-1].bias[0] = -8.0
    assert float(_fit(_local(field), field, 0.0, 0).max()) < 0.01
    assert float(_fit(_local(field), field, 60.0, 30).median()) > 0.9, "empty space filled"
    with torch.no_grad():
        field.mlp_base.model[1].layers[-1].bias[0] = 4.0
    assert float(_fit(_local(field), field, 60.0, 0).min()) > 0.9
    assert float(_fit(_local(field), field, 0.0, 30).median()) < 0.1, "the base's mass carved away"


@pytest.mark.parametrize("scale", [1e2, 1e4, 1e8])
def test_a_runaway_grid_of_changes_gives_finite_density_and_gradients(scale):
    field = _field()
    local, samples = _local(field), _samples(256)
    with torch.no_grad():
        local.encoding.hash_table.uniform_(-scale, scale)
    outputs, _, _ = local(field, samples)
    (outputs[FieldHeadNames.DENSITY].sum() + outputs[FieldHeadNames.RGB].sum()).backward()
    assert outputs[FieldHeadNames.DENSITY].isfinite().all() and outputs[FieldHeadNames.RGB].isfinite().all()
    assert all(p.grad.isfinite().all() for p in local.parameters() if p.grad is not None)


def test_a_fused_grid_and_mlp_cannot_be_read_apart():
    assert splits_grid_and_mlp(_field())
    fused = SimpleNamespace(mlp_base=SimpleNamespace(model=torch.nn.Linear(3, 16)), mlp_head=_field().mlp_head)
    assert not splits_grid_and_mlp(fused)  # tiny-cuda-nn's NetworkWithInputEncoding is one module
    assert not splits_grid_and_mlp(SimpleNamespace())


@pytest.mark.parametrize("box_share", [1.0, 0.25, 0.01])
def test_the_coarsest_level_is_as_coarse_over_the_box_as_the_bases(box_share):
    base = _field().mlp_base
    extent = 4.0
    shape = box_grid_shape(base, extent, np.full(3, box_share * extent))
    assert shape["min_res"] == max(2, round(base.min_res * box_share)) or shape["min_res"] == shape["max_res"]
    assert shape["min_res"] <= shape["max_res"] and shape["num_levels"] == base.num_levels


def test_the_added_mass_grid_is_zero_until_the_edit_adds_mass_and_only_in_its_box():
    low, high = torch.tensor(LOW, dtype=torch.float32), torch.tensor(HIGH, dtype=torch.float32)
    grid = AddedMassGrid(low, high, 8)
    points = torch.rand(8192, 3, generator=torch.Generator().manual_seed(5)) * 0.8 - 0.4  # some outside the box
    grid.refresh(lambda p: torch.zeros(len(p), 1), version=0)
    assert torch.equal(grid(points), torch.zeros(len(points), 1)), "a fresh edit samples as its base, exactly"
    corner = lambda p: ((p > 0.1).all(dim=-1, keepdim=True)).float()  # noqa: E731
    # Mass twice and half as opaque over a lattice step as its share of the largest opacity a ray may miss.
    step = float((high - low).max()) / 16
    per_step = -math.log1p(-MISSED_OPACITY) * step / float((high - low).norm())
    for density, on in ((2.0 * per_step / step, True), (0.5 * per_step / step, False)):
        grid.refresh(lambda p: density * corner(p), version=1)
        value = grid(points)
        in_box = ((points >= low) & (points <= high)).all(dim=-1)
        assert (~in_box).any() and torch.equal(value[~in_box], torch.zeros_like(value[~in_box]))
        near = value[in_box & (points > 0.2).all(dim=-1)]
        assert len(near) and bool((near == 1.0).all()) == on
        far = value[in_box & (points < 0.0).all(dim=-1)]
        assert len(far) and torch.equal(far, torch.zeros_like(far))


def test_the_hull_proposal_starts_at_one_and_stays_finite_however_far_it_runs():
    low, high = torch.tensor([-0.3, -0.3, -0.3]), torch.tensor([0.3, 0.3, 0.3])
    proposal = HullProposal(low, high, 8)
    points = torch.rand(4096, 3, generator=torch.Generator().manual_seed(2)) * 2.0 - 1.0  # inside and outside the box
    assert torch.equal(proposal(points), torch.ones(4096, 1))  # the hull's density as set: samples as before
    proposal(points[:64]).sum().backward()
    assert proposal.log_scale.grad.any()  # a loss on the sampler's density reaches the grid
    for runaway in (1e30, -1e30):
        with torch.no_grad():
            proposal.log_scale.fill_(runaway)
        value = proposal(points)
        assert torch.isfinite(value).all() and value.min() > 0
        assert torch.allclose(value, torch.full_like(value, float(np.exp(np.sign(runaway) * LOG_SCALE_BOUND))), rtol=1e-5)


def test_the_hull_proposal_reads_its_grid_at_its_rate_and_an_edit_saved_without_one_as_it_was_saved():
    low, high = torch.tensor([-0.3, -0.3, -0.3]), torch.tensor([0.3, 0.3, 0.3])
    points = torch.rand(512, 3, generator=torch.Generator().manual_seed(3)) * 0.6 - 0.3
    proposal = HullProposal(low, high, 4)
    with torch.no_grad():
        proposal.log_scale.fill_(0.25)
    expected = float(np.exp(0.25 * PROPOSAL_RATE))
    assert torch.allclose(proposal(points), torch.full((512, 1), expected), rtol=1e-5)
    # A new edit's checkpoint carries its rate; one saved before the rate (0.10) reads its grid as s itself.
    reloaded = HullProposal(low, high, 4, rate=1.0)
    reloaded.load_state_dict(proposal.state_dict())
    assert torch.equal(reloaded(points), proposal(points))
    outer = torch.nn.ModuleDict({"hull_proposal": HullProposal(low, high, 4), "other": torch.nn.Linear(1, 1)})
    outer.load_state_dict({"other.weight": torch.ones(1, 1)}, strict=False)  # a state without it keeps its rate
    assert float(outer["hull_proposal"].rate) == PROPOSAL_RATE
    saved_without = {"log_scale": proposal.log_scale.detach().clone()}
    old = HullProposal(low, high, 4)
    old.load_state_dict(saved_without)
    assert float(old.rate) == 1.0
    assert torch.allclose(old(points), torch.full((512, 1), float(np.exp(0.25))), rtol=1e-5)
