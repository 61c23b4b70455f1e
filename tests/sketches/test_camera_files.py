"""sked-eval's camera files: every format nerfstudio's dataparsers read test cameras from, read as they read it."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from sked_ns.demo.scenes.sphere import orbit_pose
from sked_ns.errors import SkedUserError
from sked_ns.evaluation import novel_views
from sked_ns.sketches.data_frame import data_frame_transform
from sked_ns.sketches.sketch_set import DataparserTransform

WIDTH, HEIGHT = 40, 30
ANGLE_X = 0.8  # radians, Blender's camera_angle_x
FOCAL = 0.5 * WIDTH / np.tan(0.5 * ANGLE_X)
POSES = [np.concatenate([orbit_pose(azimuth, 25.0, 3.0), [[0, 0, 0, 1]]]) for azimuth in (10.0, 130.0, 250.0)]


def write_images(folder, names, size=(WIDTH, HEIGHT)):
    """RGBA images, as Blender's are (a grey square on a transparent background)."""
    for name in names:
        image = np.zeros((size[1], size[0], 4), dtype=np.uint8)
        image[5:20, 8:30] = (40, 90, 200, 255)
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / name), image)


def write_blender(folder):
    """A Blender scene's test split: camera_angle_x, no w/h/cx/cy, file_path without its extension."""
    write_images(folder, [f"test/r_{i}.png" for i in range(len(POSES))])
    frames = [{"file_path": f"./test/r_{i}", "rotation": 0.0, "transform_matrix": pose.tolist()}
              for i, pose in enumerate(POSES)]
    (folder / "transforms_test.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))
    return folder


def write_nerfstudio(folder, per_frame: bool, extra=None):
    """The same cameras as nerfstudio-data writes them: intrinsics at the top level or per frame."""
    write_images(folder, [f"images/frame_{i:05d}.png" for i in range(len(POSES))])
    intrinsics = {"fl_x": FOCAL, "fl_y": FOCAL, "cx": WIDTH / 2, "cy": HEIGHT / 2, "w": WIDTH, "h": HEIGHT}
    frames = [{"file_path": f"images/frame_{i:05d}.png", "transform_matrix": pose.tolist(),
               **(intrinsics if per_frame else {})} for i, pose in enumerate(POSES)]
    meta = {**({} if per_frame else intrinsics), "camera_model": "OPENCV", "frames": frames, **(extra or {})}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def views_of(folder, transform=DataparserTransform(), applies_file_transform=True):
    return novel_views.transforms_views(folder, transform, resolution=WIDTH, background=(1.0, 1.0, 1.0),
                                        with_images=True, applies_file_transform=applies_file_transform)


def assert_same_cameras(a, b):
    """Same poses, intrinsics and sizes, hence the same rays and renders."""
    assert len(a) == len(b)
    for one, other in zip(a, b):
        for key in ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "distortion_params"):
            np.testing.assert_allclose(getattr(one.camera, key).numpy(), getattr(other.camera, key).numpy(),
                                       atol=1e-5, err_msg=key)
        rays, other_rays = one.camera.generate_rays(0), other.camera.generate_rays(0)
        np.testing.assert_allclose(rays.directions.numpy(), other_rays.directions.numpy(), atol=1e-5)


def test_blender_and_nerfstudio_files_of_the_same_cameras_give_the_same_views(tmp_path):
    blender = views_of(write_blender(tmp_path / "blender"))  # the folder: its transforms_test.json
    nerfstudio = views_of(write_nerfstudio(tmp_path / "nerfstudio", per_frame=False))
    assert_same_cameras(blender, nerfstudio)
    assert (int(blender[0].camera.width), int(blender[0].camera.height)) == (WIDTH, HEIGHT)  # from the image
    assert float(blender[0].camera.fx) == pytest.approx(FOCAL)
    # Blender's RGBA images composited on the background, like the dataparser's alpha_color.
    for one, other in zip(blender, nerfstudio):
        torch.testing.assert_close(one.ground_truth, other.ground_truth)
    assert blender[0].ground_truth[0, 0].tolist() == [1.0, 1.0, 1.0]


def test_global_and_per_frame_intrinsics_agree_and_a_top_level_value_wins(tmp_path):
    global_ = views_of(write_nerfstudio(tmp_path / "global", per_frame=False))
    per_frame = views_of(write_nerfstudio(tmp_path / "per_frame", per_frame=True))
    assert_same_cameras(global_, per_frame)
    # nerfstudio-data takes a top-level fl_x over a frame's (its `fx_fixed`).
    folder = write_nerfstudio(tmp_path / "both", per_frame=True, extra={"fl_x": 2 * FOCAL})
    assert float(views_of(folder)[0].camera.fx) == pytest.approx(2 * FOCAL)


def test_blender_cameras_match_nerfstudios_blender_dataparser(tmp_path):
    """The cameras nerfstudio's blender-data gives its model, scale_factor included, are those sked-eval scores."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    folder = write_blender(tmp_path / "blender")
    outputs = BlenderDataParserConfig(data=folder, scale_factor=0.5).setup().get_dataparser_outputs("test")
    transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64),
                                    float(outputs.dataparser_scale))
    ours = views_of(folder, transform, applies_file_transform=False)
    for index, view in enumerate(ours):
        theirs = outputs.cameras[index]
        np.testing.assert_allclose(view.camera.camera_to_worlds.numpy(), theirs.camera_to_worlds.numpy(), atol=1e-5)
        for key in ("fx", "fy", "cx", "cy"):
            assert float(getattr(view.camera, key)) == pytest.approx(float(getattr(theirs, key)), rel=1e-5)


def test_applied_transform_and_distortion_match_nerfstudios_dataparser(tmp_path):
    """ns-process-data files hold poses moved by `applied_transform`, which the run's transform already contains."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    applied = [[0.0, 1.0, 0.0, 0.1], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, -1.0, 0.3]]
    distortion = {"k1": 0.05, "k2": -0.01, "p1": 0.001}
    folder = write_nerfstudio(tmp_path / "data", per_frame=False,
                              extra={"applied_transform": applied, "applied_scale": 2.0, **distortion})
    config = NerfstudioDataParserConfig(data=folder, eval_mode="all", downscale_factor=1)
    outputs = config.setup().get_dataparser_outputs("train")
    transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64),
                                    float(outputs.dataparser_scale))
    ours = views_of(folder, transform)
    order = np.argsort([f"frame_{i:05d}" for i in range(len(POSES))])  # nerfstudio sorts frames by file name
    for view, index in zip(ours, order):
        theirs = outputs.cameras[int(index)]
        np.testing.assert_allclose(view.camera.camera_to_worlds.numpy(), theirs.camera_to_worlds.numpy(), atol=1e-5)
        np.testing.assert_allclose(view.camera.distortion_params.numpy(), theirs.distortion_params.numpy(), atol=1e-7)
        assert view.camera.camera_type.item() == theirs.camera_type.item()


def test_sked_eval_reads_a_blender_target(tmp_path):
    """`sked-eval --target` with a Blender test split (was: 'frame 0 lacks fl_x, w, h')."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    from sked_ns.evaluation.evaluate import choose_novel_views

    folder = write_blender(tmp_path / "blender")
    pipeline = SimpleNamespace(
        model=SimpleNamespace(config=SimpleNamespace(background_color="white")),
        datamanager=SimpleNamespace(dataparser_transform=DataparserTransform(scale=0.5),
                                    config=SimpleNamespace(dataparser=BlenderDataParserConfig(data=folder))))
    views, source = choose_novel_views(pipeline, "eval", folder / "transforms_test.json", resolution=20, max_views=12)
    assert source.startswith("target") and len(views) == 3
    assert views[0].ground_truth.shape == (15, 20, 3)
    np.testing.assert_allclose(views[0].camera.camera_to_worlds[:, 3].numpy(), 0.5 * POSES[0][:3, 3], atol=1e-5)


def test_every_nerfstudio_camera_model_is_known():
    from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE

    assert set(novel_views.CAMERA_MODELS) == set(CAMERA_MODEL_TO_TYPE)


@pytest.mark.parametrize("meta, message", [
    ({"frames": [{"transform_matrix": np.eye(4).tolist(), "w": 8, "h": 8}]},
     r"transforms.json frame 0: no focal length; give 'fl_x' \(pixels\) or 'camera_angle_x'"),
    ({"camera_angle_x": 0.7, "frames": [{"transform_matrix": np.eye(4).tolist()}]},
     r"transforms.json frame 0: no 'w' and 'h' and no 'file_path'"),
    ({"camera_angle_x": 0.7, "frames": [{"file_path": "./test/missing", "transform_matrix": np.eye(4).tolist()}]},
     r"frame 0: no 'w' and 'h', and its image .*missing cannot be read"),
    ({"fl_x": 10, "w": 8, "h": 8, "frames": [{"transform_matrix": [[1, 0], [0, 1]]}]},
     r"frame 0: 'transform_matrix' must be a 4x4 matrix"),
    ({"fl_x": 10, "w": 8, "h": 8, "frames": [{"file_path": "a.png"}]}, r"frame 0: missing 'transform_matrix'"),
    ({"fl_x": "wide", "w": 8, "h": 8, "frames": [{"transform_matrix": np.eye(4).tolist()}]},
     r"frame 0: 'fl_x' must be a number, got 'wide'"),
    ({"fl_x": 10, "w": 8, "h": 8, "camera_model": "KANNALA", "frames": [{"transform_matrix": np.eye(4).tolist()}]},
     r"unknown 'camera_model' 'KANNALA'; nerfstudio knows SIMPLE_PINHOLE"),
    ({"fl_x": 10, "w": 8, "h": 8, "distortion_params": [0.1], "frames": [{"transform_matrix": np.eye(4).tolist()}]},
     r"'distortion_params' must be 6 numbers"),
    ({"images": []}, r"expected a JSON object with a non-empty list 'frames'"),
])
def test_unreadable_camera_files_name_the_file_frame_and_field(tmp_path, meta, message):
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(meta))
    with pytest.raises(SkedUserError, match=message):
        views_of(path)


def test_a_folder_without_a_camera_file_says_what_it_looked_for(tmp_path):
    with pytest.raises(SkedUserError, match=r"no camera file here \(looked for transforms.json and transforms_test.json\)"):
        views_of(tmp_path)


def test_a_sketch_set_copied_from_an_ns_process_data_transforms_json_lands_on_its_photos(tmp_path):
    """Sketch views whose poses are copied from transforms.json ("frame": "data") sit where the dataparser puts
    those photos, although the run's transform starts from the COLMAP frame before `applied_transform`."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from sked_ns.sketches.sketch_set import SketchSet, SketchView

    applied = [[0.0, 1.0, 0.0, 0.1], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, -1.0, 0.3]]
    folder = write_nerfstudio(tmp_path / "data", per_frame=False, extra={"applied_transform": applied, "applied_scale": 2.0})
    config = NerfstudioDataParserConfig(data=folder, eval_mode="all", downscale_factor=1)
    outputs = config.setup().get_dataparser_outputs("train")
    run_transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64),
                                        float(outputs.dataparser_scale))
    mask = np.zeros((HEIGHT, WIDTH), dtype=bool)
    mask[10:20, 10:20] = True
    views = [SketchView(mask=mask, camera_to_world=POSES[i][:3].copy(), fl_x=FOCAL, fl_y=FOCAL, cx=WIDTH / 2,
                        cy=HEIGHT / 2) for i in (0, 1)]
    model_frame = SketchSet(views=views, frame="data").in_model_frame(data_frame_transform(config, run_transform))
    for view, index in zip(model_frame.views, (0, 1)):  # frames are named in order, so nerfstudio keeps it
        np.testing.assert_allclose(view.camera_to_world, outputs.cameras.camera_to_worlds[index].numpy(), atol=1e-5)
    # The edit's datamanager hands the model this frame for its sketch set.
    from sked_ns.engine.datamanager import SKETCH_FRAME, SkedDataManagerConfig

    datamanager = SkedDataManagerConfig(dataparser=config).setup(device="cpu")
    handed = datamanager.train_dataset.metadata[SKETCH_FRAME]
    np.testing.assert_allclose(SketchSet(views=views, frame="data").in_model_frame(handed).views[1].camera_to_world,
                               outputs.cameras.camera_to_worlds[1].numpy(), atol=1e-5)
    # Without applied_transform in the file, the data frame is the run's own.
    plain = write_nerfstudio(tmp_path / "plain", per_frame=False)
    same = data_frame_transform(NerfstudioDataParserConfig(data=plain), run_transform)
    np.testing.assert_allclose(same.transform, run_transform.transform)
    assert same.scale == pytest.approx(run_transform.scale)
