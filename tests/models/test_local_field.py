"""The local NeRF edit (local_field.py, local_edit.py): a residual on the frozen base over the editable box only."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames

from sked_ns.engine.edit_run import edit_config
from sked_ns.engine.trainer import resolve_edit
from sked_ns.evaluation.render import render_at, render_base_at
from sked_ns.models.nerf.density_grid import PROPOSAL_RATE
from sked_ns.models.nerf.local_field import MAX_LOG2_TABLE, MIN_LOG2_TABLE, LocalField, LocalResidual, local_grid_shape

ONE = torch.ones(())  # 1 - w: fully editable
SHAPE = {"num_levels": 4, "min_res": 4, "max_res": 32, "log2_hashmap_size": 12, "features_per_level": 2}
DELTA = 0.07  # the step the edit's losses turn density into occupancy at (preservation_delta's default)
SCALE = 1.0 / math.sqrt(3.0)  # s: a density per diagonal of the unit box, as the edit sets it


def _residual(seed: int = 0) -> LocalResidual:
    torch.manual_seed(seed)
    return LocalResidual(np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5]), SHAPE, density_scale=SCALE)


def _points(count: int = 4096, seed: int = 1) -> torch.Tensor:
    return torch.rand(count, 3, generator=torch.Generator().manual_seed(seed)) * 2.0 - 1.0  # half of them in the box


def _moved(residual: LocalResidual, scale: float = 0.5) -> LocalResidual:
    with torch.no_grad():
        for parameter in residual.parameters():
            parameter.add_(scale * torch.randn_like(parameter))
    return residual


def test_the_residual_starts_as_the_base_bit_for_bit():
    residual, points = _residual(), _points()
    density = torch.rand(len(points), 1) * 50.0
    rgb = torch.rand(len(points), 3)
    inside, raw = residual(points)
    assert inside.any() and (~inside).any()
    assert torch.equal(residual.density(density, inside, raw, ONE), density)
    assert torch.equal(residual.colour(rgb, inside, raw, ONE), rgb)
    half = density.half()  # a field evaluated under autocast
    assert torch.equal(residual.density(half, inside, raw, ONE), half)


def test_outside_the_box_the_edit_is_the_base_however_the_residual_moved():
    residual, points = _moved(_residual()), _points()
    density, rgb = torch.rand(len(points), 1) * 50.0, torch.rand(len(points), 3)
    inside, raw = residual(points)
    edited_density, edited_rgb = residual.density(density, inside, raw, ONE), residual.colour(rgb, inside, raw, ONE)
    outside = ~inside[:, 0]
    assert torch.equal(edited_density[outside], density[outside])
    assert torch.equal(edited_rgb[outside], rgb[outside])
    assert not torch.equal(edited_density[~outside], density[~outside]), "the residual moved inside the box"
    # Where w = 1 (nothing editable) the moved residual changes nothing either.
    held = torch.zeros(len(points), 1)
    assert torch.equal(residual.density(density, inside, raw, held), density)
    assert torch.equal(residual.colour(rgb, inside, raw, held), rgb)
    # ... and no gradient reaches the residual from outside the box.
    loss = edited_density[outside].sum() + edited_rgb[outside].sum()
    gradients = torch.autograd.grad(loss, list(residual.parameters()), allow_unused=True)
    assert all(g is None or not g.any() for g in gradients)


def _fit(residual: LocalResidual, base: torch.Tensor, target: torch.Tensor, points: torch.Tensor, steps: int):
    # The trainer's group: grid and head at the hash grids' rate (field_edit._hash_grid_groups).
    optimiser = torch.optim.Adam(residual.parameters(), lr=5e-2, betas=(0.9, 0.99), eps=1e-15)
    for _ in range(steps):
        inside, raw = residual(points)
        density = residual.density(base, inside, raw, ONE)
        # L_pres-like squashed opacity at delta, as the edit's density losses see it
        opacity = -torch.expm1(-density * DELTA)
        loss = ((opacity - (-torch.expm1(-target * DELTA))) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        inside, raw = residual(points)
        return residual.density(base, inside, raw, ONE)


def test_the_residual_adds_mass_in_empty_space_and_carves_what_the_base_holds():
    points = torch.rand(512, 3, generator=torch.Generator().manual_seed(3)) - 0.5  # all inside
    empty, solid = torch.zeros(len(points), 1), torch.full((len(points), 1), 60.0)
    added = _fit(_residual(), empty, solid, points, steps=30)
    assert float((-torch.expm1(-added * DELTA)).median()) > 0.9, "empty space filled"
    carved = _fit(_residual(), solid, empty, points, steps=30)
    assert float((-torch.expm1(-carved * DELTA)).median()) < 0.1, "the base's mass carved away"
    assert (carved >= 0).all() and (added >= 0).all()


def test_g_adds_s_times_exp_g_minus_one():
    residual, points = _residual(), _points()
    inside, raw = residual(points)
    raw = raw.detach().clone()
    raw[..., 1] = 1.0
    added = residual.density(torch.zeros(len(points), 1), inside, raw, ONE)[inside[:, 0]]
    torch.testing.assert_close(added, torch.full_like(added, SCALE * math.expm1(1.0)))


def test_the_edited_density_stays_finite_in_half_precision():
    residual, points = _residual(), _points()
    inside, raw = residual(points)
    raw = torch.full_like(raw, 50.0)  # s exp(50) is far past fp16's largest value
    density = residual.density(torch.rand(len(points), 1).half() * 50.0, inside, raw, ONE)
    assert density.dtype == torch.float16 and density.isfinite().all()


@pytest.mark.parametrize("g", [15.0, 100.0, 1e4])
def test_a_runaway_g_gives_finite_density_and_gradient_where_the_edit_is_held(g):
    residual, points = _residual(), _points(64)
    inside, raw = residual(points)
    raw = torch.full_like(raw, g).requires_grad_(True)  # exp(g) past float32's range for the larger ones
    editable = torch.zeros(len(points), 1)  # w = 1: 0 x exp(g) must not be NaN
    editable[::2] = 1.0
    density = residual.density(torch.rand(len(points), 1) * 50.0, inside, raw, editable)
    density.sum().backward()
    assert density.isfinite().all() and raw.grad.isfinite().all()


def test_carved_space_can_be_filled_again():
    points = torch.rand(256, 3, generator=torch.Generator().manual_seed(4)) - 0.5
    residual, base = _residual(), torch.full((len(points), 1), 5.0)
    carved = _fit(residual, base, torch.zeros_like(base), points, steps=20)
    assert float(carved.median()) < 1.5
    # Carving stops pushing once the density is 0, so the way back is not a climb from wherever it drifted.
    refilled = _fit(residual, base, torch.full_like(base, 60.0), points, steps=60)
    assert float(refilled.median()) > float(base.median())


@pytest.mark.parametrize("box_share", [1.0, 0.5, 0.1, 0.01])
def test_the_grid_follows_the_box(box_share):
    base = HashEncoding(num_levels=16, min_res=16, max_res=2048, log2_hashmap_size=19, implementation="torch")
    base.max_res = 2048  # nerfstudio's MLPWithHashEncoding keeps it; HashEncoding does not
    extent = 2.0
    shape = local_grid_shape(base, extent, np.full(3, box_share * extent))
    # The box's finest cell is at most the base's finest cell scaled by box / scene.
    assert box_share * extent / shape["max_res"] <= (extent / 2048) * box_share * (1 + 1e-9)
    assert MIN_LOG2_TABLE <= shape["log2_hashmap_size"] <= min(MAX_LOG2_TABLE, 19)
    across = 2048 * box_share
    if math.pi * across**2 < 2**MIN_LOG2_TABLE:
        assert shape["log2_hashmap_size"] == MIN_LOG2_TABLE
    small = HashEncoding(num_levels=4, min_res=16, max_res=64, log2_hashmap_size=10, implementation="torch")
    small.max_res = 64
    assert local_grid_shape(small, extent, np.full(3, box_share * extent))["log2_hashmap_size"] == 10  # never above


# ---- on a demo base ----------------------------------------------------------------------------------------------
def _model(scene, tmp_path, representation: str = "local"):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=5)
    config.pipeline.model.nerf_edit_field = representation
    resolve_edit(config)
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    model.update_to_step(10**6)  # past the edit-box warm-up
    if hasattr(model, "occupancy_grid"):  # the base's cells: the sampler as the base's, the field under test
        model.occupancy_grid.binaries.copy_(model.frozen_base.occupancy_grid.binaries)
    return model


@pytest.mark.parametrize("base", ["scene", "ngp_scene"])
def test_a_local_edit_trains_and_saves_only_its_residual(request, tmp_path, base):
    model = _model(request.getfixturevalue(base), tmp_path)
    assert model.local_field is not None
    trainable = {id(p) for group in model.get_param_groups().values() for p in group}
    own = [model.local_field, model.colour_residual] + ([model.hull_proposal] if base == "scene" else [])
    assert trainable == {id(p) for module in own for p in module.parameters()}
    assert getattr(model, "hull_proposal", None) is None or base == "scene"  # nerfacto's samples: proposals
    saved = model.state_dict()
    assert not [key for key in saved if key.startswith(("field.", "proposal_networks."))]
    assert any(key.startswith("local_field.") for key in saved)
    view = model.sketch_set.views[0]
    edit, base_render = render_at(model, view, 24), render_base_at(model, view, 24)
    assert torch.equal(edit["rgb"], base_render["rgb"]), "the edit starts as the base bit for bit"
    # A moved residual moves only what is in the box and not kept.
    with torch.no_grad():
        for parameter in model.local_field.parameters():
            parameter.add_(0.3 * torch.randn(parameter.shape, generator=torch.Generator().manual_seed(0)))
    moved = render_at(model, view, 24)
    same = (moved["rgb"] == base_render["rgb"]).all(dim=-1).flatten()
    camera_rays = model._collide(_view_rays(view, 24))
    away = model.photo_rays_kept(camera_rays)
    assert bool(same[away].all()) and not bool(same.all())
    # Loading the saved state back restores the residual and keeps the base.
    fresh = _model(request.getfixturevalue(base), tmp_path / "again")
    fresh.load_state_dict(model.state_dict())
    assert fresh.local_field is not None
    assert torch.equal(render_at(fresh, view, 24)["rgb"], moved["rgb"])


def _view_rays(view, resolution):
    from sked_ns.sketches.sketch_set import sketch_view_at

    camera = sketch_view_at(view, resolution)[0]
    return camera.generate_rays(camera_indices=0, keep_shape=True).flatten()


def test_gradients_of_a_local_edit_reach_only_its_residual(scene, tmp_path):
    model = _model(scene, tmp_path).train()
    outputs, samples, field_outputs = model._render(model._collide(_view_rays(model.sketch_set.views[1], 16)))
    loss = field_outputs[FieldHeadNames.DENSITY].sum() + field_outputs[FieldHeadNames.RGB].sum()
    loss.backward()
    for name, parameter in model.named_parameters():
        if not name.startswith(("local_field.", "colour_residual.", "hull_proposal.")):  # the edit's own modules
            assert parameter.grad is None, name
    assert any(p.grad is not None and p.grad.any() for p in model.local_field.parameters())


def test_an_edit_saved_as_a_whole_field_loads_as_one(scene, tmp_path):
    full = _model(scene, tmp_path / "full", "full-copy")
    with torch.no_grad():
        for parameter in full.field.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=torch.Generator().manual_seed(1)))
    saved = full.state_dict()
    assert any(key.startswith("field.") for key in saved)
    local = _model(scene, tmp_path / "local")  # a config.yml without the setting reads today's default
    local.load_state_dict(saved)
    assert local.local_field is None and local.config.nerf_edit_field == "full-copy"
    assert any(p.requires_grad for p in local.field.parameters())
    view = local.sketch_set.views[0]
    assert torch.equal(render_at(local, view, 24)["rgb"], render_at(full, view, 24)["rgb"])


def test_a_base_whose_grid_and_mlp_are_fused_gets_a_full_copy(scene, tmp_path, monkeypatch, capsys):
    import sked_ns.models.nerf.field_edit as field_edit

    monkeypatch.setattr(field_edit, "splits_grid_and_mlp", lambda field: False)  # as a tiny-cuda-nn base
    model = _model(scene, tmp_path)
    assert model.local_field is None and model.config.nerf_edit_field == "full-copy"
    assert any(p.requires_grad for p in model.field.parameters())
    assert "fused (tiny-cuda-nn)" in capsys.readouterr().out.replace("\n", " ")


def test_an_edit_saved_as_a_residual_loads_as_one(scene, tmp_path):
    saved_by = _model(scene, tmp_path / "residual")
    saved_by._use_residual()
    _moved(saved_by.local_field, 0.3)
    saved = saved_by.state_dict()
    assert any(key.startswith("local_field.head.") for key in saved)
    model = _model(scene, tmp_path / "field")
    assert type(model.local_field).__name__ == "LocalField"
    model.load_state_dict(saved)
    assert isinstance(model.local_field, LocalResidual)
    view = model.sketch_set.views[0]
    assert torch.equal(render_at(model, view, 24)["rgb"], render_at(saved_by, view, 24)["rgb"])


def test_the_interlevel_loss_teaches_a_local_edit_where_its_new_content_is(scene, tmp_path):
    """nerfacto's interlevel loss trains the hull proposal (density_grid.HullProposal) as it trains proposal networks."""
    model = _model(scene, tmp_path).train()
    assert torch.equal(model.hull_proposal.log_scale, torch.zeros_like(model.hull_proposal.log_scale))
    assert float(model.hull_proposal.rate) == PROPOSAL_RATE  # a fresh edit's, whatever it loaded at set-up
    outputs, _, _ = model._render(model._collide(_view_rays(model.sketch_set.views[0], 16)))
    losses = model._sampling_losses([outputs])
    assert torch.isfinite(losses["interlevel_loss"])
    losses["interlevel_loss"].backward()
    assert model.hull_proposal.log_scale.grad is not None and model.hull_proposal.log_scale.grad.any()


def test_a_local_field_saved_without_hull_proposal_or_colour_residual_loads(scene, tmp_path):
    """0.9 saved neither: they load as fresh ones, which move nothing (the edit renders as it did)."""
    saved_by = _model(scene, tmp_path / "saved")
    _moved(saved_by.local_field, 0.3)
    state = {key: value for key, value in saved_by.state_dict().items()
             if not key.startswith(("hull_proposal.", "colour_residual."))}
    model = _model(scene, tmp_path / "loaded")
    model.load_state_dict(state)
    view = model.sketch_set.views[0]
    assert torch.equal(render_at(model, view, 24)["rgb"], render_at(saved_by, view, 24)["rgb"])


def test_a_base_that_predicts_normals_gets_a_local_field_and_its_normals(tmp_path, monkeypatch):
    """`ns-train nerfacto --pipeline.model.predict-normals True`: the edit is a LocalField, it starts as its base
    bit for bit in colour and normals (the base's field is called for them), and a step's gradient reaches it."""
    from sked_ns.demo import base as demo_base
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.sketches.sketch_set import save_sketch_set

    plain = demo_base.nerfacto_config

    def with_normals(*args, **kwargs):
        config = plain(*args, **kwargs)
        config.pipeline.model.predict_normals = True
        return config

    monkeypatch.setattr(demo_base, "nerfacto_config", with_normals)
    demo_scene.write_demo_dataset(tmp_path / "data")
    run = demo_base.build_demo_base(tmp_path / "data", tmp_path / "runs", steps=30, points_per_step=2048)
    save_sketch_set(demo_scene.demo_sketch_set(size=64), tmp_path / "sketches")
    model = _model({"base": run, "data": tmp_path / "data", "sketches": tmp_path / "sketches"}, tmp_path / "edit")
    assert model.config.predict_normals and isinstance(model.local_field, LocalField)
    view = model.sketch_set.views[0]
    rays = model._collide(_view_rays(view, 16))
    edit, base = model.eval().get_outputs(rays), model.render_base(rays)
    for key in ("rgb", "normals", "pred_normals"):
        assert torch.equal(edit[key], base[key]), key
    model.train()
    outputs, _, field_outputs = model._render(model._collide(_view_rays(view, 16)))
    assert torch.isfinite(outputs["normals"]).all() and torch.isfinite(outputs["pred_normals"]).all()
    (field_outputs[FieldHeadNames.DENSITY].sum() + field_outputs[FieldHeadNames.RGB].sum()).backward()
    assert any(p.grad is not None and p.grad.any() for p in model.local_field.parameters())
