"""The random view's rays made on the device (cameras.pinhole_rays) are nerfstudio's generate_rays, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.demo.scenes.sphere import look_at
from sked_ns.sketches.cameras import cameras_of, pinhole_rays


@pytest.mark.parametrize("size, focal", [(1, 1.0), (16, 20.0), (33, 7.3), (64, 1e4)])
def test_pinhole_rays_are_nerfstudios(size, focal):
    pose = torch.tensor(look_at(np.array([1.0, -2.0, 1.5]), np.array([0.1, 0.0, -0.2])), dtype=torch.float32)
    reference = cameras_of(pose[None], focal, focal, size / 2, size / 2, size, size).generate_rays(
        camera_indices=0, keep_shape=True)
    ours = pinhole_rays(pose, focal, size)
    for name in ("origins", "directions", "pixel_area", "camera_indices"):
        assert torch.equal(getattr(ours, name), getattr(reference, name)), name
    assert torch.equal(ours.metadata["directions_norm"], reference.metadata["directions_norm"])
    assert ours.times is None and ours.nears is None
