"""The reference guidance samples its target as the edit's render was sampled (splat supersampling)."""

import numpy as np
import pytest
import torch

from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig
from sked_ns.demo.scenes.catalogue import scene_named
from sked_ns.demo.scenes.objects import CAMERA_RADIUS
from sked_ns.demo.scenes.sphere import orbit_pose
from sked_ns.guidance import RenderedView

SIZE = 24


class _Identity:
    """A dataparser transform that leaves poses as they are (the model frame is the data frame)."""

    @staticmethod
    def invert(camera_to_world):
        return camera_to_world


def _guidance(sampling="as-rendered"):
    guidance = ReferenceGuidanceConfig(target="vase", sampling=sampling).setup()
    guidance.prepare(None, "cpu", {"dataparser_transform": _Identity()})
    return guidance


def _view(samples_per_side, image=None, base_image=None):
    pose = orbit_pose(30.0, 20.0, CAMERA_RADIUS)
    image = torch.zeros(1, 3, SIZE, SIZE) if image is None else image
    return RenderedView(image=image, camera_to_world=pose, focal=1.1 * SIZE, direction="front",
                        base_image=base_image, samples_per_side=samples_per_side)


def _plain_target(factor):
    """A plain reference: the analytic target and base at factor x the size, each pixel the mean of its block."""
    scene, pose = scene_named("vase"), orbit_pose(30.0, 20.0, CAMERA_RADIUS)
    size = (1.1 * SIZE * factor, SIZE * factor, SIZE * factor)
    target, base = scene.render_target(pose, *size)["rgb"], scene.render_base(pose, *size)["rgb"]
    colour, changed_colour, changed = (torch.zeros(SIZE, SIZE, 3), torch.zeros(SIZE, SIZE, 3),
                                       torch.zeros(SIZE, SIZE, 1))
    for y in range(SIZE):
        for x in range(SIZE):
            for dy in range(factor):
                for dx in range(factor):
                    sample, under = target[y * factor + dy, x * factor + dx], base[y * factor + dy, x * factor + dx]
                    differs = float((sample - under).abs().max() > 1e-3)
                    colour[y, x] += sample / factor ** 2
                    changed_colour[y, x] += differs * sample / factor ** 2
                    changed[y, x] += differs / factor ** 2
    return [value.permute(2, 0, 1)[None] for value in (colour, changed_colour, changed)]


@pytest.mark.parametrize("factor", [1, 3])
def test_target_is_the_mean_of_its_samples(factor):
    produced = _guidance().target_image(_view(factor))
    for fast, plain in zip(produced, _plain_target(factor)):
        assert fast.shape == plain.shape and torch.allclose(fast, plain, atol=1e-5)


def test_a_supersampled_view_gets_a_part_thinner_than_a_pixel_as_a_share_of_it():
    """The vase's stem is under a 24 px pixel wide: sampled once, each pixel shows it whole or not at all."""
    _, _, point_share = _guidance("pixel-centre").target_image(_view(4))
    _, _, area_share = _guidance().target_image(_view(4))
    assert set(point_share.unique().tolist()) <= {0.0, 1.0}  # pixel-centre ignores how the view was sampled
    partial = (area_share > 0.05) & (area_share < 0.95)
    assert int(partial.sum()) >= 5
    assert torch.equal(_guidance("pixel-centre").target_image(_view(4))[0], _guidance().target_image(_view(1))[0])


def test_loss_is_zero_at_the_target_composed_with_the_base_render():
    """Each pixel's reference: the target over its changed samples, the frozen base's render over the rest."""
    guidance = _guidance()
    base_image = torch.rand(1, 3, SIZE, SIZE)
    _, changed_colour, changed = guidance.target_image(_view(4))
    expected = changed_colour + (1 - changed) * base_image
    assert float(guidance(_view(4, expected, base_image), 0)["reference_loss"]) < 1e-10
    moved = expected + 0.1 * changed  # only where the part is: the loss must see it
    assert float(guidance(_view(4, moved, base_image), 0)["reference_loss"]) > 1e-5
    # Without a base render the analytic target is the reference everywhere.
    target, _, _ = guidance.target_image(_view(4))
    assert float(guidance(_view(4, target), 0)["reference_loss"]) < 1e-10
    assert np.isfinite(float(guidance(_view(4, torch.ones(1, 3, SIZE, SIZE), base_image), 0)["reference_loss"]))
