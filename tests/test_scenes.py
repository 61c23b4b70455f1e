"""Benchmark scenes: well-formed edits, and reference-guided edits that reach their targets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.demo import scene as demo_scene
from sked_ns.edit_box import compute_edit_box
from sked_ns.edit_run import edit_config, run_edit
from sked_ns.metrics import intersection_over_sketch, psnr_outside
from sked_ns.render import load_pipeline, render_at, resized_mask
from sked_ns.sketches import load_sketch_set, save_sketch_set


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
    save_sketch_set(demo_scene.SCENES[name].sketch_set(64), tmp_path / "sketches")
    config = edit_config(scene["base"], scene["data"], tmp_path / "sketches", tmp_path / "out", iterations=60,
                         guidance_resolution=32, silhouette_resolution=32)
    config.pipeline.model.guidance.target = name
    trainer = run_edit(config)
    base = load_pipeline(scene["base"])
    sketches = load_sketch_set(tmp_path / "sketches").in_model_frame(trainer.pipeline.datamanager.dataparser_transform)
    for view in sketches.views:
        mask = resized_mask(view, 64)
        before, after = render_at(base.model, view, 64), render_at(trainer.pipeline.model, view, 64)
        ios_before = intersection_over_sketch(before["accumulation"], mask)
        ios_after = intersection_over_sketch(after["accumulation"], mask)
        # Seeded as ns-train seeds, measured: handle 0.69 -> 0.91, 0.36 -> 0.85, 0.61 -> 0.93; antenna 0.10 -> 0.85,
        # 0.23 -> 0.81. (Handle's first view is mostly the sphere already, so "+0.2" had no margin there.)
        assert ios_after > 0.75 and ios_after > ios_before + 0.15
        # Measured 40.0 / 36.0 / 34.7 dB on handle's views, 36.0 / 36.0 on antenna's (23-33 dB before the
        # base-density preservation target and the photo anchor).
        assert psnr_outside(after["rgb"], before["rgb"], mask) > 30.0


@pytest.mark.parametrize("name", ["vase", "crate"])
def test_held_out_scenes_write_base_target_and_sketches(name, tmp_path):
    from sked_ns.demo import benchmark_scenes
    import json

    scene = benchmark_scenes.SCENES[name]
    paths = benchmark_scenes.write_benchmark(name, tmp_path, count=12, size=32)
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
    from sked_ns.demo.benchmark_scenes import union

    base_sdf = union(scene.base_parts)[0]
    assert base_sdf(on_edit).min() < 0.02, "the edit touches an existing surface"


def cv2_read(path):
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127
