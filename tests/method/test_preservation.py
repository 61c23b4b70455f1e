"""Preservation weights: the distance-transform lookup equals brute force, and stays finite."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from conftest import random_blob_mask, random_view
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import exact_distance_one, near_pixel_edge, sketch_distance_one

from sked_ns.method.preservation import (
    SketchDistanceField,
    _sketch_distance,
    check_beta,
    preservation_weight,
    sketch_distance_transform,
)
from sked_ns.sketches.sketch_set import SketchView

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _points(rng, count):
    """Points near the object, far off to the side, and some behind cameras."""
    return np.concatenate([rng.uniform(-1, 1, (count, 3)), rng.uniform(-6, 6, (count // 2, 3))])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), num_views=st.integers(1, 4), width=st.integers(4, 48), height=st.integers(4, 48))
def test_lookup_equals_brute_force(seed, num_views, width, height):
    rng = np.random.default_rng(seed)
    views = [random_view(rng, width + 3 * j, height, f"v{j}") for j in range(num_views)]
    points = _points(rng, 40)
    fast = SketchDistanceField(views).per_view_distance(torch.tensor(points, dtype=torch.float32)).numpy()
    for j, view in enumerate(views):
        for i, point in enumerate(points):
            if near_pixel_edge(point, view):
                continue  # float32 vs float64 may round to the neighbouring pixel
            expected = sketch_distance_one(point, view)
            if math.isinf(expected):
                assert math.isinf(fast[j, i])
            else:
                assert fast[j, i] == pytest.approx(expected, rel=1e-5, abs=1e-6)
                # Outside the image the rule is an upper bound of the true distance.
                assert fast[j, i] >= exact_distance_one(point, view) * (1 - 1e-6) - 1e-6  # float32 rounding


def test_distance_transform_is_exact(rng):
    mask = random_blob_mask(rng, 37, 29, blobs=3)
    rows, cols = np.mgrid[0:29, 0:37]
    mask_rows, mask_cols = np.nonzero(mask)
    brute = np.sqrt((rows[..., None] - mask_rows) ** 2 + (cols[..., None] - mask_cols) ** 2).min(-1)
    np.testing.assert_allclose(sketch_distance_transform(mask), brute, rtol=1e-6)
    assert (sketch_distance_transform(mask)[mask] == 0).all()


def test_behind_every_camera_means_fully_preserved(rng):
    views = [random_view(rng, 16, 16) for _ in range(2)]
    field = SketchDistanceField(views)
    behind = torch.tensor(views[0].camera_to_world[:, 3] + 2.0 * views[0].camera_to_world[:, 2], dtype=torch.float32)
    distance = field.per_view_distance(behind[None])
    assert math.isinf(distance[0, 0])
    weight = field.preservation_weight(behind[None], beta=0.025)
    assert weight.item() == 1.0


def test_mean_over_views(rng):
    views = [random_view(rng, 20, 20) for _ in range(3)]
    field = SketchDistanceField(views)
    points = torch.tensor(rng.uniform(-0.5, 0.5, (50, 3)), dtype=torch.float32)
    torch.testing.assert_close(field.distance(points), field.per_view_distance(points).mean(0))


@pytest.mark.parametrize("device", DEVICES)
def test_any_batch_shape_dtype_and_device(rng, device):
    views = [random_view(rng, 24, 24) for _ in range(2)]
    field = SketchDistanceField(views).to(device)
    points = torch.tensor(rng.uniform(-1, 1, (4, 5, 3)), dtype=torch.float16, device=device)
    weight = field.preservation_weight(points, beta=0.025)
    assert weight.shape == (4, 5) and weight.device.type == device
    reference = field.preservation_weight(points.float().reshape(-1, 3), beta=0.025).reshape(4, 5)
    torch.testing.assert_close(weight, reference)


def test_weight_formula():
    beta = 0.05
    distance = torch.tensor([0.0, beta, 2 * beta])
    expected = 1 - torch.exp(-(distance**2) / (2 * beta**2))
    torch.testing.assert_close(preservation_weight(distance, beta), expected)


@pytest.mark.parametrize("beta", [1e-30, 1e-6, 0.005, 0.025, 1.0, 1e3, 1e30])
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32])
def test_weight_is_finite_and_bounded_at_extremes(beta, dtype):
    distance = torch.tensor([0.0, 1e-8, 1e-3, 0.5, 1.0, 60000.0, math.inf]).to(dtype)
    weight = preservation_weight(distance, beta)
    assert torch.isfinite(weight).all()
    assert ((weight >= 0) & (weight <= 1)).all()
    assert weight[0] == 0.0 and weight[-1] == 1.0
    assert (weight[1:] >= weight[:-1]).all()  # monotone in the distance


@pytest.mark.parametrize("beta", [0.0, -0.1, math.nan, math.inf, "0.1"])
def test_bad_beta_is_refused(beta):
    with pytest.raises(ValueError, match="beta"):
        check_beta(beta)
    with pytest.raises(ValueError, match="beta"):
        preservation_weight(torch.zeros(3), beta)


def test_far_points_stay_finite(rng):
    views = [random_view(rng, 16, 16) for _ in range(2)]
    field = SketchDistanceField(views)
    far = torch.tensor([[1e30, -1e30, 3e20], [1e-30, 0.0, 0.0], [float("nan")] * 3], dtype=torch.float32)
    distance = field.per_view_distance(far)
    assert not torch.isnan(distance).any()
    assert torch.isfinite(field.preservation_weight(far, 0.025)).all()


@pytest.mark.slow
def test_compiled_lookup_equals_eager(rng):
    views = [random_view(rng, 40 + 8 * j, 32, f"v{j}") for j in range(3)]
    points = torch.tensor(_points(rng, 70_000), dtype=torch.float32)  # > one chunk
    eager = SketchDistanceField(views).distance(points)
    # pytest ignores UserWarnings (pyproject): record them, or a silent fallback would compare eager with eager.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        field = SketchDistanceField(views, compile=True)
        compiled = field.distance(points)
    assert not [w for w in caught if "sketch lookup" in str(w.message)], "the compiled lookup fell back to eager"
    assert field._lookup is not _sketch_distance, "the compiled lookup was not used"
    assert torch.equal(torch.isinf(eager), torch.isinf(compiled))
    finite = torch.isfinite(eager)
    torch.testing.assert_close(compiled[finite], eager[finite], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_lookup_is_float32_under_mixed_precision(rng, device):
    """Training runs under autocast; the projection must not drop to half precision (pixels would move)."""
    views = [random_view(rng, 200, 160, f"v{j}") for j in range(2)]
    field = SketchDistanceField(views).to(device)
    points = torch.tensor(_points(rng, 5000), dtype=torch.float32, device=device)
    exact = field.distance(points)
    dtype = torch.float16 if device == "cuda" else torch.bfloat16
    with torch.autocast(device_type=device, dtype=dtype):
        mixed = field.distance(points)
    assert mixed.dtype == torch.float32
    assert torch.equal(torch.isinf(exact), torch.isinf(mixed))
    finite = torch.isfinite(exact)
    torch.testing.assert_close(mixed[finite], exact[finite], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("scale", [1, 2])
def test_a_nerfstudio_ray_through_a_sketch_pixel_has_distance_zero(rng, scale):
    """Ties the projection to nerfstudio's own: rays of the (rescaled) sketch camera hit the mask pixel they came from."""
    from sked_ns.sketches.sketch_set import sketch_view_at

    width, height, (row, col) = 48, 36, (10, 30)
    view = random_view(rng, width, height, "v")
    mask = np.zeros((height, width), bool)
    mask[row : row + scale, col : col + scale] = True  # one pixel of the camera the rays come from
    view = SketchView(mask=mask, camera_to_world=view.camera_to_world, fl_x=view.fl_x, fl_y=view.fl_y, cx=view.cx,
                      cy=view.cy)
    camera, reduced_mask = sketch_view_at(view, max(width, height) // scale)
    r, c = row // scale, col // scale
    assert reduced_mask[r, c] and reduced_mask.sum() == 1
    rays = camera.generate_rays(camera_indices=0, keep_shape=True)
    field = SketchDistanceField([view])
    for dr, dc in [(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)]:
        origin, direction = rays.origins[r + dr, c + dc], rays.directions[r + dr, c + dc]
        points = origin + torch.tensor([[0.5], [1.0], [2.0], [5.0]]) * direction
        distance = field.per_view_distance(points)[0] * width  # pixels
        if (dr, dc) == (0, 0):
            assert (distance == 0).all()
        else:
            assert (distance >= 1 - 1e-4).all()  # a neighbouring pixel (at half size, its rays graze pixel edges)
            if scale == 1:
                torch.testing.assert_close(distance, torch.ones_like(distance), rtol=0, atol=1e-4)
