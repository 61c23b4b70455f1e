"""Benchmark scenes: well-formed edits, and reference-guided edits that reach their targets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.engine.edit_run import edit_config, run_edit
from sked_ns.evaluation.metrics import psnr_outside
from sked_ns.evaluation.render import load_pipeline, render_at, resized_mask
from sked_ns.method.edit_box import compute_edit_box
from sked_ns.sketches.sketch_set import load_sketch_set, save_sketch_set


def test_three_scenes_of_different_shapes_sizes_and_baselines():
    assert len(demo_scene.SCENES) >= 3
    coverage = {name: np.mean([v.mask.mean() for v in s.sketch_set(64).views]) for name, s in demo_scene.SCENES.items()}
    assert len({round(c, 3) for c in coverage.values()}) == len(coverage)  # different sizes
    assert {len(s.sketch_views) for s in demo_scene.SCENES.values()} >= {2, 3}


@pytest.mark.parametrize("name", list(demo_scene.SCENES))
def test_edit_box_holds_the_whole_edit_and_the_edit_is_new_mass(name):
    scene = demo_scene.SCENES[name]
    sketches = scene.sketch_set(96)
    box = compute_edit_box(sketches.views)
    points = torch.rand(400_000, 3) * 2.4 - 1.2
    inside_edit = points[scene.edit_sdf(points) < -0.01]
    assert len(inside_edit) > 20 and box.contains(inside_edit.double()).all()
    # Most of the added volume is empty space in the base: the edit must create new mass.
    assert (demo_scene.sphere_sdf(inside_edit) > 0).float().mean() > 0.5


@pytest.mark.parametrize("name", ["handle", "antenna"])
def test_reference_edit_reaches_each_target(scene, tmp_path, name):
    edit_scene = demo_scene.SCENES[name]
    sketch_set = edit_scene.sketch_set(64)
    save_sketch_set(sketch_set, tmp_path / "sketches")
    config = edit_config(scene["base"], scene["data"], tmp_path / "sketches", tmp_path / "out", iterations=60,
                         guidance_resolution=32, silhouette_resolution=32)
    config.pipeline.model.guidance.target = name
    trainer = run_edit(config)
    base = load_pipeline(scene["base"])
    sketches = load_sketch_set(tmp_path / "sketches").in_model_frame(trainer.pipeline.datamanager.dataparser_transform)
    for view, data_view in zip(sketches.views, sketch_set.views):
        mask = resized_mask(view, 64).bool()
        # Judged against the exact target, not the whole sketch: a sketch is the part's outline dilated by a
        # pixel (a thin ring or rod: 40-50% margin), which a correct edit leaves empty. A haze filling the whole
        # sketch scored IoS above the exact target's (antenna 0.83 vs 0.53) and passed "IoS > 0.75".
        camera = (data_view.camera_to_world, data_view.fl_x, 64, 64)
        target, sphere = (render(*camera)["hit"].bool() for render in (edit_scene.render_target, edit_scene.render_base))
        new_part, margin = mask & target & ~sphere, mask & ~target
        before, after = render_at(base.model, view, 64), render_at(trainer.pipeline.model, view, 64)
        accumulation_before, accumulation_after = (r["accumulation"].reshape(mask.shape) for r in (before, after))
        # Measured (handle's three views, antenna's two): the new part 0.87 / 0.90 / 0.94, 0.95 / 0.89 filled
        # (0.03-0.18 before); the margin 0.23 / 0.24 / 0.38, 0.48 / 0.25 (random views in the authors' 40-80 deg,
        # edit-fill 0: antenna 0.62-0.64 / 0.40 on its first / second view, the haze this catches: it fails).
        assert accumulation_after[new_part].mean() > 0.8
        assert accumulation_after[new_part].mean() > accumulation_before[new_part].mean() + 0.5
        assert accumulation_after[margin].mean() < 0.6
        # Measured 55.8 / 45.3 / 42.2 dB on handle's views, 41.7 / 38.6 on antenna's.
        assert psnr_outside(after["rgb"], before["rgb"], mask.float()) > 30.0


@pytest.mark.parametrize("name", ["vase", "crate"])
def test_held_out_scenes_write_base_target_and_sketches(name, tmp_path):
    import json

    from sked_ns.demo.scenes import catalogue
    from sked_ns.demo.scenes import objects as benchmark_scenes

    scene = benchmark_scenes.SCENES[name]
    paths = catalogue.write_benchmark(name, tmp_path, count=12, size=32)
    data = json.loads((paths["data"] / "transforms.json").read_text())
    target = json.loads((paths["target"] / "transforms.json").read_text())
    assert len(data["frames"]) == 12
    # The target is the edited scene at exactly the frames nerfstudio holds out for evaluation.
    held_out = [data["frames"][i]["file_path"] for i in benchmark_scenes.eval_indices(12)]
    assert [frame["file_path"] for frame in target["frames"]] == held_out
    changed = [cv2_read(paths["target"] / frame["changed_mask_path"]) for frame in target["frames"]]
    assert all(0 < mask.mean() < 0.5 for mask in changed if mask.any()) and any(mask.any() for mask in changed)
    sketches = load_sketch_set(paths["sketches"])
    assert len(sketches.views) == len(scene.sketch_views) and all(v.mask.any() for v in sketches.views)
    # The added part touches the base (a flower in a vase, a handle on a crate) and lies in the edit box.
    points = torch.rand(300_000, 3) * 2 - 1
    on_edit = points[scene.edit_sdf(points) < 0]
    assert len(on_edit) > 50 and compute_edit_box(sketches.views).contains(on_edit.double()).all()
    from sked_ns.demo.scenes.objects import union

    base_sdf = union(scene.base_parts)[0]
    assert base_sdf(on_edit).min() < 0.02, "the edit touches an existing surface"


def cv2_read(path):
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127


def test_the_catalogue_writes_the_capture_like_scene_through_its_own_lens(tmp_path):
    import json

    from sked_ns.demo.reference_guidance import reference_scene
    from sked_ns.demo.scenes import capture, catalogue

    assert catalogue.scene_named("bust") is capture.SCENES["bust"] is reference_scene("bust")
    paths = catalogue.write_benchmark("bust", tmp_path, count=10, size=32)  # size: the portrait frames' height
    meta = json.loads((paths["data"] / "transforms.json").read_text())
    assert (meta["camera_model"], meta["h"], meta["w"]) == ("OPENCV", 32, 18) and len(meta["frames"]) == 10
    target = json.loads((paths["target"] / "transforms.json").read_text())
    assert target["k1"] == meta["k1"] and all("changed_mask_path" in frame for frame in target["frames"])
