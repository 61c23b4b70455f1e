"""Gradient-checkpointed field chunks (models/nerf/chunked.py) give the plain evaluation's outputs and gradients."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding

from sked_ns.models.nerf.chunked import chunked

RTOL = 1e-5
"""Chunks change only the batch sizes of the same float32 operations: a parameter's gradient is summed over the
samples in another order, so an element that cancels to far below its tensor's others moves by ulps of those."""


def assert_close(got: torch.Tensor, expected: torch.Tensor) -> None:
    """Within RTOL of each element, or of the tensor's largest element (the magnitude its sums carry)."""
    torch.testing.assert_close(got, expected, rtol=RTOL, atol=RTOL * float(expected.abs().max()) + 1e-30)


class ModalField(torch.nn.Module):
    """A hash grid and an MLP whose output depends on its mode (as nerfacto's appearance embedding does)."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.grid = HashEncoding(num_levels=4, min_res=4, max_res=32, log2_hashmap_size=10, implementation="torch")
        self.mlp = torch.nn.Sequential(torch.nn.Linear(self.grid.get_out_dim(), 16), torch.nn.ReLU(),
                                       torch.nn.Linear(16, 4))
        self.bias = torch.nn.Parameter(torch.tensor([0.5, -0.5]))

    def forward(self, positions: torch.Tensor, times=None) -> dict:
        features = self.mlp(self.grid(positions.reshape(-1, 3))).reshape(*positions.shape[:-1], 4)
        shift = self.bias[0] if self.training else self.bias[1]
        return {"density": torch.nn.functional.softplus(features[..., :1] + shift), "rgb": features[..., 1:].sigmoid(),
                "normals": None}


def _gradients(field: ModalField, evaluate, positions: torch.Tensor, grad_out: dict) -> list:
    field.zero_grad()
    field.train(False)  # as SKED renders random views: the average appearance, then the mode restored
    outputs = evaluate(positions)
    field.train(True)
    loss = sum((outputs[key] * grad_out[key]).sum() for key in ("density", "rgb"))
    loss.backward()
    return [outputs["density"].detach(), outputs["rgb"].detach()] + [p.grad.clone() for p in field.parameters()] + [
        field.bias.grad.clone()]


@pytest.mark.parametrize("shape", [(37, 5), (200,)])
@pytest.mark.parametrize("chunk", [1, 5, 64, 10**9])
def test_chunked_evaluation_matches_the_plain_one_at_every_chunk_size(shape, chunk):
    field = ModalField()
    generator = torch.Generator().manual_seed(1)
    positions = torch.rand(*shape, 3, generator=generator)
    grad_out = {"density": torch.randn(*shape, 1, generator=generator), "rgb": torch.randn(*shape, 3, generator=generator)}
    plain = _gradients(field, field, positions, grad_out)
    pieces = _gradients(field, chunked(field, chunk, [field]), positions, grad_out)
    for expected, got in zip(plain, pieces):
        assert_close(got, expected)


def test_the_backward_re_run_sees_the_mode_of_the_first_run():
    field = ModalField()
    positions = torch.rand(64, 4, 3, generator=torch.Generator().manual_seed(2))
    grad_out = {"density": torch.ones(64, 4, 1), "rgb": torch.zeros(64, 4, 3)}
    forgetful = _gradients(field, chunked(field, 16, []), positions, grad_out)  # modes not declared
    plain = _gradients(field, field, positions, grad_out)
    remembered = _gradients(field, chunked(field, 16, [field]), positions, grad_out)
    # The bias of the first run's mode (eval: bias[1]) gets the gradient; a re-run in training mode would give it
    # to bias[0] instead.
    assert plain[-1][1] != 0 and plain[-1][0] == 0
    assert_close(remembered[-1], plain[-1])
    assert not torch.allclose(forgetful[-1], plain[-1])


def test_chunks_hold_only_their_outputs_until_the_backward_pass():
    """What a checkpointed chunk keeps for the backward pass: its inputs and outputs, not the hash grid's activations."""
    field = ModalField()
    positions = torch.rand(4096, 3, generator=torch.Generator().manual_seed(3))
    held = {}
    for name, evaluate in (("plain", field), ("chunked", chunked(field, 512, [field]))):
        saved = []
        with torch.autograd.graph.saved_tensors_hooks(lambda t: (saved.append(t.numel() * t.element_size()), t)[1],
                                                      lambda t: t):
            outputs = evaluate(positions)
        held[name] = sum(saved)
        outputs["density"].sum().backward()
    assert held["chunked"] < held["plain"] / 10


def test_plain_chunks_without_autograd_and_none_at_chunk_0():
    calls = []

    def function(positions, times=None):
        calls.append(torch.is_grad_enabled())
        return positions.sum(-1, keepdim=True)

    positions = torch.rand(10, 3, requires_grad=True)
    chunked(function, 0)(positions)
    assert calls == [True]  # one call: no chunks
    with torch.no_grad():
        out = chunked(function, 4)(positions)
    assert calls[1:] == [False] * 3  # 10 rows in plain chunks of 4: bounded transients, nothing kept
    torch.testing.assert_close(out, function(positions))
    chunked(function, lambda: 5)(positions)
    assert len(calls) == 4 + 1 + 2


def _edit_gradients(pipeline, chunk: int) -> dict:
    """Every trainable parameter's gradient after one SKED step's losses (the same data and sampler noise)."""
    model = pipeline.model
    model.config.field_chunk = chunk
    pipeline.prepare_guidance()
    model.zero_grad(set_to_none=True)
    data = pipeline.datamanager.next_sked(3, photo_rays=model.photo_anchor_acts())
    torch.manual_seed(0)
    _, losses, _ = model.get_sked_loss_dict(data, 3)
    sum(losses.values()).backward()
    return {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("base", ["scene", "ngp_scene"])
def test_a_chunked_sked_step_has_the_unchunked_gradients(base, request, tmp_path):
    """The whole step (random view, sketch views, photo rays, L_pres against the base) at the chunk sizes' extremes:
    at most one ray per chunk (16 samples: a proposal stage's ray is one row, the tiny field's 32 samples per ray
    two chunks) and all samples in one chunk, against no checkpointing. (One sample per chunk: the tests above.)"""
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.engine.trainer import resolve_edit

    scene = request.getfixturevalue(base)
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=10,
                         guidance_resolution=8, silhouette_resolution=8)
    config.pipeline.model.lambda_new_mass = 1.0  # every loss of the step takes part
    resolve_edit(config)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    pipeline.train()
    plain = _edit_gradients(pipeline, 0)
    assert plain and any(bool(g.abs().sum() > 0) for g in plain.values())
    for chunk in (16, 10**9):
        got = _edit_gradients(pipeline, chunk)
        assert got.keys() == plain.keys()
        for name, expected in plain.items():
            # 1e-3 of the largest entry: small chunks run the MLPs' matrix products at other batch sizes, and
            # float rounding in a density is amplified through the compositing's exponentials; a chunk missed or
            # re-run in another mode is off by the gradient's own size.
            scale = float(expected.abs().max())
            error = float((got[name] - expected).abs().max())
            assert error <= 1e-3 * scale + 1e-8, f"{name} at chunk {chunk}: off by {error:.3g} (largest {scale:.3g})"
