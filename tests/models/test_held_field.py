"""Kept content held exactly on NeRF bases (held_field.py): samples with w above keep_threshold are the base's."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames

from sked_ns.engine.edit_run import edit_config
from sked_ns.engine.trainer import resolve_edit
from sked_ns.evaluation.render import render_at, render_base_at
from sked_ns.models.nerf.held_field import held_field_outputs
from sked_ns.sketches.sketch_set import sketch_view_at


def _samples(positions: torch.Tensor) -> RaySamples:
    shape = positions.shape[:-1]
    frustums = Frustums(origins=positions, directions=torch.nn.functional.normalize(positions + 3.0, dim=-1),
                        starts=torch.zeros(*shape, 1), ends=torch.ones(*shape, 1), pixel_area=torch.ones(*shape, 1))
    return RaySamples(frustums=frustums, camera_indices=torch.zeros(*shape, 1, dtype=torch.long))


class _ToyField(torch.nn.Module):
    """A field of positions only, as nerfstudio's fields: RaySamples of any batch shape -> dict of tensors."""

    def __init__(self, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Tanh(), torch.nn.Linear(16, 4))

    def forward(self, samples: RaySamples):
        out = self.net(samples.frustums.get_positions())
        return {FieldHeadNames.DENSITY: torch.nn.functional.softplus(out[..., :1]),
                FieldHeadNames.RGB: torch.sigmoid(out[..., 1:])}


@pytest.mark.parametrize("kept_share", [0.0, 0.3, 1.0])
def test_held_outputs_equal_a_plain_composite_in_values_and_gradients(kept_share):
    edit, base = _ToyField(0), _ToyField(1).requires_grad_(False)
    samples = _samples(torch.randn(7, 5, 3))
    kept = torch.rand(7, 5, generator=torch.Generator().manual_seed(2)) < kept_share
    outputs, base_outputs = held_field_outputs(edit, base, samples, kept)
    # The plain reference: both fields everywhere, the base's where kept.
    reference = {key: torch.where(kept[..., None], base(samples)[key], value) for key, value in edit(samples).items()}
    for key, value in reference.items():
        assert torch.equal(outputs[key], value), key
        assert torch.equal(base_outputs[key], base(samples)[key]), key
    loss = sum((value * torch.arange(1.0, 1 + value.shape[-1])).sum() for value in outputs.values())
    gradients = torch.autograd.grad(loss, list(edit.parameters()), allow_unused=True)
    reference_loss = sum((value * torch.arange(1.0, 1 + value.shape[-1])).sum() for value in reference.values())
    expected = torch.autograd.grad(reference_loss, list(edit.parameters()), allow_unused=True)
    for got, want in zip(gradients, expected):
        want = torch.zeros_like(got) if want is None else want
        assert got is not None and torch.allclose(got, want, atol=1e-6)  # all kept: zero, but still a graph


def test_nothing_held_when_kept_is_none():
    edit, base = _ToyField(0), _ToyField(1).requires_grad_(False)
    samples = _samples(torch.randn(4, 3, 3))
    outputs, _ = held_field_outputs(edit, base, samples, None)
    assert torch.equal(outputs[FieldHeadNames.RGB], edit(samples)[FieldHeadNames.RGB])


def _moved_model(scene, tmp_path, keep_threshold: float):
    """An edit model whose editable field (its local residual, or its copy of the field and proposals) all moved, as
    hash-grid collisions move them."""
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=5)
    config.pipeline.model.keep_threshold = keep_threshold
    if keep_threshold >= 1:  # the paper's model: a whole field held softly (a local residual fades where w -> 1)
        config.pipeline.model.nerf_edit_field = "full-copy"
    resolve_edit(config)
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    model.update_to_step(10**6)  # past the edit-box warm-up
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for module in (model.field, getattr(model, "proposal_networks", torch.nn.Identity()),
                       model.local_field or torch.nn.Identity()):
            for parameter in module.parameters():
                parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    return model.eval()


def _rays(model, view, resolution: int):
    camera = sketch_view_at(view, resolution)[0]
    return model._collide(camera.generate_rays(camera_indices=0, keep_shape=True).flatten())


@pytest.mark.slow
@pytest.mark.parametrize("base, keep_threshold", [("scene", 0.99), ("scene", 1.0), ("ngp_scene", 0.99)])
def test_kept_space_renders_the_base_however_the_editable_field_moved(request, tmp_path, base, keep_threshold):
    model = _moved_model(request.getfixturevalue(base), tmp_path, keep_threshold)
    if hasattr(model, "occupancy_grid"):  # the base's cells only: the sampler as the base's, the field under test
        model.occupancy_grid.binaries.copy_(model.frozen_base.occupancy_grid.binaries)
    view = model.sketch_set.views[0]
    edit, base = render_at(model, view, 24), render_base_at(model, view, 24)
    same = (edit["rgb"] == base["rgb"]).all(dim=-1).flatten()
    away = model.photo_rays_kept(_rays(model, view, 24))  # rays whose every point has w above 0.99
    assert away.float().mean() > 0.5 and not away.all()
    if keep_threshold < 1:
        assert bool(same[away].all()), f"{int((~same[away]).sum())} pixels of kept space moved"
        assert not bool(same[~away].all()), "the editable region is held too"
    else:  # the paper's soft hold: a moved field moves kept content until L_pres pulls it back
        assert float(same[away].float().mean()) < 0.1


def test_kept_samples_carry_the_base_outputs_and_only_the_others_a_gradient(scene, tmp_path):
    model = _moved_model(scene, tmp_path, 0.99).train()
    outputs, samples, field_outputs = model._render(_rays(model, model.sketch_set.views[1], 16))
    base_outputs = outputs["_base_field_outputs"]
    kept = model.preservation_weight(samples.frustums.get_positions())[..., 0] > 0.99
    assert kept.any() and (~kept).any()
    for key in (FieldHeadNames.DENSITY, FieldHeadNames.RGB):
        assert torch.equal(field_outputs[key][kept], base_outputs[key][kept].to(field_outputs[key].dtype)), key
        assert not torch.equal(field_outputs[key][~kept], base_outputs[key][~kept]), key
    parameters = [p for p in model.parameters() if p.requires_grad]  # the local residual's, or the field's
    loss = lambda mask: (field_outputs[FieldHeadNames.DENSITY][mask].sum()  # noqa: E731
                         + field_outputs[FieldHeadNames.RGB][mask].sum())
    kept_gradients = torch.autograd.grad(loss(kept), parameters, retain_graph=True, allow_unused=True)
    assert all(g is None or not g.any() for g in kept_gradients), "a kept sample trains the field"
    edit_gradients = torch.autograd.grad(loss(~kept), parameters, allow_unused=True)
    assert any(g is not None and g.any() for g in edit_gradients)


@pytest.mark.parametrize("keep_threshold, acts", [(0.99, False), (0.999, True), (1.0, True)])
def test_the_photo_anchor_runs_only_where_its_rays_are_not_all_held(scene, tmp_path, keep_threshold, acts):
    # Its rays have w above photo_threshold (0.99) everywhere: at keep_threshold 0.99 each is the base's exactly.
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=1)
    config.pipeline.model.keep_threshold = keep_threshold
    resolve_edit(config)
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    assert model.photo_anchor_acts() is acts
