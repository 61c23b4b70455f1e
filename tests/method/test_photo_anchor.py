"""The base-photo anchor: which rays are safe, the pose corrections, and that it keeps what L_pres alone loses."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle

from sked_ns.method.photo_anchor import correct_poses, editable_box, rays_away_from_edit, search_box

CENTRE = torch.tensor([0.3, -0.2, 0.1])


def ball_weight(points):
    """w = 0 inside a ball of radius 0.2 around CENTRE, 1 outside (a sketch hull stand-in)."""
    return ((points - CENTRE).norm(dim=-1) > 0.2).float()


def test_editable_box_holds_the_low_weight_points_and_little_else():
    box = editable_box(ball_weight, torch.tensor([[-1.0] * 3, [1.0] * 3]), threshold=0.99, resolution=41)
    assert (box[:3] <= CENTRE - 0.2).all() and (box[3:] >= CENTRE + 0.2).all()
    assert (box[3:] - box[:3]).max() < 0.6  # the ball, a cell of margin, not the scene
    assert editable_box(lambda p: torch.ones(len(p)), torch.tensor([[-1.0] * 3, [1.0] * 3]), 0.99) is None


def test_rays_through_the_hull_are_unsafe_and_the_rest_safe():
    box = editable_box(ball_weight, torch.tensor([[-1.0] * 3, [1.0] * 3]), threshold=0.99, resolution=41)
    origins = torch.tensor([[-3.0, -0.2, 0.1], [-3.0, 0.9, 0.9], [-3.0, -0.2 + 0.24, 0.1 + 0.24], [0.3, -0.2, 3.0]])
    directions = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])  # the last points away
    nears, fars = torch.zeros(4, 1), torch.full((4, 1), 100.0)
    safe = rays_away_from_edit(origins, directions, nears, fars, box, ball_weight, 0.99)
    # Through the ball; far from the box; through the box's corner but outside the ball; away from it.
    assert safe.tolist() == [False, True, True, True]
    # The near plane counts: a ray starting past the ball never meets it.
    assert rays_away_from_edit(origins[:1], directions[:1], torch.full((1, 1), 4.0), fars[:1], box, ball_weight, 0.99)


def test_pose_corrections_match_nerfstudio():
    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=3, device="cpu")
    with torch.no_grad():
        optimizer.pose_adjustment.normal_(std=0.05)
    rays = RayBundle(origins=torch.randn(5, 3), directions=torch.nn.functional.normalize(torch.randn(5, 3), dim=-1),
                     pixel_area=torch.ones(5, 1), camera_indices=torch.tensor([[0], [2], [1], [2], [0]]))
    expected = RayBundle(origins=rays.origins.clone(), directions=rays.directions.clone(), pixel_area=rays.pixel_area,
                         camera_indices=rays.camera_indices)
    with torch.no_grad():
        optimizer.apply_to_raybundle(expected)
        correct_poses(rays, [optimizer])
    torch.testing.assert_close(rays.origins, expected.origins)
    torch.testing.assert_close(rays.directions, expected.directions)


def test_photos_the_base_does_not_explain_turn_the_anchor_off_loudly():
    from sked_ns.method.photo_anchor import SkedPhotoWarning, check_base_explains_photos

    generator = torch.Generator().manual_seed(0)
    photos = torch.rand(400, 3, generator=generator)
    noise = lambda sigma: (photos + sigma * torch.randn(400, 3, generator=generator)).clamp(0, 1)  # noqa: E731
    psnr, anchored = check_base_explains_photos(noise(0.02), photos)
    assert psnr > 30 and anchored  # a trained base: no word
    with pytest.warns(SkedPhotoWarning, match=r"only 1[5-9]\.\d dB.*lambda-photo 0"):
        assert check_base_explains_photos(noise(0.15), photos)[1]
    with pytest.warns(SkedPhotoWarning, match=r"--data: .* \d\.\d dB.*photo anchor is OFF"):
        assert not check_base_explains_photos(torch.rand(400, 3, generator=generator), photos)[1]  # other photos


def test_the_search_grows_past_the_scene_box_to_an_edit_box_there_unless_the_base_is_bounded():
    scene = torch.tensor([[-1.0] * 3, [1.0] * 3])
    low, high = np.array([0.8, -0.1, -0.1]), np.array([1.4, 0.1, 0.1])  # a region on the box's face
    grown = search_box(scene, low, high, 0.5, None)
    assert torch.allclose(grown, torch.tensor([[-1.0] * 3, [1.7, 1.0, 1.0]]).double().to(grown.dtype))
    assert torch.equal(search_box(scene, low, high, 0.5, scene.numpy()), scene)
    inside = search_box(scene, low - [1.0, 0, 0], high - [1.0, 0, 0], 0.5, None)  # near the face, not past it
    assert torch.equal(inside, scene)  # inside the box: searched as before
    centre = torch.tensor([1.2, 0.0, 0.0])
    found = editable_box(lambda p: ((p - centre).norm(dim=-1) > 0.15).float(), grown, 0.99, resolution=41)
    assert found is not None and found[3] >= 1.35  # the far side of a region past the face is found
