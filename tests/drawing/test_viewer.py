"""The viewer side: the sked-sketch panel on a real base, steering controls, the headless CLI."""

from __future__ import annotations

import dataclasses
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from sked_ns.errors import SkedUserError
from sked_ns.sketches.sketch_set import load_sketch_set


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _sked_sketch() -> str:
    return shutil.which("sked-sketch", path=str(Path(sys.executable).parent)) or shutil.which("sked-sketch")


@pytest.fixture(scope="module")
def sketch_viewer(scene, tmp_path_factory):
    from sked_ns.drawing.sketch_viewer import start_viewer, stop_viewer

    out = tmp_path_factory.mktemp("drawn") / "sketches"
    viewer, panel = start_viewer(scene["base"], out, port=_free_port())
    yield {"viewer": viewer, "panel": panel, "out": out}
    stop_viewer(viewer)


def test_panel_without_a_browser_says_so(sketch_viewer):
    panel = sketch_viewer["panel"]
    panel._guarded(panel.capture)
    assert "No viewer client is connected" in panel.last_message
    assert panel.save_button.disabled and panel.add_button.disabled


def test_panel_draws_two_views_and_saves_the_set(scene, sketch_viewer, monkeypatch):
    """Every panel action, with the browser's camera replaced by the hat's sketch cameras."""
    import sked_ns.drawing.sketch_viewer as sketch_viewer_module
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.sketches.cameras import PinholeCamera

    panel = sketch_viewer["panel"]
    transform = panel.session.transform
    base_files = {p: p.read_bytes() for p in scene["base"].rglob("*") if p.is_file()}
    for view in demo_scene.SCENES["hat"].sketch_set(size=48).in_model_frame(transform).views:
        camera = PinholeCamera.from_view(view)
        monkeypatch.setattr(sketch_viewer_module, "client_camera", lambda server, width=512, c=camera: c)
        panel.capture()
        assert not panel.add_button.disabled
        canvas = panel.session.pending.canvas
        assert canvas.shape == (48, 48, 3) and canvas.std() > 0.01, "a real render of the base"
        ys, xs = np.nonzero(view.mask)
        for x, y in [(xs.min(), ys.min()), (xs.max() + 1, ys.min()), (xs.max() + 1, ys.max() + 1), (xs.min(), ys.max() + 1)]:
            panel.click(x / 48, y / 48)
        panel.close_scribble()
        assert panel.pending_handle is not None, "the view being drawn is shown"
        panel.add_view()
        assert panel.pending_handle is None, "an added view leaves no stale pending frustum"
        index = len(panel.session.views) - 1
        shown = panel.session.view_image(index)  # what the saved view's frustum shows
        mask = panel.session.views[index].mask
        assert np.array_equal(shown[~mask], canvas[~mask])
        assert np.allclose(shown[mask], 0.5 * canvas[mask] + 0.5 * np.array([1.0, 0.0, 0.0])), "half red inside"
    assert len(panel.handles) == 3, "two view frusta and the edit box"
    assert "Edit box" in panel.last_message and not panel.save_button.disabled
    path = panel.save()
    saved = load_sketch_set(path.parent)
    assert len(saved.views) == 2 and saved.frame == "data"
    panel._guarded(panel.save)
    assert "never overwritten" in panel.last_message
    assert {p: p.read_bytes() for p in scene["base"].rglob("*") if p.is_file()} == base_files, "base untouched"


def test_headless_canvases_round_trip_through_the_cli(scene, tmp_path):
    canvases = tmp_path / "canvases"
    result = subprocess.run([_sked_sketch(), "canvases", str(scene["base"]), str(canvases), "--images", "0", "5"],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for index in range(2):
        canvas = cv2.imread(str(canvases / f"view_{index:02d}.png"))
        assert canvas is not None and canvas.std() > 2, "the base rendered at a training camera"
        painted = canvas.copy()
        cv2.circle(painted, (48, 20), 10, (0, 0, 255), 2)  # a closed red stroke around the top of the sphere
        cv2.imwrite(str(canvases / f"view_{index:02d}_sketch.png"), painted)
    result = subprocess.run([_sked_sketch(), "import", str(canvases), "--out", str(tmp_path / "sketches")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    sketches = load_sketch_set(tmp_path / "sketches")
    assert all(300 < view.mask.sum() < 500 for view in sketches.views), "the filled circle, about pi 10^2 px"
    bad = subprocess.run([_sked_sketch(), "canvases", str(scene["base"]), str(tmp_path / "c2"), "--images", "99"],
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "--images 99" in bad.stderr


def test_sked_sketch_on_a_folder_that_is_not_a_run(tmp_path):
    result = subprocess.run([_sked_sketch(), str(tmp_path), "--out", str(tmp_path / "s")], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode != 0 and "config.yml" in result.stderr


def test_sked_sketch_takes_the_base_once_as_a_folder_or_as_load_config(tmp_path):
    from sked_ns.drawing.sketch_viewer import entrypoint
    from sked_ns.errors import SkedUserError

    for argv in (["--out", str(tmp_path / "s")], [str(tmp_path), "--load-config", str(tmp_path / "c.yml"), "--out",
                                                   str(tmp_path / "s")]):
        with pytest.raises(SkedUserError, match="give the base once"):
            entrypoint(argv)
    with pytest.raises(SkedUserError, match="--load-config .*nowhere: no such file"):  # named as typed
        entrypoint(["--load-config", str(tmp_path / "nowhere" / "config.yml"), "--out", str(tmp_path / "s")])
    assert not (tmp_path / "s").exists()


def test_steering_controls_change_what_the_viewer_shows(scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.engine.trainer import resolve_edit
    from sked_ns.evaluation.render import render_at, render_base_at

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=2)
    resolve_edit(config)
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    with torch.no_grad():  # make the edit differ from the base
        for parameter in model.local_field.colour_mlp.parameters():  # the default edit's copy of the colour MLP
            parameter.add_(0.5)
    view = model.sketch_set.views[0]
    edit, base = render_at(model, view, 24), render_base_at(model, view, 24)
    assert (edit["rgb"] - base["rgb"]).abs().max() > 0.05
    model.viewer_show_base.value = True
    assert torch.equal(render_at(model, view, 24)["rgb"], base["rgb"])
    model.viewer_show_base.value = False
    from sked_ns.sketches.sketch_set import sketch_view_at

    camera = sketch_view_at(view, 24)[0]
    model.eval()
    with torch.no_grad():
        plain = model.get_outputs_for_camera(camera)
        model.viewer_tint.value = True
        tinted = model.get_outputs_for_camera(camera)
    editable = (plain["preservation_weight"][..., 0] < 0.5)
    changed = (tinted["rgb"] - plain["rgb"]).abs().amax(-1) > 1e-3
    assert changed[editable].all() and not changed[plain["preservation_weight"][..., 0] > 0.999].any()
    before = plain["preservation_weight"].clone()
    model.viewer_beta.value = 0.2
    model.viewer_beta.cb_hook(model.viewer_beta)
    assert model.config.beta == 0.2
    with torch.no_grad():
        wider = model.get_outputs_for_camera(camera)["preservation_weight"]
    assert (wider <= before + 1e-6).all() and (wider < before - 0.05).any(), "a larger beta preserves less"
    model.viewer_beta.value = -1.0
    with pytest.raises(ValueError):
        model.viewer_beta.cb_hook(model.viewer_beta)


def test_cpu_preview_is_a_downscaled_render_of_the_same_view(scene):
    """The captured view's backdrop, rendered narrower on a CPU, shows the same picture."""
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.drawing.sketch_viewer import load_base, renderer
    from sked_ns.sketches.cameras import PinholeCamera

    _, pipeline, transform = load_base(scene["base"], "cpu")
    view = demo_scene.SCENES["hat"].sketch_set(size=64).in_model_frame(transform).views[0]
    camera = dataclasses.replace(PinholeCamera.from_view(view), height=48)  # not square: both axes scale
    full = renderer(pipeline)(camera)
    assert np.array_equal(renderer(pipeline, max_width=64)(camera), full), "no resize when it fits"
    preview = renderer(pipeline, max_width=32)(camera)
    assert preview.shape == full.shape == (48, 64, 3)
    error = np.abs(cv2.GaussianBlur(preview, (5, 5), 1.5) - cv2.GaussianBlur(full, (5, 5), 1.5)).mean()
    flipped = np.abs(cv2.GaussianBlur(preview[::-1], (5, 5), 1.5) - cv2.GaussianBlur(full, (5, 5), 1.5)).mean()
    assert error < 0.02 and error < flipped / 3, (error, flipped)


def test_capture_pressed_again_while_rendering_is_ignored(sketch_viewer):
    panel = sketch_viewer["panel"]
    pending = panel.session.pending
    with panel._capturing:  # a capture in progress
        panel._guarded(panel.capture)
    assert "Still rendering" in panel.last_message and panel.session.pending is pending


def test_sked_sketch_refuses_an_existing_set_and_a_bad_port_before_loading_anything(tmp_path):
    from sked_ns.drawing.sketch_viewer import entrypoint

    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "sketches.json").write_text("{}")
    for argv in (["no-base", "--out", str(tmp_path / "done")], ["import", "no-canvases", "--out", str(tmp_path / "done")]):
        with pytest.raises(SkedUserError, match=r"--out .*done already holds a sketch set"):
            entrypoint(argv)
    assert (tmp_path / "done" / "sketches.json").read_text() == "{}"
    with pytest.raises(SkedUserError, match="argument --port: '70000' is not a port number"):
        entrypoint(["no-base", "--out", str(tmp_path / "new"), "--port", "70000"])


def test_a_slow_capture_says_how_long_it_has_been_rendering(scene, sketch_viewer, monkeypatch):
    import time

    import sked_ns.drawing.sketch_viewer as sketch_viewer_module
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.sketches.cameras import PinholeCamera

    panel = sketch_viewer["panel"]
    camera = PinholeCamera.from_view(demo_scene.SCENES["hat"].sketch_set(size=16).views[0])
    monkeypatch.setattr(sketch_viewer_module, "client_camera", lambda server, width=512: camera)
    monkeypatch.setattr(sketch_viewer_module, "CAPTURE_BEAT_SECONDS", 0.05)
    monkeypatch.setattr(panel.session, "render", lambda c: (time.sleep(0.4), np.zeros((c.height, c.width, 3)))[1])
    said, say = [], panel._say
    monkeypatch.setattr(panel, "_say", lambda line: (said.append(line), say(line)))
    previous = panel.session.pending
    try:
        panel.capture()
    finally:
        panel.session.pending = previous
        panel.server.scene.remove_pointer_callback()
        panel._set_drawing(False)
    assert said[0] == "Rendering the captured view..."
    assert any(line.startswith("Still rendering the captured view (") for line in said[1:-2]), said
    assert said[-1].startswith("Click the points"), said



def _look_at_pose(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A 3x4 OpenGL camera-to-world at `position` looking at `target`."""
    forward = np.asarray(target, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    return np.stack([right, true_up, -forward, np.asarray(position, float)], axis=1)


def test_the_viewer_opens_on_the_point_the_photos_look_at_from_where_they_were_taken(rng):
    from sked_ns.engine.viewer import scene_framing

    target = np.array([0.3, -0.2, 0.1])
    angles = rng.uniform(0, 2 * np.pi, 12)
    positions = np.stack([2 * np.cos(angles), 2 * np.sin(angles), rng.uniform(0.5, 1.0, 12)], axis=1) + target
    poses = np.stack([_look_at_pose(p, target) for p in positions])
    position, look_at, up = scene_framing(poses)
    assert np.allclose(look_at, target, atol=1e-9)
    assert any(np.allclose(position, p) for p in positions)  # a pose the photos were taken from
    assert up[2] > 0.8
    parallel = np.stack([_look_at_pose(p, p + np.array([0.0, 1.0, 0.0])) for p in positions[:4] * [1, 0, 1]])
    assert np.allclose(scene_framing(parallel)[1], 0.0)  # axes that never meet: the origin nerfstudio centres on
