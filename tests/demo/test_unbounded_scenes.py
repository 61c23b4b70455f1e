"""The unbounded benchmark scene (issue 22): a ground to the horizon, a sky, low cameras that see both."""

import json

import numpy as np
import pytest
import torch

from sked_ns.demo.scenes import unbounded as unbounded_scenes
from sked_ns.demo.scenes.catalogue import scene_named, write_benchmark
from sked_ns.demo.scenes.objects import eval_indices, visible_added_part
from sked_ns.demo.scenes.unbounded import FOCAL, SCENES, capture_pose, capture_poses, sky, trace_unbounded
from sked_ns.sketches.random_views import look_at


def test_rays_that_miss_show_the_sky_and_downward_rays_hit_the_ground_exactly():
    scene = SCENES["lawn"]
    up = look_at(np.array([2.0, -2.0, 0.4]), np.array([7.0, -2.0, 3.0]))  # looks up and away: sky only
    render = scene.render_base(up, 40.0, 16, 16)
    assert not render["hit"].any()
    directions = torch.nn.functional.normalize(render["points"] - torch.tensor([2.0, -2.0, 0.4]), dim=-1)
    assert torch.allclose(render["rgb"], sky(directions), atol=1e-4)
    # Looking down from far away, past every object: every pixel is ground, at z = 0 to float precision.
    down = look_at(np.array([20.0, -20.0, 1.0]), np.array([21.0, -21.0, 0.0]))
    render = trace_unbounded(scene.base_parts, down, 40.0, 16, 16)
    assert render["hit"].all()
    assert render["points"][..., 2].abs().max() < 1e-4


def test_the_capture_sees_the_horizon_and_the_added_part_touches_the_block():
    scene = SCENES["lawn"]
    low = [pose for index, pose in enumerate(capture_poses()) if index % 3 < 2]  # the two lower rings
    sky_fraction = [float((~scene.render_base(pose, FOCAL / 4, 32, 32)["hit"]).float().mean()) for pose in low[::4]]
    assert min(sky_fraction) > 0.05, sky_fraction  # every low photo shows sky: the scene is unbounded
    # The stem stands on the block's top (an existing surface), not in the air.
    top = torch.tensor([[0.1, 0.0, unbounded_scenes.BLOCK_TOP]])
    assert scene.edit_sdf(top).abs().item() < 0.021  # the stem's radius
    for azimuth, elevation in scene.sketch_views:  # the lamp shows at every sketch view
        visible = visible_added_part(scene, capture_pose(azimuth, elevation), FOCAL / 2, 64, 64)["visible"]
        assert visible.sum() > 10


def test_write_benchmark_writes_a_nerfstudio_dataset_its_target_and_sketches(tmp_path):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    assert scene_named("lawn") is SCENES["lawn"]
    paths = write_benchmark("lawn", tmp_path, count=10, size=32)
    outputs = NerfstudioDataParserConfig(data=paths["data"]).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) == 9
    target = json.loads((paths["target"] / "transforms.json").read_text())
    assert [frame["changed_mask_path"] for frame in target["frames"]] == [
        f"images/frame_{index:03d}_changed.png" for index in eval_indices(10)]
    sketches = json.loads((paths["sketches"] / "sketches.json").read_text())
    assert len(sketches["views"]) == 3


@pytest.mark.parametrize("name", sorted(SCENES))
def test_reference_guidance_finds_the_scene(name):
    from sked_ns.demo.reference_guidance import reference_scene

    assert reference_scene(name) is SCENES[name]
