"""Novel-view evaluation: cameras from a transforms.json, the kept-pixel metrics, and that a broken edit fails them."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from nerfstudio.field_components.field_heads import FieldHeadNames

from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.engine.edit_run import edit_config, run_edit
from sked_ns.evaluation import novel_views
from sked_ns.evaluation.render import load_pipeline
from sked_ns.sketches.sketch_set import DataparserTransform

TARGET_VIEWS = ((45.0, 20.0), (200.0, 35.0), (300.0, 10.0))


@pytest.fixture(scope="module")
def small_edit(scene, tmp_path_factory):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path_factory.mktemp("edit"),
                         iterations=40, guidance_resolution=24, silhouette_resolution=24, steps_per_save=100)
    run = run_edit(config).base_dir
    return {"run": run, "pipeline": load_pipeline(run)}


def write_target(folder, size=48, views=TARGET_VIEWS):
    """The hat scene's ground truth at a few cameras, with its changed-region masks (as benchmark scenes write)."""
    (folder / "images").mkdir(parents=True)
    focal, frames = 1.2 * size, []
    hat = demo_scene.SCENES["hat"]
    for index, (azimuth, elevation) in enumerate(views):
        pose = demo_scene.orbit_pose(azimuth, elevation, 2.4)
        target = hat.render_target(pose, focal, size, size)
        base = demo_scene.render(demo_scene.sphere_sdf, pose, focal, size, size)
        changed = ((target["rgb"] - base["rgb"]).abs().amax(-1) > 1e-3).numpy()
        cv2.imwrite(str(folder / f"images/{index}.png"), (target["rgb"].numpy()[..., ::-1] * 255).round().astype(np.uint8))
        cv2.imwrite(str(folder / f"images/{index}_changed.png"), changed.astype(np.uint8) * 255)
        frames.append({"file_path": f"images/{index}.png", "changed_mask_path": f"images/{index}_changed.png",
                       "transform_matrix": np.concatenate([pose, [[0, 0, 0, 1]]]).tolist()})
    (folder / "transforms.json").write_text(json.dumps({"fl_x": focal, "fl_y": focal, "cx": size / 2, "cy": size / 2,
                                                        "w": size, "h": size, "frames": frames}))
    return folder


def test_transforms_cameras_land_in_the_model_frame_with_their_images(scene, tmp_path):
    target = write_target(tmp_path / "target")
    transform = DataparserTransform.from_json(scene["base"] / "dataparser_transforms.json")
    views = novel_views.transforms_views(target, transform, resolution=24, background=(1, 1, 1), with_images=True)
    assert len(views) == 3
    pose = demo_scene.orbit_pose(*TARGET_VIEWS[1], 2.4)
    np.testing.assert_allclose(views[1].camera.camera_to_worlds.numpy(), transform.apply(pose), atol=1e-5)
    assert (int(views[1].camera.width), int(views[1].camera.height)) == (24, 24)
    assert float(views[1].camera.fx) == pytest.approx(1.2 * 24)  # rescaled with the image
    assert views[1].ground_truth.shape == (24, 24, 3) and views[1].changed.dtype == torch.bool
    assert views[1].changed.any() and not views[1].changed.all()


def test_transforms_without_intrinsics_name_the_file_and_frame(tmp_path):
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(ValueError, match=r"transforms.json frame 0: no 'w' and 'h' and no 'file_path'"):
        novel_views.transforms_views(path, DataparserTransform(), 32, (1, 1, 1), True)


def test_edit_keeps_novel_views_and_gets_closer_to_the_target(small_edit, tmp_path):
    pipeline = small_edit["pipeline"]
    views = novel_views.transforms_views(write_target(tmp_path / "target"), pipeline.datamanager.dataparser_transform,
                                         48, (1, 1, 1), True)
    result = novel_views.evaluate_novel_views(pipeline.model, views, target=True)
    mean = result["mean"]
    assert 0.3 < mean["keep_fraction"] < 1.0
    assert mean["psnr_keep"] > 25 and mean["ssim_keep"] > 0.8 and 0 <= mean["leak"] < 0.05
    # Against the analytic ground truth the edit keeps what the base had (a 40-step edit at 24 px loses 1.1-1.6 dB
    # here, by thread count: the base's faint haze changes colour; the benchmark tracks the 0.5 dB target), and
    # is closer to the hat.
    assert mean["psnr_keep_gt"] > mean["psnr_keep_gt_base"] - 2.0
    assert mean["psnr_target_changed"] > mean["psnr_target_changed_base"] + 1.0
    assert len(result["rows"]) == 3 and result["rows"][0].shape == (48, 144, 3)


def test_a_hazy_edit_fails_the_novel_view_metrics(small_edit, tmp_path):
    """A metric that a visibly broken edit passes is a bug: add haze everywhere and watch them drop."""
    model = small_edit["pipeline"].model
    views = novel_views.orbit_views(model.edit_box.center, 1.0, 4, 32)
    clean = novel_views.evaluate_novel_views(model, views)["mean"]
    original = model._held_outputs  # the edit's field outputs at its samples, whatever it trains

    def hazy(ray_samples, evaluate):
        edited, base = original(ray_samples, evaluate)
        # a thin fog everywhere: each sample keeps most light, the whole ray does not
        return {**edited, FieldHeadNames.DENSITY: edited[FieldHeadNames.DENSITY] + 0.3}, base

    model._held_outputs = hazy
    try:
        broken = novel_views.evaluate_novel_views(model, views)["mean"]
    finally:
        del model._held_outputs
    assert broken["leak"] > clean["leak"] + 0.1
    assert broken["psnr_keep"] < clean["psnr_keep"] - 5


def test_sked_eval_scores_the_eval_split_and_a_target(small_edit, tmp_path):
    from sked_ns.evaluation.evaluate import evaluate

    metrics = evaluate(small_edit["run"], resolution=32, novel_resolution=32)["metrics"]
    # Region IoS counts only what lies near the sketches: the base's sphere under the hat barely counts.
    mean = metrics["mean"]
    assert mean["ios_region_base"] < mean["ios_base"] and mean["ios_region"] > mean["ios_region_base"] + 0.3
    novel = metrics["novel_views"]
    assert novel["cameras"] == "the base dataset's eval split" and len(novel["views"]) >= 2
    assert {"psnr_keep", "ssim_keep", "leak", "psnr_keep_gt", "psnr_keep_gt_base", "ssim_keep_gt",
            "ssim_keep_gt_base"} <= set(novel["mean"])
    with_target = evaluate(small_edit["run"], resolution=32, novel_resolution=32,
                           target=write_target(tmp_path / "target"))["metrics"]["novel_views"]
    assert with_target["cameras"].startswith("target") and "psnr_target_changed_base" in with_target["mean"]
