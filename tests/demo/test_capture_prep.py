"""benchmarks/capture_prep.py: an instant-ngp capture (the fox's layout) becomes a nerfstudio-data dataset."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sked_ns.errors import SkedUserError

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import capture_prep  # noqa: E402

WIDTH, HEIGHT = 36, 64
CAMERA = {"camera_angle_x": 0.75, "fl_x": 46.0, "fl_y": 45.5, "k1": 0.058, "k2": -0.081, "p1": -0.00098,
          "p2": 0.00016, "cx": 18.4, "cy": 32.2, "w": float(WIDTH), "h": float(HEIGHT), "aabb_scale": 4}


def _pose(index):
    angle = 0.3 * index
    return [[np.cos(angle), 0.0, np.sin(angle), 3 * np.sin(angle)], [0.0, 1.0, 0.0, 0.2 * index],
            [-np.sin(angle), 0.0, np.cos(angle), 3 * np.cos(angle)], [0.0, 0.0, 0.0, 1.0]]


@pytest.fixture
def ngp_capture(tmp_path):
    """An instant-ngp clone's layout: data/nerf/fox with transforms.json listing six photos, two of them absent."""
    folder = tmp_path / "instant-ngp" / "data" / "nerf" / "fox"
    (folder / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    frames = []
    for index in range(6):
        name = f"images/{index + 1:04d}.jpg"
        if index not in (2, 4):
            cv2.imwrite(str(folder / name), rng.integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8))
        frames.append({"file_path": name, "sharpness": 30.0, "transform_matrix": _pose(index)})
    (folder / "transforms.json").write_text(json.dumps({**CAMERA, "frames": frames}))
    return tmp_path / "instant-ngp"


def _digest(folder: Path) -> str:
    return hashlib.sha256(b"".join(p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file())).hexdigest()


def test_the_capture_becomes_nerfstudio_data_at_its_new_size_missing_photos_dropped(ngp_capture, tmp_path, capsys):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    before = _digest(ngp_capture)
    written = capture_prep.prepare(ngp_capture, tmp_path / "fox-2", downscale=2)
    printed = capsys.readouterr().out.splitlines()
    assert sum("missing" in line for line in printed) == 1 and printed[0].startswith("2 of the 6 images")
    meta = json.loads(written.read_text())
    assert (meta["camera_model"], meta["w"], meta["h"]) == ("OPENCV", WIDTH // 2, HEIGHT // 2)
    assert meta["fl_x"] == pytest.approx(23.0) and meta["fl_y"] == pytest.approx(22.75)
    assert (meta["cx"], meta["cy"]) == (pytest.approx(9.2), pytest.approx(16.1))
    assert all(meta[key] == CAMERA[key] for key in ("k1", "k2", "p1", "p2"))  # normalised coordinates: unscaled
    assert [frame["transform_matrix"] for frame in meta["frames"]] == [_pose(i) for i in (0, 1, 3, 5)]
    photo = cv2.imread(str(written.parent / meta["frames"][0]["file_path"]))
    source = cv2.imread(str(ngp_capture / "data/nerf/fox/images/0001.jpg")).astype(np.float32)
    assert photo.shape == (HEIGHT // 2, WIDTH // 2, 3)
    assert np.abs(photo - source.reshape(HEIGHT // 2, 2, WIDTH // 2, 2, 3).mean(axis=(1, 3))).max() <= 1  # area mean
    assert _digest(ngp_capture) == before  # the capture is only read
    outputs = NerfstudioDataParserConfig(data=written.parent, center_method="focus").setup().get_dataparser_outputs(
        "train")
    assert outputs.cameras.distortion_params.abs().sum() > 0 and int(outputs.cameras.width[0]) == WIDTH // 2


def test_the_folder_alone_is_a_source_too(ngp_capture, tmp_path):
    written = capture_prep.prepare(ngp_capture / "data/nerf/fox", tmp_path / "out", downscale=1)
    assert len(json.loads(written.read_text())["frames"]) == 4


@pytest.mark.parametrize("case, pattern", [
    ("no source", r"^SOURCE \S+: no such folder"),
    ("no transforms", r"^SOURCE \S+: neither \S+transforms.json nor \S+transforms.json exists"),
    ("downscale 0", r"^--downscale 0: a whole number >= 1"),
    ("output not empty", r"^OUTPUT \S+: not empty. Pass --overwrite"),
])
def test_bad_input_is_one_line_before_anything_is_written(ngp_capture, tmp_path, case, pattern):
    source, output, downscale = ngp_capture, tmp_path / "out", 8
    if case == "no source":
        source = tmp_path / "nowhere"
    elif case == "no transforms":
        source = tmp_path / "empty"
        source.mkdir()
    elif case == "downscale 0":
        downscale = 0
    else:
        output.mkdir()
        (output / "notes.txt").write_text("mine")
    with pytest.raises(SkedUserError, match=pattern) as refused:
        capture_prep.prepare(source, output, downscale)
    assert "\n" not in str(refused.value)
    assert not (output / "transforms.json").exists() and not (output / "images").exists()
