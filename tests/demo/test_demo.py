"""The README's main command: the demo edit, end to end on the CPU."""

from __future__ import annotations

import json

import cv2
import pytest

from sked_ns.demo.run import run


@pytest.mark.slow
def test_demo_edits_the_scene_and_reports(tmp_path):
    summary = run(tmp_path / "demo", size=48, iterations=30, base_steps=300)
    assert summary["guidance"] == "reference"  # no diffusion weights here, and no prompt
    assert summary["mean_weight_on_hat"] < 0.05  # the sketched hat may change
    assert summary["mean_weight_on_sphere"] > 0.6  # most of the base is kept
    for path in summary["images"]:
        assert cv2.imread(path) is not None
    for view in summary["views"]:
        assert view["ios_edit"] > view["ios_base"]  # the hat grew into the sketches
    assert json.loads((tmp_path / "demo" / "summary.json").read_text())["iterations"] == 30


def test_prompt_without_weights_falls_back_to_reference(tmp_path, monkeypatch, capsys):
    from sked_ns.demo.run import choose_guidance

    monkeypatch.setenv("HF_HOME", str(tmp_path / "empty-cache"))
    assert choose_guidance("a red hat", "CompVis/stable-diffusion-v1-4") == "reference"
    assert "reference guidance" in capsys.readouterr().out


def test_demo_never_writes_into_a_foreign_folder(tmp_path):
    (tmp_path / "mine.txt").write_text("user data")
    with pytest.raises(FileExistsError, match="not made by sked-demo"):
        run(tmp_path, size=32)
    assert (tmp_path / "mine.txt").read_text() == "user data"
