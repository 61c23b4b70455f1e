"""Sketch sets: round trip, frames, scribble filling and every bad input."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import random_view

from sked_ns.sketches.sketch_set import (
    FRAMES,
    DataparserTransform,
    SketchSet,
    SketchView,
    fill_scribbles,
    load_sketch_set,
    mask_from_image,
    save_sketch_set,
)


@pytest.fixture
def sketch_folder(tmp_path, rng):
    views = [random_view(rng, 64, 48, f"v{i}") for i in range(3)]
    save_sketch_set(SketchSet(views=views, frame="data"), tmp_path / "set")
    return tmp_path / "set", views


def _edit_json(folder, change):
    path = folder / "sketches.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_round_trip(sketch_folder):
    folder, views = sketch_folder
    loaded = load_sketch_set(folder)
    assert loaded.frame == "data" and len(loaded.views) == 3
    for original, again in zip(views, loaded.views):
        np.testing.assert_array_equal(original.mask, again.mask)
        np.testing.assert_allclose(original.camera_to_world, again.camera_to_world, atol=1e-12)
        assert (again.fl_x, again.fl_y, again.cx, again.cy) == pytest.approx(
            (original.fl_x, original.fl_y, original.cx, original.cy)
        )
        assert (again.width, again.height) == (64, 48)


def test_frame_defaults_to_data_and_model_frame_needs_no_transform(sketch_folder):
    folder, _ = sketch_folder
    _edit_json(folder, lambda meta: meta.pop("frame"))
    loaded = load_sketch_set(folder)
    assert loaded.frame == "data"
    with pytest.raises(ValueError, match="dataparser"):
        loaded.in_model_frame(None)
    _edit_json(folder, lambda meta: meta.update(frame="model"))
    model = load_sketch_set(folder)
    assert model.in_model_frame(None) is model


def test_data_frame_applies_the_dataparser_transform(sketch_folder):
    folder, views = sketch_folder
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    transform = DataparserTransform(np.concatenate([rotation, [[0.1], [-0.2], [0.3]]], axis=1), scale=0.5)
    model = load_sketch_set(folder).in_model_frame(transform)
    assert model.frame == "model"
    for original, moved in zip(views, model.views):
        # A point fixed to the camera moves with it: p_model = (T p_data) * scale.
        local = np.array([0.1, -0.2, -1.0])
        data_point = original.camera_to_world[:, :3] @ local + original.camera_to_world[:, 3]
        expected = (rotation @ data_point + [0.1, -0.2, 0.3]) * 0.5
        scaled_local = local * 0.5
        np.testing.assert_allclose(moved.camera_to_world[:, :3] @ scaled_local + moved.camera_to_world[:, 3], expected)


def test_dataparser_transform_reads_nerfstudio_json(tmp_path):
    path = tmp_path / "dataparser_transforms.json"
    path.write_text(json.dumps({"transform": np.eye(4)[:3].tolist(), "scale": 0.25}))
    assert DataparserTransform.from_json(path).scale == 0.25
    path.write_text("{}")
    with pytest.raises(ValueError, match="dataparser_transforms.json"):
        DataparserTransform.from_json(path)


def test_closed_scribble_is_filled_and_blob_is_unchanged():
    ring = np.zeros((40, 40), np.uint8)
    cv2.circle(ring, (20, 20), 12, 1, thickness=2)
    filled = fill_scribbles(ring.astype(bool))
    assert filled[20, 20] and filled.sum() > 2 * ring.sum()
    blob = np.zeros((40, 40), bool)
    blob[5:15, 8:30] = True
    np.testing.assert_array_equal(fill_scribbles(blob), blob)


def test_rgba_masks_use_alpha_and_gray_masks_use_brightness():
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[1:3, 1:3] = [0, 0, 0, 255]  # black, opaque blob on transparent (authors' style)
    assert mask_from_image(rgba).sum() == 4
    gray = np.zeros((4, 4), np.uint8)
    gray[0, :] = 255
    assert mask_from_image(gray).sum() == 4


def test_saving_never_overwrites(sketch_folder):
    folder, views = sketch_folder
    before = (folder / "sketches.json").read_bytes()
    with pytest.raises(FileExistsError, match="sketches.json"):
        save_sketch_set(SketchSet(views=views[:2]), folder)
    assert (folder / "sketches.json").read_bytes() == before


@pytest.mark.parametrize(
    "change, error, message",
    [
        (lambda m, f: m["views"][1].update(mask_path="masks/nope.png"), FileNotFoundError, r"nope.png.*not found"),
        (lambda m, f: (f / "masks/view_01.png").write_text("not a png"), ValueError, r"view_01.png.*cannot read"),
        (lambda m, f: m["views"][0].update(w=65), ValueError, r"view_00.png.*64x48.*w=65"),
        (lambda m, f: cv2.imwrite(str(f / "masks/view_02.png"), np.zeros((48, 64), np.uint8)), ValueError, r"view_02.png.*empty"),
        (lambda m, f: m.update(views=m["views"][:1]), ValueError, r"sketches.json.*at least two"),
        (lambda m, f: m["views"][1]["transform_matrix"][0].__setitem__(3, float("nan")), ValueError, r"views\[1\].*transform_matrix.*NaN"),
        (lambda m, f: m["views"][0]["transform_matrix"][0].__setitem__(0, 2.0), ValueError, r"views\[0\].*transform_matrix.*rotation"),
        (lambda m, f: m.update(frame="world"), ValueError, r"sketches.json.*unknown 'frame' 'world'"),
        (lambda m, f: m["views"][2].pop("fl_x"), ValueError, r"views\[2\].*'fl_x'"),
        (lambda m, f: m["views"][2].update(fl_y=-1), ValueError, r"views\[2\].*'fl_y'.*positive"),
    ],
    ids=["missing-mask", "unreadable-mask", "size-mismatch", "empty-mask", "one-view", "nan-pose", "scaled-pose",
         "unknown-frame", "missing-field", "negative-focal"],
)
def test_bad_input_names_the_file_and_field(sketch_folder, change, error, message):
    folder, _ = sketch_folder
    _edit_json(folder, lambda meta: change(meta, folder))
    with pytest.raises(error, match=message):
        load_sketch_set(folder)


def test_missing_or_broken_json(tmp_path):
    with pytest.raises(FileNotFoundError, match="sketches.json"):
        load_sketch_set(tmp_path)
    (tmp_path / "sketches.json").write_text("{oops")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_sketch_set(tmp_path)


def test_sketch_set_needs_two_views(rng):
    with pytest.raises(ValueError, match="at least two"):
        SketchSet(views=[random_view(rng, 8, 8)])


def test_bounding_box_covers_every_contour():
    mask = np.zeros((20, 30), bool)
    mask[2:4, 3:5] = True
    mask[15:18, 20:27] = True
    view = SketchView(mask=mask, camera_to_world=np.eye(4)[:3], fl_x=10, fl_y=10, cx=15, cy=10)
    assert view.bounding_box() == (3, 2, 27, 18)


def test_dataparser_transform_inverts_and_maps_points(rng):
    from sked_ns.demo.scenes.sphere import orbit_pose

    angle = 0.7
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    transform = DataparserTransform(np.concatenate([rotation, [[0.3], [0.1], [-0.5]]], axis=1), scale=0.4)
    pose = orbit_pose(30.0, 20.0, 2.0)
    np.testing.assert_allclose(transform.invert(transform.apply(pose)), pose, atol=1e-12)
    import torch

    points = torch.tensor(rng.normal(size=(10, 3)))
    moved = transform.points_to_model(points)
    np.testing.assert_allclose(moved.numpy(), ((rotation @ points.numpy().T).T + [0.3, 0.1, -0.5]) * 0.4, atol=1e-12)
    np.testing.assert_allclose(transform.points_to_data(moved).numpy(), points.numpy(), atol=1e-12)
    # A camera's origin maps like a point.
    np.testing.assert_allclose(transform.apply(pose)[:, 3], transform.points_to_model(torch.tensor(pose[:, 3])).numpy())


# ---- lens distortion: masks painted on distorted photos ------------------------------------------
WIDTH, HEIGHT, FOCAL, CX, CY = 160, 120, 100.0, 80.3, 59.6


def _distorted_set(tmp_path, rng, coefficients, pixel, camera_model=None):
    """A set whose first view is a disc painted around `pixel` (row, col) of a distorted photo."""
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    photo_mask = (rows - pixel[0]) ** 2 + (cols - pixel[1]) ** 2 <= 2**2
    first = SketchView(mask=photo_mask, camera_to_world=random_view(rng, 8, 8).camera_to_world,
                       fl_x=FOCAL, fl_y=FOCAL, cx=CX, cy=CY, name="photo")
    save_sketch_set(SketchSet(views=[first, random_view(rng, 64, 48)]), tmp_path / "set")
    _edit_json(tmp_path / "set", lambda meta: meta["views"][0].update(
        dict(zip(("k1", "k2", "k3", "k4", "p1", "p2"), coefficients)), **({"camera_model": camera_model} if camera_model else {})))
    return tmp_path / "set", first


@pytest.mark.parametrize("coefficients, pixel", [
    ((-0.3, 0.05, -0.01, 0.002, 0.004, -0.006), (20, 130)),  # barrel, the photo's upper right
    ((0.3, 0.02, 0.0, 0.0, -0.003, 0.005), (10, 150)),  # pincushion, near the corner
], ids=["barrel", "pincushion"])
def test_a_mask_on_a_distorted_photo_lands_where_nerfstudio_traces_that_pixel(tmp_path, rng, coefficients, pixel):
    import torch
    from nerfstudio.cameras.cameras import Cameras, CameraType

    from sked_ns.sketches.cameras import project

    folder, photo = _distorted_set(tmp_path, rng, coefficients, pixel)
    loaded = load_sketch_set(folder).views[0]
    # nerfstudio trains the photo's pixel with this ray (undistorted by its own camera model).
    camera = Cameras(camera_to_worlds=torch.tensor(photo.camera_to_world[None], dtype=torch.float32),
                     fx=FOCAL, fy=FOCAL, cx=CX, cy=CY, width=WIDTH, height=HEIGHT,
                     distortion_params=torch.tensor(coefficients, dtype=torch.float32), camera_type=CameraType.PERSPECTIVE)
    ray = camera.generate_rays(camera_indices=0, coords=torch.tensor([[pixel[0] + 0.5, pixel[1] + 0.5]]))
    point = (ray.origins + 2.0 * ray.directions).double()
    intrinsics = torch.tensor([loaded.intrinsics])
    pixels, _ = project(point, torch.tensor(loaded.camera_to_world[None]), intrinsics)
    u, v = pixels[0, 0].numpy()
    assert math.hypot(u - pixel[1] - 0.5, v - pixel[0] - 0.5) > 5.0  # distortion moves it: the test means something
    assert loaded.mask[int(v), int(u)], "the undistorted mask covers the pinhole projection of the traced point"
    centroid_v, centroid_u = np.argwhere(loaded.mask).mean(axis=0) + 0.5
    assert math.hypot(centroid_u - u, centroid_v - v) < 1.0
    assert (loaded.fl_x, loaded.fl_y, loaded.cx, loaded.cy) == (FOCAL, FOCAL, CX, CY)  # same intrinsics, pinhole


def test_zero_distortion_loads_as_before(tmp_path, rng):
    folder, photo = _distorted_set(tmp_path, rng, (0.0,) * 6, (20, 130), camera_model="OPENCV")
    np.testing.assert_array_equal(load_sketch_set(folder).views[0].mask, photo.mask)
    _edit_json(folder, lambda meta: meta["views"][0].update(distortion_params=[0.0] * 6))
    np.testing.assert_array_equal(load_sketch_set(folder).views[0].mask, photo.mask)


def test_distortion_params_list_is_read_like_nerfstudio(tmp_path, rng):
    coefficients = (-0.3, 0.05, -0.01, 0.002, 0.004, -0.006)
    folder, photo = _distorted_set(tmp_path, rng, coefficients, (20, 130))
    by_fields = load_sketch_set(folder).views[0].mask
    assert not np.array_equal(by_fields, photo.mask)
    _edit_json(folder, lambda meta: [meta["views"][0].pop(key) for key in ("k1", "k2", "k3", "k4", "p1", "p2")]
               and meta["views"][0].update(distortion_params=list(coefficients)))
    np.testing.assert_array_equal(load_sketch_set(folder).views[0].mask, by_fields)


def test_saving_a_distorted_set_keeps_what_was_loaded(tmp_path, rng):
    folder, _ = _distorted_set(tmp_path, rng, (-0.3, 0.05, -0.01, 0.002, 0.004, -0.006), (20, 130))
    loaded = load_sketch_set(folder)
    again = load_sketch_set(save_sketch_set(loaded, tmp_path / "copy").parent)
    for view, copy in zip(loaded.views, again.views):
        np.testing.assert_array_equal(view.mask, copy.mask)  # saved undistorted: loading it again changes nothing
        np.testing.assert_allclose(view.camera_to_world, copy.camera_to_world, atol=1e-12)
        assert (view.fl_x, view.fl_y, view.cx, view.cy) == (copy.fl_x, copy.fl_y, copy.cx, copy.cy)


@pytest.mark.parametrize("where", ["view", "set"])
def test_a_non_perspective_camera_model_is_refused(tmp_path, rng, where):
    folder, _ = _distorted_set(tmp_path, rng, (0.1, 0.0, 0.0, 0.0, 0.0, 0.0), (20, 130))
    if where == "view":
        _edit_json(folder, lambda meta: meta["views"][0].update(camera_model="OPENCV_FISHEYE"))
    else:
        _edit_json(folder, lambda meta: meta.update(camera_model="OPENCV_FISHEYE"))
    with pytest.raises(ValueError, match=r"sketches.json views\[0\].*'camera_model' 'OPENCV_FISHEYE'.*undistorted"):
        load_sketch_set(folder)


@pytest.mark.parametrize("change, message", [
    (lambda view: view.update(k1="strong"), r"views\[0\].*'k1' must be a number"),
    (lambda view: view.update(distortion_params=[0.1, 0.0]), r"views\[0\].*'distortion_params' must be 6 finite"),
    (lambda view: view.update(k1=1e6), r"view_00.png.*empty once the lens distortion.*views\[0\]"),
], ids=["not-a-number", "short-list", "mask-outside-the-pinhole-view"])
def test_bad_distortion_names_the_view_and_field(tmp_path, rng, change, message):
    folder, _ = _distorted_set(tmp_path, rng, (0.0,) * 6, (20, 130))
    _edit_json(folder, lambda meta: change(meta["views"][0]))
    with pytest.raises(ValueError, match=message):
        load_sketch_set(folder)


def test_a_mask_that_cannot_be_written_is_an_error(tmp_path, rng):
    (tmp_path / "set" / "masks" / "view_01.png").mkdir(parents=True)  # a folder where the PNG should go
    with pytest.raises(OSError, match=r"view_01.png.*could not write"):
        save_sketch_set(SketchSet(views=[random_view(rng, 8, 8), random_view(rng, 8, 8)]), tmp_path / "set")


def _demo_frame():
    """The demo's training cameras in the model frame, under the transform nerfstudio's dataparser gives it."""
    from sked_ns.demo.scenes import sphere as scene

    transform = DataparserTransform(np.concatenate([np.eye(3), [[0.0], [0.0], [-1.08]]], axis=1), 0.431)
    positions = np.stack([transform.apply(pose)[:, 3] for pose in scene.demo_camera_poses(24)])
    return transform, positions, np.zeros(3)


def test_a_sketch_set_declared_in_the_wrong_frame_is_refused_naming_the_field_and_value(tmp_path):
    from sked_ns.demo.scenes import sphere as scene
    from sked_ns.sketches.data_frame import SKETCH_FRAME, TRAINING_CAMERAS, model_frame_sketches

    transform, positions, centre = _demo_frame()
    demo = scene.demo_sketch_set(size=64)  # data-frame poses
    save_sketch_set(demo, tmp_path / "right")
    save_sketch_set(SketchSet(views=demo.views, frame="model"), tmp_path / "wrong")
    metadata = {SKETCH_FRAME: transform, TRAINING_CAMERAS: (positions, centre)}
    assert model_frame_sketches(tmp_path / "right", metadata).frame == "model"
    with pytest.raises(ValueError, match=r'wrong/sketches.json: "frame": "model".*2\.\dx.*Set "frame": "data"'):
        model_frame_sketches(tmp_path / "wrong", metadata)


def test_a_frame_is_not_second_guessed_where_both_readings_fit(rng):
    from sked_ns.demo.scenes import sphere as scene
    from sked_ns.sketches.data_frame import check_declared_frame

    _, positions, centre = _demo_frame()
    demo = scene.demo_sketch_set(size=64)
    unscaled = DataparserTransform(np.eye(4)[:3], 1.0)  # data and model frames alike: nothing to tell apart
    for frame in FRAMES:
        check_declared_frame(SketchSet(views=demo.views, frame=frame), unscaled, positions / 0.431, centre, Path("x"))
    # A model-frame set sketched from 1.7x nearer than the training cameras is legal (close-ups), however it reads.
    transform, positions, centre = _demo_frame()
    near = [dataclasses.replace(v, camera_to_world=np.concatenate([v.camera_to_world[:, :3], 0.6 * transform.apply(
        v.camera_to_world)[:, 3:]], axis=1)) for v in demo.views]
    check_declared_frame(SketchSet(views=near, frame="model"), transform, positions, centre, Path("x"))
