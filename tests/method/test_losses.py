"""SKED losses: hand-computed values, and finite values and gradients at the extremes."""

from __future__ import annotations

import math

import pytest
import torch

from sked_ns.method.losses import (
    ALPHA_EPS,
    PROBABILITY_EPS,
    REFERENCE_SKETCH_COVERAGE,
    new_mass_loss,
    preservation_loss,
    silhouette_loss,
    sparsity_loss,
)

DELTA = 0.07


def test_preservation_loss_by_hand():
    # Sample 0: base occupied (density 10 > 5), edit alpha = 0.5, colours differ, w = 0.5.
    # Sample 1: base empty, edit density 0 (alpha 0), colours ignored, w = 1.
    density_edit = torch.tensor([[math.log(2) / DELTA], [0.0]])
    density_base = torch.tensor([[10.0], [0.0]])
    rgb_edit = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0]])
    rgb_base = torch.tensor([[0.4, 0.3, 0.7], [0.0, 1.0, 0.0]])
    weight = torch.tensor([[0.5], [1.0]])
    loss = preservation_loss(density_edit, rgb_edit, density_base, rgb_base, weight, delta=DELTA, lambda_colour=5.0)
    p0 = PROBABILITY_EPS + (1 - 2 * PROBABILITY_EPS) * 0.5
    p1 = PROBABILITY_EPS
    expected = (0.5 * (-math.log(p0) + 5.0 * (0.01 + 0.04 + 0.04)) + 1.0 * -math.log(1 - p1)) / 2
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_preservation_loss_is_zero_weighted_on_the_sketch():
    density = torch.rand(8, 1) * 50
    loss = preservation_loss(density, torch.rand(8, 3), torch.rand(8, 1) * 50, torch.rand(8, 3), torch.zeros(8, 1))
    assert loss.item() == 0.0


def test_density_target_keeps_a_soft_base_where_the_occupancy_target_sharpens_it():
    # Base densities either side of the occupancy threshold (5), the edit equal to the base: the paper's target
    # pushes 3 -> 0 and 8 -> inf (a soft shell becomes a hard one); the base's own density is a stationary point.
    density_base = torch.tensor([[0.0], [3.0], [8.0], [200.0]])
    rgb = torch.rand(4, 3)
    gradients = {}
    for target in ("occupancy", "density"):
        density_edit = density_base.clone().requires_grad_(True)
        preservation_loss(density_edit, rgb, density_base, rgb, torch.ones(4, 1), delta=DELTA, target=target).backward()
        gradients[target] = density_edit.grad.squeeze(-1)
    assert gradients["occupancy"][1] > 0 and gradients["occupancy"][2] < 0
    assert gradients["density"].abs().max() < 1e-6
    # And it is a minimum: moving the edit's density either way costs.
    for scale in (0.5, 2.0):
        moved = preservation_loss(density_base * scale, rgb, density_base, rgb, torch.ones(4, 1), delta=DELTA,
                                  target="density")
        assert moved > preservation_loss(density_base, rgb, density_base, rgb, torch.ones(4, 1), delta=DELTA,
                                         target="density")


def test_density_target_gates_colour_by_the_base_alpha():
    # Colour of a faint base sample (sigma 3, alpha 0.19 at delta 0.07) is held, not free as under the threshold.
    args = (torch.full((1, 1), 3.0), torch.zeros(1, 3), torch.full((1, 1), 3.0), torch.ones(1, 3), torch.ones(1, 1))
    soft = preservation_loss(*args, delta=DELTA, target="density") - preservation_loss(
        args[0], args[3], args[2], args[3], args[4], delta=DELTA, target="density")
    p = PROBABILITY_EPS + (1 - 2 * PROBABILITY_EPS) * -math.expm1(-3.0 * DELTA)
    assert soft.item() == pytest.approx(5.0 * p * 3.0, rel=1e-5)
    hard = preservation_loss(*args, delta=DELTA, target="occupancy") - preservation_loss(
        args[0], args[3], args[2], args[3], args[4], delta=DELTA, target="occupancy")
    assert hard.item() == 0.0


def test_preservation_target_names_the_field():
    with pytest.raises(ValueError, match="preservation_target"):
        preservation_loss(torch.zeros(1, 1), torch.zeros(1, 3), torch.zeros(1, 1), torch.zeros(1, 3), torch.ones(1, 1),
                          target="binary")


def test_silhouette_loss_by_hand():
    accumulation = torch.tensor([[[1.0, 0.5], [0.0, 0.25]]])
    masks = torch.tensor([[[1.0, 1.0], [0.0, 1.0]]])
    squash = lambda a: math.log(ALPHA_EPS + (1 - ALPHA_EPS) * a)  # noqa: E731
    expected = -(squash(1.0) + squash(0.5) + squash(0.25)) / 4
    assert silhouette_loss(accumulation, masks).item() == pytest.approx(expected, rel=1e-6)
    assert silhouette_loss(torch.ones(1, 2, 2), torch.ones(1, 2, 2)).item() == 0.0


def test_sparsity_loss_by_hand():
    assert sparsity_loss(torch.full((3, 3), 0.5)).item() == pytest.approx(1.0, rel=1e-6)  # one bit, as the authors'
    p = 0.2  # H = -(p log2 p + (1 - p) log2 (1 - p))
    assert sparsity_loss(torch.full((2,), p)).item() == pytest.approx(-(p * math.log2(p) + (1 - p) * math.log2(1 - p)), rel=1e-6)
    assert sparsity_loss(torch.tensor([0.0, 1.0])).item() < 2e-3


@pytest.mark.parametrize("target", ["occupancy", "density"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
@pytest.mark.parametrize("density_value", [0.0, 1e-6, 5.0, 1e6, math.inf])
def test_preservation_loss_finite_with_gradient(dtype, density_value, target):
    density_value = min(density_value, torch.finfo(dtype).max) if math.isfinite(density_value) else density_value
    density_edit = torch.full((4, 6, 1), density_value, dtype=dtype, requires_grad=True)
    rgb_edit = torch.rand(4, 6, 3, dtype=dtype, requires_grad=True)
    density_base = torch.tensor([0.0, 6e4, 4.9, 5.1, 0.0, 1e3], dtype=dtype).reshape(1, 6, 1).expand(4, 6, 1)
    weight = torch.rand(4, 6, 1, dtype=dtype)
    loss = preservation_loss(density_edit, rgb_edit, density_base, torch.rand(4, 6, 3, dtype=dtype), weight,
                             target=target)
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.isfinite(density_edit.grad).all() and torch.isfinite(rgb_edit.grad).all()


def test_empty_region_still_pulls_density_up():
    # An occupied base sample where the edit is empty must get a push (no dead clamp).
    density_edit = torch.zeros(1, 1, requires_grad=True)
    preservation_loss(density_edit, torch.zeros(1, 3), torch.full((1, 1), 100.0), torch.zeros(1, 3), torch.ones(1, 1)).backward()
    assert density_edit.grad.item() < 0
    accumulation = torch.zeros(1, 4, 4, requires_grad=True)
    silhouette_loss(accumulation, torch.ones(1, 4, 4)).backward()
    assert (accumulation.grad < 0).all() and torch.isfinite(accumulation.grad).all()


def test_sketch_normalised_silhouette_loss_by_hand():
    accumulation = torch.tensor([[[1.0, 0.5], [0.0, 0.25]], [[0.5, 0.5], [0.5, 0.5]]])
    masks = torch.tensor([[[1.0, 1.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 1.0]]])
    squash = lambda a: math.log(ALPHA_EPS + (1 - ALPHA_EPS) * a)  # noqa: E731
    expected = REFERENCE_SKETCH_COVERAGE * -(squash(1.0) + squash(0.5) + squash(0.25) + squash(0.5)) / 4
    assert silhouette_loss(accumulation, masks, "sketch").item() == pytest.approx(expected, rel=1e-6)
    # As the datamanager passes them: the views' pixels concatenated.
    assert silhouette_loss(accumulation.flatten(), masks.flatten(), "sketch").item() == pytest.approx(expected, rel=1e-6)
    with pytest.raises(ValueError, match="normalisation"):
        silhouette_loss(accumulation, masks, "pixels")


def test_sketch_normalisation_pulls_a_small_sketch_as_hard_as_a_large_one():
    # Image normalisation (paper): each sketch ray gets the same push, so a small sketch gets little in total.
    small, large = torch.zeros(1, 10, 10), torch.zeros(1, 10, 10)
    small[0, :1, :2], large[0, :5, :] = 1.0, 1.0
    for normalisation, ratio in (("image", 2 / 50), ("sketch", 1.0)):
        pulls = []
        for mask in (small, large):
            accumulation = torch.full((1, 10, 10), 0.5, requires_grad=True)
            silhouette_loss(accumulation, mask, normalisation).backward()
            pulls.append(-accumulation.grad.sum().item())
        assert pulls[0] / pulls[1] == pytest.approx(ratio, rel=1e-5)


@pytest.mark.parametrize("normalisation", ["image", "sketch"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
@pytest.mark.parametrize("alpha", [0.0, 1.0, 0.5])
@pytest.mark.parametrize("mask_fill", [0.0, 1.0])
def test_silhouette_and_sparsity_finite_at_extremes(dtype, alpha, mask_fill, normalisation):
    accumulation = torch.full((2, 5, 5), alpha, dtype=dtype, requires_grad=True)
    masks = torch.full((2, 5, 5), mask_fill, dtype=dtype)
    total = silhouette_loss(accumulation, masks, normalisation) + sparsity_loss(accumulation)
    total.backward()
    assert torch.isfinite(total) and torch.isfinite(accumulation.grad).all()
    if mask_fill == 0.0:  # empty masks: nothing to fill
        assert silhouette_loss(accumulation, masks, normalisation).item() == 0.0


def test_no_samples_gives_zero():
    empty = torch.zeros(0, 1)
    assert preservation_loss(empty, torch.zeros(0, 3), empty, torch.zeros(0, 3), empty).item() == 0.0


class _FarIsKept:
    """Stands in for a SKED model: w = 1 beyond x = 1 (a wall far behind the sketch), 0 before (the edit)."""

    def preservation_weight(self, positions):
        return (positions[..., :1] > 1.0).float()


def test_a_wall_behind_the_sketch_does_not_fill_it():
    # Two rays, two samples each: near (x = 0.5, editable) and far (x = 2, kept). Ray 0 sees only the opaque wall.
    from sked_ns.models.nerf.field_edit import SkedMixin

    positions = torch.tensor([[[0.5, 0, 0], [2.0, 0, 0]]]).expand(2, 2, 3)
    weights = torch.tensor([[[0.0], [1.0]], [[0.6], [0.4]]], requires_grad=True)
    accumulation = weights.sum(dim=-2)
    editable = SkedMixin.editable_accumulation(_FarIsKept(), positions, weights, accumulation)
    torch.testing.assert_close(editable.detach(), torch.tensor([[0.0], [0.6]]))
    masks = torch.ones(1, 1, 2)
    assert silhouette_loss(accumulation.reshape(1, 1, 2), masks) < 0.3  # the paper's L_sil: nearly satisfied
    assert silhouette_loss(editable.reshape(1, 1, 2), masks) > 4.0  # ours: the empty sketch still asks for mass
    silhouette_loss(editable.reshape(1, 1, 2), masks).backward()
    assert weights.grad[0, 0, 0] < 0 and weights.grad[0, 1, 0] == 0  # pulls the near sample, ignores the wall
    # Packed samples (occupancy grids) give the same.
    packed = SkedMixin.editable_accumulation(_FarIsKept(), positions.reshape(4, 3), weights.detach().reshape(4, 1),
                                             accumulation.detach(), ray_indices=torch.tensor([0, 0, 1, 1]))
    torch.testing.assert_close(packed, editable.detach())


def test_new_mass_loss_by_hand():
    # Sample 0: new mass (edit alpha 0.5 over an empty base), w = 0.25. Sample 1: the base's own mass kept (alpha 0.5
    # in both): nothing added. Sample 2: the edit thinner than the base: nothing added. Sample 3: new mass, kept (w 1).
    half = math.log(2) / DELTA
    density_edit = torch.tensor([[half], [half], [0.0], [half]], requires_grad=True)
    density_base = torch.tensor([[0.0], [half], [half], [0.0]])
    weight = torch.tensor([[0.25], [0.0], [0.5], [1.0]])
    loss = new_mass_loss(density_edit, density_base, weight, DELTA)
    assert loss.item() == pytest.approx(0.75 * 0.5 / (0.75 + 1.0 + 0.5 + 0.0), rel=1e-6)
    loss.backward()
    # Only the added mass near the sketches is pushed down; the base's own mass and kept samples feel nothing.
    assert density_edit.grad[0, 0] > 0 and (density_edit.grad[1:] == 0).all()


def test_new_mass_loss_spares_solid_parts_more_than_haze():
    density = torch.tensor([[2.0], [200.0]], requires_grad=True)  # alpha 0.13 (haze), 1.0 (a solid part)
    new_mass_loss(density, torch.zeros(2, 1), torch.zeros(2, 1), DELTA).backward()
    assert density.grad[0, 0] > 1e3 * density.grad[1, 0] > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
@pytest.mark.parametrize("density_value", [0.0, 1e-6, 5.0, 1e6, math.inf, -1.0])
@pytest.mark.parametrize("weight_value", [0.0, 0.5, 1.0])
def test_new_mass_loss_finite_at_extremes(dtype, density_value, weight_value):
    density_value = min(density_value, torch.finfo(dtype).max) if math.isfinite(density_value) else density_value
    density_edit = torch.full((4, 6, 1), density_value, dtype=dtype, requires_grad=True)
    density_base = torch.tensor([0.0, 6e4, 4.9, 5.1, 0.0, 1e3], dtype=dtype).reshape(1, 6, 1).expand(4, 6, 1)
    loss = new_mass_loss(density_edit, density_base, torch.full((4, 6, 1), weight_value, dtype=dtype), DELTA)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(density_edit.grad).all()
    assert 0.0 <= loss.item() <= 1.0
    if weight_value == 1.0:  # every sample kept: nothing to penalise, and no 0/0
        assert loss.item() == 0.0
    assert new_mass_loss(torch.zeros(0, 1), torch.zeros(0, 1), torch.zeros(0, 1)).item() == 0.0
