"""The authors' layout: conversion keeps every ray, and the cat's hat lands above its head."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sked_ns.drawing.authors_import import Y_UP_TO_Z_UP, import_authors_sketches, read_authors_meta
from sked_ns.method.edit_box import compute_edit_box
from sked_ns.sketches.cameras import project
from sked_ns.sketches.sketch_set import load_sketch_set, save_sketch_set

CAT = Path(__file__).resolve().parents[1] / "data" / "sked-authors-cat"


def test_reads_their_metadata_saved_from_cuda():
    intrinsics, poses = read_authors_meta(CAT / "meta_data.pkl")
    np.testing.assert_allclose(intrinsics, [305.0889197, 305.0889197, 256, 256])
    assert poses.shape == (2, 4, 4)
    radius = np.linalg.norm(poses[:, :3, 3], axis=1)
    np.testing.assert_allclose(radius, 1.5, atol=1e-3)


def test_imported_views_see_the_same_pixels_as_the_authors_projection():
    intrinsics, poses = read_authors_meta(CAT / "meta_data.pkl")
    sketches = import_authors_sketches(CAT)
    rng = np.random.default_rng(1)
    points_theirs = rng.uniform(-0.6, 0.6, (500, 3))
    fx, fy, cx, cy = intrinsics
    for pose, view in zip(poses, sketches.views):
        # Their projection (code/utils/rend_utils.py): [X, Y, Z] = (p - t) R; u = fx X / Z + cx.
        local = (points_theirs - pose[:3, 3]) @ pose[:3, :3]
        u_theirs = fx * local[:, 0] / local[:, 2] + cx
        v_theirs = fy * local[:, 1] / local[:, 2] + cy
        points_ours = torch.tensor(points_theirs @ Y_UP_TO_Z_UP.T)
        pixels, depth = project(points_ours, torch.tensor(view.camera_to_world[None]), torch.tensor(view.intrinsics[None]))
        assert (depth[0] > 0).all()
        np.testing.assert_allclose(pixels[0, :, 0].numpy(), view.width - u_theirs, atol=1e-6)  # mirrored canvas
        np.testing.assert_allclose(pixels[0, :, 1].numpy(), v_theirs, atol=1e-6)


def test_masks_are_their_canvases_mirrored():
    import cv2

    sketches = import_authors_sketches(CAT)
    canvas = cv2.imread(str(CAT / "sketches" / "canvas_00.png"), cv2.IMREAD_UNCHANGED)
    theirs = canvas[..., 3] > 127
    mirrored = sketches.views[0].mask[:, ::-1]
    assert (mirrored == theirs).mean() > 0.995
    assert sketches.frame == "model" and len(sketches.views) == 2


def test_edit_box_sits_above_the_cat(tmp_path):
    sketches = import_authors_sketches(CAT)
    box = compute_edit_box(sketches.views)
    assert box.min[2] > 0.2 and np.all(box.size > 0.1) and np.all(box.size < 1.0)
    # And the imported set survives our own format.
    save_sketch_set(sketches, tmp_path / "cat")
    again = load_sketch_set(tmp_path / "cat")
    np.testing.assert_allclose(compute_edit_box(again.views).min, box.min, atol=1e-9)


def test_bad_folders(tmp_path):
    with pytest.raises(FileNotFoundError, match="meta_data.pkl"):
        import_authors_sketches(tmp_path)
    (tmp_path / "meta_data.pkl").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="meta_data.pkl"):
        import_authors_sketches(tmp_path)


def test_the_command_replaces_a_sketch_set_only_with_overwrite(tmp_path, capsys):
    from sked_ns.drawing.authors_import import entrypoint
    from sked_ns.errors import SkedUserError

    entrypoint([str(CAT), str(tmp_path / "cat")])
    with pytest.raises(SkedUserError, match=r"cat/sketches.json already exists.*--overwrite") as error:
        entrypoint([str(CAT), str(tmp_path / "cat")])
    assert "overwrite=True" not in str(error.value)
    entrypoint([str(CAT), str(tmp_path / "cat"), "--overwrite"])
    assert capsys.readouterr().out.count("wrote") == 2 and len(load_sketch_set(tmp_path / "cat").views) == 2
