"""CLIP similarity: loaded only from local files, and equal to CLIP's own forward pass."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_clip import build_tiny_clip

from sked_ns.evaluation.clip_score import CLIP_MEAN, CLIP_STD, ClipScorer, orbit_cameras


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    return build_tiny_clip(tmp_path_factory.mktemp("clip"))


def test_similarity_equals_clips_own_logits(tiny_clip):
    scorer, reason = ClipScorer.load(str(tiny_clip))
    assert reason is None
    generator = torch.Generator().manual_seed(0)
    images = [torch.rand(32, 32, 3, generator=generator) for _ in range(3)]
    ours = scorer.similarity(images, "a cat wearing a chef hat")
    # Reference: CLIPModel.forward's logits are exp(logit_scale) x cosine similarity.
    pixels = (torch.stack([image.permute(2, 0, 1) for image in images]) - torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)) \
        / torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    tokens = scorer.tokenizer(["a cat wearing a chef hat"], padding="max_length", return_tensors="pt")
    with torch.no_grad():
        output = scorer.model(input_ids=tokens["input_ids"], attention_mask=tokens["attention_mask"], pixel_values=pixels)
    reference = (output.logits_per_image[:, 0] / scorer.model.logit_scale.exp()).tolist()
    np.testing.assert_allclose(ours, reference, rtol=1e-4, atol=1e-5)
    assert len(set(np.round(ours, 6))) == 3, "different images, different scores"


def test_missing_clip_weights_are_reported_not_faked(tmp_path):
    scorer, reason = ClipScorer.load(str(tmp_path / "no-clip-here"))
    assert scorer is None and reason.startswith("unavailable") and "no-clip-here" in reason


def test_orbit_cameras_look_at_the_centre():
    centre = np.array([0.1, -0.2, 0.3])
    poses = orbit_cameras(centre, 2.0, count=40)
    assert len(poses) == 40
    for pose in poses:
        assert np.linalg.norm(pose[:, 3] - centre) == pytest.approx(2.0)
        forward = -pose[:, 2]
        np.testing.assert_allclose(forward, (centre - pose[:, 3]) / 2.0, atol=1e-9)
    azimuths = {round(float(np.degrees(np.arctan2(p[0, 3] - centre[0], -(p[1, 3] - centre[1])))) % 360) for p in poses}
    assert len(azimuths) == 40, "40 distinct directions around the object"
