"""Random views: the authors' angle ranges around the edit box, directional labels, look-at jitter."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch

from sked_ns.engine.datamanager import SkedDataManagerConfig
from sked_ns.sketches.random_views import RandomViewSampler, orbit_position

CENTRE = np.array([0.3, -0.2, 0.5])


def _samples(sampler, count, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return [sampler.sample(generator) for _ in range(count)]


def _polar_deg(pose, centre):
    offset = pose[:, 3] - centre
    return math.degrees(math.acos(offset[2] / np.linalg.norm(offset)))


def test_the_datamanager_uses_the_authors_ranges():
    config = SkedDataManagerConfig()
    assert tuple(config.elevation_range) == (-60.0, 90.0)  # polar angle 0-150 deg
    assert tuple(config.fov_range) == (40.0, 80.0)
    sampler = RandomViewSampler(centre=CENTRE, radius=2.0)
    assert (sampler.elevation_range_deg, sampler.fov_range_deg) == (tuple(config.elevation_range), tuple(config.fov_range))


def test_views_are_uniform_in_polar_angle_and_every_direction_is_used():
    sampler = RandomViewSampler(centre=CENTRE, radius=2.0, front_azimuth_deg=30.0)
    samples = _samples(sampler, 4000)
    polar = np.array([_polar_deg(pose, CENTRE) for pose, _, _ in samples])
    labels = [direction for _, _, direction in samples]
    counts = Counter(labels)
    assert {"front", "side", "back", "overhead"} <= set(counts) and "bottom" not in counts
    assert polar.min() >= 0.0 and polar.max() <= 150.0 + 1e-6
    # Uniform in the angle: a fifth within 30 deg of the top (uniform over the sphere would give 7%).
    assert counts["overhead"] / len(samples) == pytest.approx(30 / 150, abs=0.025)
    assert np.histogram(polar, bins=5, range=(0, 150))[0] / len(samples) == pytest.approx([0.2] * 5, abs=0.03)
    for (pose, _, direction), angle in zip(samples, polar):
        assert (direction == "overhead") == (angle < 30.0 - 1e-9)
    fov = np.array([fov for _, fov, _ in samples])
    assert fov.min() >= 40.0 and fov.max() <= 80.0 and fov.min() < 42.0 and fov.max() > 78.0


def test_every_view_looks_at_the_centre_and_front_faces_the_first_sketch():
    first_sketch = np.eye(4)[:3]
    first_sketch[:, 3] = CENTRE + orbit_position(50.0, 10.0, 2.0)
    sampler = RandomViewSampler.around_sketches(CENTRE, [first_sketch, first_sketch])
    for pose, _, direction in _samples(sampler, 300):
        to_centre = CENTRE - pose[:, 3]
        np.testing.assert_allclose(-pose[:, 2], to_centre / np.linalg.norm(to_centre), atol=1e-9)
        if direction == "front":  # within 30 deg of the first sketch's azimuth
            offset = pose[:, 3] - CENTRE
            azimuth = math.degrees(math.atan2(offset[0], -offset[1]))
            assert abs((azimuth - 50.0 + 180.0) % 360.0 - 180.0) < 30.0


def test_look_at_jitter_moves_the_target_in_every_direction(monkeypatch):
    from sked_ns.sketches import random_views

    targets = []
    look_at = random_views.look_at
    monkeypatch.setattr(random_views, "look_at", lambda position, target: targets.append(target) or look_at(position, target))
    _samples(RandomViewSampler(centre=CENTRE, radius=2.0, jitter=0.2), 200)
    offsets = np.array(targets) - CENTRE
    assert np.abs(offsets).max() <= 0.2 * 2.0 / 2 + 1e-12  # within jitter x radius / 2 per axis
    diagonal = np.ones(3) / math.sqrt(3)
    off_diagonal = offsets - np.outer(offsets @ diagonal, diagonal)
    assert np.linalg.norm(off_diagonal, axis=1).max() > 0.05  # not all along (1, 1, 1)


def test_the_sampler_is_deterministic_given_the_generator():
    sampler = RandomViewSampler(centre=CENTRE, radius=2.0, jitter=0.1)
    first, again = _samples(sampler, 20, seed=7), _samples(sampler, 20, seed=7)
    for (pose_a, fov_a, dir_a), (pose_b, fov_b, dir_b) in zip(first, again):
        np.testing.assert_array_equal(pose_a, pose_b)
        assert fov_a == fov_b and dir_a == dir_b


def _box_span_deg(sampler):
    """The edit box's bounding sphere seen from the orbit's distance: its angular diameter."""
    return 2 * math.degrees(math.asin(sampler.edit_radius / sampler.radius))


def test_a_small_edit_is_framed_at_edit_fill_of_the_range_middle():
    """A part small beside the scene (bounding sphere 0.2 at distance 2: 11.5 deg) would span a fifth of a 60 deg
    view; the range is narrowed in proportion until it spans edit_fill there."""
    sampler = RandomViewSampler(centre=CENTRE, radius=2.0, edit_radius=0.2, edit_fill=0.7)
    low, high = (sampler.fov_scale * value for value in sampler.fov_range_deg)
    assert high / low == pytest.approx(2.0)  # the authors' proportions kept
    assert _box_span_deg(sampler) / ((low + high) / 2) == pytest.approx(0.7)
    fovs = [fov for _, fov, _ in _samples(sampler, 400)]
    assert low - 1e-9 <= min(fovs) and max(fovs) <= high + 1e-9
    assert min(fovs) < low + 2 and max(fovs) > high - 2  # the whole narrowed range is drawn


@pytest.mark.parametrize("edit_radius, edit_fill", [(1.5, 0.7), (0.2, 0.0), (0.0, 0.7), (5.0, 1.0)])
def test_a_large_edit_or_no_framing_keeps_the_authors_range(edit_radius, edit_fill):
    """Never wider than the authors' range: an edit box that already spans edit_fill (or a camera inside its
    bounding sphere) keeps 40-80 deg, and so does edit_fill 0 or an unknown box."""
    sampler = RandomViewSampler(centre=CENTRE, radius=2.0, edit_radius=edit_radius, edit_fill=edit_fill)
    assert sampler.fov_scale == 1.0
    fovs = [fov for _, fov, _ in _samples(sampler, 200)]
    assert 40.0 <= min(fovs) and max(fovs) <= 80.0 and max(fovs) - min(fovs) > 35


def test_edit_fill_is_validated_and_a_frame_filled_by_the_edit_warns():
    from sked_ns.errors import SkedUserError
    from sked_ns.method.options import SkedOptions
    from sked_ns.method.validation import check_options

    assert SkedDataManagerConfig().edit_fill == 0.7
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises((SkedUserError, ValueError), match="edit-fill"):
            check_options(SkedOptions(), SkedDataManagerConfig(edit_fill=bad))
    with pytest.warns(UserWarning, match="edit-fill"):
        check_options(SkedOptions(), SkedDataManagerConfig(edit_fill=0.95))
