"""The colour residual: zero at the start, never moves what is kept, reaches a colour the head cannot, finite at extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.models.nerf.colour_residual import ColourResidual


def _residual(seed: int = 0) -> ColourResidual:
    torch.manual_seed(seed)
    return ColourResidual(np.zeros(3), np.ones(3))


def test_a_new_residual_leaves_every_colour_bit_for_bit():
    rgb, positions, weight = torch.rand(64, 8, 3), torch.rand(64, 8, 3), torch.rand(64, 8, 1)
    assert torch.equal(_residual().apply(rgb, positions, weight), rgb)


def test_kept_points_keep_the_heads_colour_and_gradient():
    residual = _residual()
    torch.nn.init.normal_(residual.linear.weight, std=5.0)
    rgb = torch.rand(32, 3, requires_grad=True)
    positions = torch.rand(32, 3)
    weight = torch.ones(32, 1)
    weight[:16] = 0.0  # the first half is inside the sketches
    out = residual.apply(rgb, positions, weight)
    assert torch.equal(out[16:], rgb[16:])
    assert (out[:16] - rgb[:16]).abs().max() > 1e-2
    out[16:].sum().backward()
    assert torch.equal(rgb.grad[16:], torch.ones(16, 3))
    assert residual.linear.weight.grad is None or not residual.linear.weight.grad.any()


def test_it_reaches_a_colour_the_head_does_not_make():
    # The head says grey everywhere; 200 Adam steps on the residual alone make the editable points red.
    residual = _residual()
    optimiser = torch.optim.Adam(residual.parameters(), lr=5e-2)
    positions = torch.rand(256, 3)
    grey, red = torch.full((256, 3), 0.5), torch.tensor([0.85, 0.15, 0.15]).expand(256, 3)
    weight = torch.zeros(256, 1)
    for _ in range(200):
        optimiser.zero_grad()
        (residual.apply(grey, positions, weight) - red).pow(2).mean().backward()
        optimiser.step()
    assert (residual.apply(grey, positions, weight) - red).abs().max() < 0.05


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
@pytest.mark.parametrize("value", [0.0, 1.0])
def test_finite_at_saturated_colours_far_points_and_any_weight(dtype, value):
    residual = _residual()
    torch.nn.init.normal_(residual.linear.weight, std=100.0)
    rgb = torch.full((6, 3), value, dtype=dtype, requires_grad=True)
    positions = torch.tensor([[0.5, 0.5, 0.5], [1e6, -1e6, 0.0], [-5.0, 2.0, 0.5]] * 2)
    weight = torch.tensor([[0.0], [0.5], [1.0]] * 2)
    out = residual.apply(rgb, positions, weight)
    out.float().sum().backward()
    assert out.dtype == dtype and torch.isfinite(out).all() and torch.isfinite(rgb.grad).all()
    assert (out.float() >= -1e-3).all() and (out.float() <= 1 + 1e-3).all()
