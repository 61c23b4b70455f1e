"""Edit box: the LP box equals a dense sampling of the frustum intersection; clipped only where the base is bounded;
nerfacc layout."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from nerfacc import OccGridEstimator

from sked_ns.demo.scenes.sphere import orbit_pose
from sked_ns.method.edit_box import (
    EditBox,
    check_view_baselines,
    compute_edit_box,
    content_bounds,
    occupancy_grid_mask,
)
from sked_ns.sketches.cameras import project
from sked_ns.sketches.sketch_set import SketchView


def _cube_view(azimuth, elevation, cube_centre, half, size=64, focal=80.0, name=""):
    """A view whose mask is the projected footprint of a cube's corners' bounding box."""
    pose = orbit_pose(azimuth, elevation, 3.0)
    corners = torch.tensor(
        [[cube_centre[0] + sx * half, cube_centre[1] + sy * half, cube_centre[2] + sz * half]
         for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64
    )
    pixels, _ = project(corners, torch.tensor(pose[None]), torch.tensor([[focal, focal, size / 2, size / 2]], dtype=torch.float64))
    u0, v0 = pixels[0].floor().min(0).values.int().tolist()
    u1, v1 = pixels[0].floor().max(0).values.int().tolist()
    mask = np.zeros((size, size), bool)
    mask[max(v0, 0) : v1 + 1, max(u0, 0) : u1 + 1] = True
    return SketchView(mask=mask, camera_to_world=pose, fl_x=focal, fl_y=focal, cx=size / 2, cy=size / 2, name=name)


def _inside_all_frusta(points, views):
    inside = torch.ones(len(points), dtype=torch.bool)
    for view in views:
        u0, v0, u1, v1 = view.bounding_box()
        pixels, depth = project(points, torch.tensor(view.camera_to_world[None]), torch.tensor(view.intrinsics[None]))
        u, v = pixels[0].unbind(-1)
        inside &= (depth[0] > 1e-3) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
    return inside


@pytest.mark.parametrize("num_views", [2, 3])
def test_box_matches_dense_sampling_of_the_intersection(num_views):
    centre, half = (0.1, -0.2, 0.3), 0.15
    views = [_cube_view(a, e, centre, half) for a, e in [(0, 10), (80, 25), (200, 40)][:num_views]]
    box = compute_edit_box(views)
    assert torch.all(box.contains(torch.tensor([centre])))
    # Dense reference: a fine grid over (and beyond) the box, kept where inside every frustum.
    lo, hi = box.min - 0.05, box.max + 0.05
    axes = [torch.linspace(float(lo[k]), float(hi[k]), 90, dtype=torch.float64) for k in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = grid[_inside_all_frusta(grid, views)]
    spacing = max((hi - lo) / 89)
    np.testing.assert_allclose(inside.min(0).values.numpy(), box.min, atol=1.5 * spacing)
    np.testing.assert_allclose(inside.max(0).values.numpy(), box.max, atol=1.5 * spacing)


def test_every_contour_counts():
    view_a = _cube_view(0, 10, (0, 0, 0), 0.1)
    second = view_a.mask.copy()
    second[2:5, 2:5] = True  # a second stroke far to the top-left
    view_b = SketchView(second, view_a.camera_to_world, view_a.fl_x, view_a.fl_y, view_a.cx, view_a.cy)
    side = _cube_view(90, 10, (0, 0, 0), 0.6)
    assert np.all(compute_edit_box([view_b, side]).size >= compute_edit_box([view_a, side]).size - 1e-9)
    assert compute_edit_box([view_b, side]).size.max() > compute_edit_box([view_a, side]).size.max() + 0.05


def test_disjoint_sketches_are_named():
    left = _cube_view(0, 10, (-0.8, 0, 0), 0.05, name="left.png")
    right = _cube_view(0, 60, (0.8, 0, 0), 0.05, name="right.png")
    with pytest.raises(ValueError, match=r"do not intersect.*left.png and right.png"):
        compute_edit_box([left, right])


def test_the_same_view_twice_is_refused_naming_both_even_with_a_scene_box():
    a = _cube_view(0, 10, (0, 0, 0), 0.1, name="masks/a.png")
    b = SketchView(a.mask, a.camera_to_world + np.array([[0, 0, 0, 0.01]] * 3), a.fl_x, a.fl_y, a.cx, a.cy,
                   name="masks/b.png")
    for scene_box in (None, np.array([[-1.0] * 3, [1.0] * 3])):  # clipped, it ran with a box out to the scene's
        with pytest.raises(ValueError, match=r"same sketch view twice \(masks/a.png and masks/b.png"):
            compute_edit_box([a, b], scene_box=scene_box)
    with pytest.raises(ValueError, match="same sketch view twice"):  # a good third view does not excuse a copy
        compute_edit_box([a, b, _cube_view(90, 10, (0, 0, 0), 0.1)])


def test_near_parallel_views_are_refused_and_narrow_ones_warned():
    scene_box = np.array([[-1.0] * 3, [1.0] * 3])
    near = [_cube_view(0, 10, (0, 0, 0), 0.1, name="a"), _cube_view(3, 10, (0, 0, 0), 0.1, name="b")]
    with pytest.raises(ValueError, match="at most 3.0 degrees apart"):
        compute_edit_box(near, scene_box=scene_box)
    narrow = [near[0], _cube_view(10, 10, (0, 0, 0), 0.1)]
    with pytest.warns(UserWarning, match=r"at most 9\.\d degrees apart"):
        compute_edit_box(narrow, scene_box=scene_box)
    assert check_view_baselines([near[0], _cube_view(60, 10, (0, 0, 0), 0.1)]) == pytest.approx(59.1, abs=1.0)


@pytest.mark.parametrize("resolution, levels", [(16, 1), ([12, 8, 10], 2), (32, 3)])
def test_occupancy_mask_uses_nerfacc_layout(resolution, levels):
    roi = [-1.0, -0.5, -0.8, 1.0, 1.5, 0.6]
    estimator = OccGridEstimator(roi_aabb=roi, resolution=resolution, levels=levels)
    box = EditBox(min=np.array([-0.3, 0.2, -0.1]), max=np.array([0.25, 0.9, 0.05]))
    mask = occupancy_grid_mask(box, roi, resolution, levels)
    assert mask.shape == estimator.binaries.shape and mask.dtype == estimator.binaries.dtype
    # nerfacc's own cell positions: x = aabb_min + (grid_coords + offset) / res * extent.
    res = estimator.resolution.double()
    for level in range(levels):
        aabb = estimator.aabbs[level].double()
        start = aabb[:3] + estimator.grid_coords.double() / res * (aabb[3:] - aabb[:3])
        end = aabb[:3] + (estimator.grid_coords.double() + 1) / res * (aabb[3:] - aabb[:3])
        overlaps = ((start <= torch.tensor(box.max)) & (end > torch.tensor(box.min))).all(-1)
        assert torch.equal(mask[level].reshape(-1), overlaps)
        assert overlaps.any()
    estimator.binaries |= mask  # drops straight into the estimator


def test_views_across_from_each_other_are_refused_as_one_line_and_a_turned_view_passes():
    scene_box = np.array([[-1.0] * 3, [1.0] * 3])
    front = _cube_view(0, 10, (0, 0, 0), 0.02, name="front")
    across = _cube_view(177, -10, (0, 0, 0), 0.02, name="across")  # frusta facing each other meet all along the line
    with pytest.raises(ValueError, match=r"lines of sight are at most 3\.0 degrees apart.*across from each other"):
        compute_edit_box([front, across], scene_box=scene_box)
    assert compute_edit_box([front, _cube_view(90, 10, (0, 0, 0), 0.02)], scene_box=scene_box).size.max() < 0.1


def test_poses_with_opencv_axes_are_named_as_facing_away_and_opengl_ones_pass():
    views = [_cube_view(a, e, (0, 0, 0), 0.1, name=f"v{a}") for a, e in [(0, 10), (80, 25)]]
    flipped = [SketchView(v.mask, v.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0]), v.fl_x, v.fl_y, v.cx, v.cy,
                          name=v.name) for v in views]  # the frame was never the trouble: it was blamed
    with pytest.raises(ValueError, match=r"v0 and v80: the cameras are facing away from the sketched region.*OpenGL"):
        compute_edit_box(flipped)
    assert compute_edit_box(views).contains(torch.zeros(1, 3)).all()


def test_sketches_meeting_outside_the_scene_box_say_so_and_the_right_frame_passes():
    scene_box = np.array([[-1.0] * 3, [1.0] * 3])
    views = [_cube_view(a, e, (0, 0, 0), 0.1, name=f"v{a}") for a, e in [(0, 10), (80, 25)]]
    # Poses read in a frame 3x too large and shifted: the sketches meet, but away from the scene.
    far = [SketchView(v.mask, np.concatenate([v.camera_to_world[:, :3], 3 * v.camera_to_world[:, 3:] + 4.0], axis=1),
                      v.fl_x, v.fl_y, v.cx, v.cy, name=v.name) for v in views]
    with pytest.raises(ValueError, match=r"meet only outside the scene's box \(around \[4\.0, 4\.0, 4\.0\].*\"frame\""):
        compute_edit_box(far, scene_box=scene_box)
    assert compute_edit_box(far).contains(torch.tensor([[4.0, 4.0, 4.0]], dtype=torch.float64)).all()
    compute_edit_box(views, scene_box=scene_box)


def test_sketches_too_wide_to_bound_the_region_say_so_and_tighter_ones_pass():
    wide = [_cube_view(a, 10, (0, 0, 0), 0.1, name=f"v{a}") for a in (0, 20)]
    wide = [SketchView(np.ones_like(v.mask), v.camera_to_world, v.fl_x, v.fl_y, v.cx, v.cy, name=v.name) for v in wide]
    with pytest.raises(ValueError, match=r"unbounded region.*outline the region more tightly"):
        compute_edit_box(wide)
    compute_edit_box([_cube_view(a, 10, (0, 0, 0), 0.1) for a in (0, 20)])


def test_content_bounds_follow_nerfstudio_s_configs():
    from nerfstudio.models.instant_ngp import InstantNGPModelConfig
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.models.splatfacto import SplatfactoModelConfig

    aabb = np.array([[-1.0, -2.0, -1.0], [1.0, 0.0, 1.0]])
    box, bounded = content_bounds(NerfactoModelConfig(), aabb)  # contracted: space past the box is held
    assert not bounded and np.array_equal(box, aabb)
    assert not content_bounds(SplatfactoModelConfig(), aabb)[1]  # no box at all
    assert content_bounds(NerfactoModelConfig(disable_scene_contraction=True), aabb)[1]
    box, bounded = content_bounds(InstantNGPModelConfig(grid_levels=3), aabb)  # its grid's outermost level
    assert bounded and np.allclose(box, [[-4.0, -5.0, -4.0], [4.0, 3.0, 4.0]])
    box, bounded = content_bounds(InstantNGPModelConfig(disable_scene_contraction=True, grid_levels=1), aabb)
    assert bounded and np.array_equal(box, aabb)


def test_a_region_past_the_scene_box_is_kept_whole_where_the_base_holds_it_and_clipped_with_a_word_where_not():
    views = [_cube_view(a, e, (0.9, 0, 0), 0.3) for a, e in [(0, 10), (80, 25)]]  # a region straddling x = 1
    scene_box = np.array([[-1.0] * 3, [1.0] * 3])
    whole = compute_edit_box(views)
    assert whole.max[0] > 1.1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        held = compute_edit_box(views, scene_box, bounded=False)
        quiet = compute_edit_box(views, scene_box, quiet=True)
    np.testing.assert_allclose(np.stack([held.min, held.max]), np.stack([whole.min, whole.max]))
    with pytest.warns(UserWarning, match=r"clipped to it, \d+% of its size cut off along x.*--center-method focus"):
        clipped = compute_edit_box(views, scene_box)
    assert clipped.max[0] == pytest.approx(1.0) and np.allclose(quiet.max, clipped.max)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside = [_cube_view(a, e, (0, 0, 0), 0.3) for a, e in [(0, 10), (80, 25)]]
        assert np.allclose(compute_edit_box(inside, scene_box).max, compute_edit_box(inside).max)


def test_frusta_unbounded_without_a_box_are_bounded_by_the_scene_box_with_a_word():
    wide = [_cube_view(a, 10, (0, 0, 0), 0.1, name=f"v{a}") for a in (0, 20)]
    wide = [SketchView(np.ones_like(v.mask), v.camera_to_world, v.fl_x, v.fl_y, v.cx, v.cy, name=v.name) for v in wide]
    scene_box = np.array([[-1.0] * 3, [1.0] * 3])
    for bounded in (True, False):
        with pytest.warns(UserWarning, match="unbounded region.*runs out to the scene's box"):
            box = compute_edit_box(wide, scene_box, bounded=bounded)
        assert (box.min >= -1 - 1e-9).all() and (box.max <= 1 + 1e-9).all()


def test_the_base_s_content_is_looked_for_as_far_on_a_thin_axis_of_the_box_as_on_its_longest():
    from types import SimpleNamespace

    from sked_ns.method.edit import SkedEdit

    looked = []
    edit = SimpleNamespace(edit_box=EditBox(min=np.array([0.0, 0.0, 0.0]), max=np.array([0.4, 0.04, 0.04])),
                           config=SimpleNamespace(sketches="hat"),
                           base_content_near=lambda low, high: looked.append((low, high)) or len(looked) > 1)
    with pytest.warns(UserWarning, match=r"^hat: the sketches meet in empty space.*barely trained"):
        SkedEdit.warn_if_off_base(edit)
    low, high = looked[0]
    np.testing.assert_allclose(np.stack([low, high]), [[-0.2, -0.2, -0.2], [0.6, 0.24, 0.24]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SkedEdit.warn_if_off_base(edit)  # content found: nothing said
