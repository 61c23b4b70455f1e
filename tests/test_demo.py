"""The README's demo: sketches of the demo scene, through the dataparser, to a weight image."""

from __future__ import annotations

import json

import cv2
import pytest

from sked_ns.demo import run


def test_demo_marks_the_hat_editable_and_keeps_the_sphere(tmp_path):
    summary = run(tmp_path / "demo", size=64)
    image = cv2.imread(summary["image"])
    assert image is not None and image.shape == (64, 3 * 64, 3)
    assert summary["mean_weight_on_hat"] < 0.05  # the sketched hat may change
    assert summary["mean_weight_on_sphere"] > 0.6  # most of the base is kept
    assert json.loads((tmp_path / "demo" / "summary.json").read_text())["beta"] == 0.025
    run(tmp_path / "demo", size=32)  # a rerun may replace its own output


def test_demo_never_writes_into_a_foreign_folder(tmp_path):
    (tmp_path / "mine.txt").write_text("user data")
    with pytest.raises(FileExistsError, match="not made by sked-demo"):
        run(tmp_path, size=32)
    assert (tmp_path / "mine.txt").read_text() == "user data"
