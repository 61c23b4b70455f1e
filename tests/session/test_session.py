"""The edit session (`ns-train sked` without --sketches): sketch in the viewer, Start edit, Edit again, go back.

The panel's actions are called as its buttons call them, with the browser's camera replaced by sketch cameras of the
demo scene (tests/drawing/test_browser.py drives the same session through Chromium).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml
from session_helpers import SessionThread, session_config

from sked_ns.sketches.sketch_set import load_sketch_set


def draw(panel, views, monkeypatch, scale: float = 1.0) -> None:
    """Capture each view's camera and outline its mask's bounding box (shrunk by `scale`), as clicks would."""
    import sked_ns.drawing.sketch_viewer as sketch_viewer_module
    from sked_ns.sketches.cameras import PinholeCamera

    sketch = panel.sketch
    for view in views:
        camera = PinholeCamera.from_view(view)
        monkeypatch.setattr(sketch_viewer_module, "client_camera", lambda server, width=512, c=camera: c)
        sketch.capture()
        ys, xs = np.nonzero(view.mask)
        centre, half = np.array([xs.mean(), ys.mean()]), scale * np.array([np.ptp(xs) + 1, np.ptp(ys) + 1]) / 2
        for corner in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            x, y = (centre + np.array(corner) * half) / np.array([view.width, view.height])
            sketch.click(float(x), float(y))
        sketch.add_view()


@pytest.fixture(scope="module")
def tiny_sd_folder(tmp_path_factory):
    from tiny_sd import build_tiny_stable_diffusion

    return build_tiny_stable_diffusion(tmp_path_factory.mktemp("sd"))


def test_a_session_sketches_edits_and_edits_again_then_resumes(scene, tmp_path, tiny_sd_folder, monkeypatch):
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.engine.edit_run import resume_config, run_edit

    config = session_config(scene, tmp_path / "out", tiny_sd_folder)
    running = SessionThread(config)
    run = config.get_base_dir()
    assert not (run / "config.yml").exists(), "config.yml waits for the sketch set it names"
    session = running.session
    panel = session.panel
    try:
        assert panel.start_button.disabled and "Training waits" in panel.last_message
        assert panel.prompt() is None and "carves" in panel.prompt_note.content
        transform = panel.sketch.session.transform
        hat = demo_scene.SCENES["hat"].sketch_set(size=48).in_model_frame(transform).views
        draw(panel, hat[:1], monkeypatch)
        panel._guarded(panel.start)
        assert "at least two" in panel.last_message and panel.requests.empty()
        draw(panel, hat[1:], monkeypatch)
        assert not panel.start_button.disabled
        panel.prompt_text.value = "a red chef hat"
        panel._prompt_changed()
        assert "Stable Diffusion" in panel.prompt_note.content
        guidance = running.trainer.config.pipeline.model.guidance
        guidance.model, sd = str(tmp_path / "no-weights"), guidance.model
        panel.start()  # the edit's own input checks refuse it: said in the panel, the views kept, nothing saved
        running.wait(lambda: "**Error:**" in panel.last_message, "the refusal")
        assert "no-weights" in panel.last_message and len(panel.sketch.session.views) == 2
        assert not (run / "sketches").exists() and not (run / "config.yml").exists() and not session.rounds
        assert not panel.start_button.disabled
        guidance.model = sd
        panel.start()
        running.wait(lambda: len(session.rounds) == 1, "round 1")
        saved = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
        assert Path(saved.pipeline.model.sketches) == run / "sketches" and saved.pipeline.model.prompt == "a red chef hat"
        assert len(load_sketch_set(run / "sketches").views) == 2
        running.wait(lambda: "is done" in panel.last_message, "round 1's steps")
        assert sorted(p.name for p in (run / "nerfstudio_models").glob("*.ckpt"))[-1] == "step-000000003.ckpt"
        controls = {element.name for element in session._installed}
        assert {"SKED show the base (not the edit)", "SKED beta (preservation falloff)"} <= controls
        assert session.model.viewer_show_base in session._installed, "the controls steer the round being shown"

        panel.edit_again()
        assert panel.source.visible and panel.source.value == "round 1" and panel.sketch.session.views == []
        assert panel.prompt() == "a red chef hat", "the last prompt stays"
        draw(panel, hat, monkeypatch, scale=0.5)
        panel.prompt_text.value = ""
        panel.start()
        running.wait(lambda: len(session.rounds) == 2, "round 2")
        running.wait(lambda: "is done" in panel.last_message, "round 2's steps")
        second = session.rounds[1]
        assert second == run.parent / f"{run.name}_round2"
        saved = yaml.load((second / "config.yml").read_text(), Loader=yaml.Loader)
        assert saved.pipeline.model.prompt is None, "an empty prompt carves"
        assert Path(saved.pipeline.model.base_checkpoint).parent == run / "nerfstudio_models", "round 1's result"
        assert load_sketch_set(second / "sketches").views[0].mask.sum() < load_sketch_set(run / "sketches").views[0].mask.sum()
        assert "round 2" in panel.rounds_text.content and panel.source.options[0] == "round 2"
        assert session.model.viewer_show_base in session._installed and len(session._installed) == len(controls)

        panel.edit_again()  # go back: round 3 continues from round 1, not from round 2
        assert list(panel.source.options) == ["round 2", "round 1", "the base"]
        draw(panel, hat, monkeypatch, scale=0.5)
        panel.source.value = "round 1"
        panel.prompt_text.value = "a red chef hat"
        guidance = session.trainer.config.pipeline.model.guidance  # the settings the next round copies
        guidance.model, sd = str(tmp_path / "no-weights"), guidance.model
        panel.start()  # refused after round 2 ended: the session waits for the next Start edit
        running.wait(lambda: "**Error:**" in panel.last_message, "the refusal of round 3")
        assert "no-weights" in panel.last_message and len(session.rounds) == 2 and running.thread.is_alive()
        assert not (run.parent / f"{run.name}_round3").exists(), "a refused round leaves no run folder"
        guidance.model = sd
        panel.start()
        running.wait(lambda: len(session.rounds) == 3, "round 3")
        saved = yaml.load((session.rounds[2] / "config.yml").read_text(), Loader=yaml.Loader)
        assert Path(saved.pipeline.model.base_checkpoint).parent == run / "nerfstudio_models", "round 1's result"
    finally:
        running.close()

    # The saved round resumes from the command line's config, with its own sketches and prompt.
    config = resume_config(second, iterations=6)
    config.vis = "tensorboard"
    resumed = run_edit(config)
    assert Path(resumed.config.load_dir) == second / "nerfstudio_models" and resumed._start_step == 4
    assert Path(resumed.config.pipeline.model.sketches) == resumed.base_dir / "sketches"  # its own copy of round 2's
    assert load_sketch_set(resumed.base_dir / "sketches").views[0].mask.tolist() == \
        load_sketch_set(second / "sketches").views[0].mask.tolist()


def _ns_train() -> str:
    return str(Path(sys.executable).parent / "ns-train")


def test_ns_train_without_sketches_opens_the_session_and_ctrl_c_leaves_no_run(scene, tmp_path):
    """The command line as users type it: the viewer serves, training waits and writes no config.yml; ctrl+c ends
    the session and removes the run folder it took."""
    from session_helpers import free_port, terminal_sigint

    port = free_port()
    process = subprocess.Popen(
        [_ns_train(), "sked", "--load-dir", str(scene["base"]), "--machine.device-type", "cpu", "--output-dir",
         str(tmp_path / "out"), "--viewer.websocket-port", str(port), "nerfstudio-data", "--data", str(scene["data"])],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "COLUMNS": "200"},
        preexec_fn=terminal_sigint)
    lines = []
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            assert line or process.poll() is None, "".join(lines)
            lines.append(line)
            if "Training waits for a sketch set" in line:
                break
        assert any(f"localhost:{port}" in line for line in lines), "".join(lines)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30) as page:
            assert page.status == 200
        runs = list((tmp_path / "out").rglob(".sked-writer.lock"))
        assert len(runs) == 1 and not (runs[0].parent / "config.yml").exists()
        process.send_signal(signal.SIGINT)
        output = process.communicate(timeout=120)[0]
    finally:
        process.kill()
    assert not runs[0].parent.exists(), "the abandoned session leaves no run folder"
    assert not list((tmp_path / "out").rglob("*")), "nor the empty folders above it"
    assert "Traceback" not in output and "KeyboardInterrupt" not in output, output[-2000:]
    assert "interrupted while setting up, before the edit wrote anything" in output, output[-2000:]
    assert process.returncode == 130, output[-2000:]


def test_no_sketches_without_the_viewer_is_refused_naming_both_ways(scene, tmp_path):
    result = subprocess.run(
        [_ns_train(), "sked", "--load-dir", str(scene["base"]), "--vis", "tensorboard", "--machine.device-type", "cpu",
         "--output-dir", str(tmp_path / "out"), "nerfstudio-data", "--data", str(scene["data"])],
        capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    errors = [line for line in (result.stdout + result.stderr).splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "--sketches" in errors[0] and "--vis viewer" in errors[0], errors
    assert not (tmp_path / "out").exists(), "refused before anything is written"
