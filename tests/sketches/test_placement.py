"""Cameras inside the sketched region or facing away from it are named as such, in either frame, and the frame is
blamed only where reading the poses in the other frame passes the checks that follow."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from sked_ns.demo.scenes import sphere as scene
from sked_ns.errors import SkedWarning
from sked_ns.method.edit_box import compute_edit_box
from sked_ns.sketches.data_frame import SKETCH_FRAME, TRAINING_CAMERAS, model_frame_sketches
from sked_ns.sketches.sketch_set import DataparserTransform, SketchSet, save_sketch_set

SCENE_BOX = np.array([[-1.0] * 3, [1.0] * 3])
HAT = np.array(scene.HAT_CENTRE)
HAT_IN_MODEL = (HAT + [0.0, 0.0, -1.08]) * 0.431


def _metadata():
    """The demo's frame: its training cameras under the transform nerfstudio's dataparser gives it."""
    transform = DataparserTransform(np.concatenate([np.eye(3), [[0.0], [0.0], [-1.08]]], axis=1), 0.431)
    positions = np.stack([transform.apply(pose)[:, 3] for pose in scene.demo_camera_poses(24)])
    return {SKETCH_FRAME: transform, TRAINING_CAMERAS: (positions, np.zeros(3))}


def _at(view, position):
    return dataclasses.replace(view, camera_to_world=np.concatenate([view.camera_to_world[:, :3],
                                                                     np.asarray(position, float)[:, None]], axis=1))


def _in_hat(views):
    return all(scene.hat_sdf(torch.tensor(view.camera_to_world[None, :, 3])).item() < 0 for view in views)


def _run(folder, frame):
    """What an edit does with a sketch set: read it in the model frame, then box it in the scene."""
    meta = json.loads((folder / "sketches.json").read_text())
    (folder / "sketches.json").write_text(json.dumps({**meta, "frame": frame}))
    return compute_edit_box(model_frame_sketches(folder, _metadata()).views, scene_box=SCENE_BOX)


def test_cameras_inside_the_sketched_part_are_named_not_blamed_on_the_frame(tmp_path):
    demo = scene.demo_sketch_set(size=64)
    # Each camera inside the hat it sketches, past its centre: the lines of sight meet behind the cameras.
    inside = [_at(view, HAT + [0, 0, 0.05] - 0.05 * view.camera_to_world[:, 2]) for view in demo.views]
    assert _in_hat(inside)
    save_sketch_set(SketchSet(views=inside), tmp_path / "set")
    for frame in ("data", "model"):  # "model" was the advice, which then found the sketches apart
        with pytest.raises(ValueError, match=r"set/sketches.json: .*view_00.png and .*view_01.png: the cameras are "
                                             r"facing away from the sketched region") as error:
            _run(tmp_path / "set", frame)
        assert "frame" not in str(error.value).split("OpenGL")[0]
    # Following the advice (out of the hat, back along each line of sight) passes.
    save_sketch_set(demo, tmp_path / "out")
    assert _run(tmp_path / "out", "data").contains(torch.tensor([HAT_IN_MODEL])).all()


def test_cameras_near_inside_the_sketched_part_are_warned_not_sent_to_the_other_frame(tmp_path):
    demo = scene.demo_sketch_set(size=64)
    # Each camera inside the hat looking at its centre from just behind: a speck of a region, in any frame.
    inside = [_at(view, HAT + [0, 0, 0.05] + 0.05 * view.camera_to_world[:, 2]) for view in demo.views]
    assert _in_hat(inside)
    save_sketch_set(SketchSet(views=inside), tmp_path / "set")
    with pytest.warns(SkedWarning, match=r"view_00.png and .*view_01.png: the cameras stand \d+x or more nearer the "
                                         r"region the sketches mark than the base's photos.*inside the scene's content\. If so, move them back out"):
        _run(tmp_path / "set", "data")


def test_a_camera_inside_another_views_sketch_is_refused_and_moving_it_out_passes():
    first, second = scene.demo_sketch_set(size=64).views
    with pytest.raises(ValueError, match=r"hat@110: the camera is inside the sketched region \(inside hat@20's "
                                         r"sketch\).*Move the camera out"):
        compute_edit_box([first, _at(second, HAT)], scene_box=SCENE_BOX)
    third = dataclasses.replace(_at(first, HAT), name="third")  # was called a copy of hat@20 (the same line of sight)
    with pytest.raises(ValueError, match=r"third: the camera is inside the sketched region \(inside every other"):
        compute_edit_box([first, second, third], scene_box=SCENE_BOX)
    compute_edit_box([first, second], scene_box=SCENE_BOX)


def test_the_frame_advice_when_followed_passes(tmp_path):
    demo = scene.demo_sketch_set(size=64)  # data-frame poses
    save_sketch_set(demo, tmp_path / "set")
    with pytest.raises(ValueError, match=r'Set "frame": "data"'):
        _run(tmp_path / "set", "model")
    assert _run(tmp_path / "set", "data").contains(torch.tensor([HAT_IN_MODEL])).all()


def test_a_sketch_view_no_photo_looked_from_is_warned_and_views_among_the_photos_are_not():
    from sked_ns.sketches.placement import PHOTO_REACH_DEG, views_off_photos, warn_views_off_photos

    first, second = scene.demo_sketch_set(size=64).views
    centre = np.zeros(3)
    arc = np.stack([scene.orbit_pose(azimuth, 0.0, 2.4)[:3, 3] for azimuth in range(-60, 61, 10)])  # photos on an arc
    on_arc = [_at(first, scene.orbit_pose(-30.0, 25.0, 2.4)[:3, 3]), _at(second, scene.orbit_pose(40.0, 15.0, 2.4)[:3, 3])]
    assert views_off_photos(on_arc, arc, centre) == []
    behind = _at(second, scene.orbit_pose(180.0, 0.0, 2.4)[:3, 3])  # opposite the arc's middle: 120 degrees from its ends
    off = views_off_photos([on_arc[0], behind], arc, centre)
    assert [index for index, _ in off] == [1] and off[0][1] == pytest.approx(120.0, abs=0.5)
    assert off[0][1] > PHOTO_REACH_DEG
    with pytest.warns(SkedWarning, match=r"sketches.json: .*\(120 degrees\): this view looks at the sketched region"):
        warn_views_off_photos([on_arc[0], behind], arc, centre, "sketches.json")
    assert views_off_photos(on_arc, np.zeros((0, 3)), centre) == []  # no photos: nothing to say
