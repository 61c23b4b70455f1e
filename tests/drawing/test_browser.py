"""The SKED sketch panel driven in a real browser (headless Chromium through Playwright).

Opens `sked-sketch`'s viewer on the tiny base, waits for the SKED panel, captures two views
from two camera positions, clicks an outline in each, adds the views, saves the set, loads it
back, and keeps a screenshot in test-artifacts/ (or $SKED_TEST_ARTIFACTS).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from session_helpers import free_port, wait_for

from sked_ns.sketches.sketch_set import load_sketch_set

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("SKED_TEST_ARTIFACTS", ROOT / "test-artifacts"))


def _chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium; `bash .ci/test` does it as root)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("Playwright is not installed (pip install -e '.[test]')")
    return path


def _click_until(click, done, what: str, panel, attempts: int = 4, patience: float = 30.0):
    """Click, and click again if the server has not seen it: a loaded CI machine can drop an event."""
    for _ in range(attempts):
        click()
        try:
            return wait_for(done, what, timeout=patience, panel=panel)
        except AssertionError:
            continue
    raise AssertionError(f"{what}: no effect after {attempts} clicks; the panel says: {panel.last_message}")


@contextlib.contextmanager
def _page(chromium: str, port: int, width: int, height: int):
    """A headless Chromium page on the viewer at `port` (software WebGL; dialogs dismissed)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=chromium, headless=True,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
        )
        page = browser.new_page(viewport={"width": width, "height": height})
        page.on("dialog", lambda dialog: dialog.dismiss())
        page.goto(f"http://127.0.0.1:{port}")
        yield page
        browser.close()


def test_sketch_panel_in_a_real_browser(scene, tmp_path):
    chromium = _chromium()
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    from sked_ns.drawing.sketch_viewer import start_viewer, stop_viewer

    out = tmp_path / "sketches"
    port = free_port()
    viewer, panel = start_viewer(scene["base"], out, port=port)
    server = viewer.viser_server
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with _page(chromium, port, 1100, 750) as page:
            page.get_by_role("button", name="Capture view").wait_for(timeout=120_000)
            try:
                _opens_framed_and_moves_as_dragged(page, viewer)
                for position in ((20.0, -20.0, 10.0), (-20.0, -20.0, 12.0)):  # viser units: 10 x nerfstudio's
                    _draw_view(page, server, panel, position, (0.45, 0.40, 0.55, 0.50))  # a small square
            except Exception:
                page.screenshot(path=str(ARTIFACTS / "sked_sketch_panel_failure.png"))
                raise
            page.get_by_role("button", name="Save sketch set").click()
            wait_for(lambda: (out / "sketches.json").exists(), "the saved sketch set", panel=panel)
            page.wait_for_timeout(1000)
            page.screenshot(path=str(ARTIFACTS / "sked_sketch_panel.png"))
            assert page.get_by_text("Saved 2 views").count() >= 1
    finally:
        stop_viewer(viewer)
    # A render thread still running at exit makes torch abort the interpreter (exit code 134).
    assert not [thread for thread in threading.enumerate() if isinstance(thread, RenderStateMachine)]
    sketches = load_sketch_set(out)
    assert len(sketches.views) == 2
    for view in sketches.views:
        # The clicked square: 10% x 10% of the view, where it was clicked.
        fraction = view.mask.mean()
        assert 0.003 < fraction < 0.03, fraction
        rows, cols = np.nonzero(view.mask)
        centre = (cols.mean() + 0.5) / view.mask.shape[1], (rows.mean() + 0.5) / view.mask.shape[0]
        assert abs(centre[0] - 0.50) < 0.02 and abs(centre[1] - 0.45) < 0.02, f"clicked around (0.50, 0.45), got {centre}"
        height, width = rows.ptp() + 1, cols.ptp() + 1
        assert 0.5 < height / width < 2 and view.mask.sum() > 0.8 * height * width, "the clicked square, filled"
    assert (ARTIFACTS / "sked_sketch_panel.png").stat().st_size > 10_000


@pytest.fixture(scope="module")
def bust(tmp_path_factory):
    """The capture-like scene (lens, portrait photos on a hand-held arc, a wall behind) and a tiny base of it."""
    from sked_ns.demo.base import build_demo_base
    from sked_ns.demo.scenes import capture
    from sked_ns.demo.scenes.objects import union

    root = tmp_path_factory.mktemp("bust")
    written = capture.write_benchmark("bust", root, count=12, height=48, sketch_size=48)
    base = build_demo_base(written["data"], root / "runs", steps=60, points_per_step=2048,
                           sdf=union(capture.SCENES["bust"].base_parts)[0])
    return {**written, "base": base}


def test_sketch_panel_on_a_capture_saves_the_set_where_the_photos_were_taken(bust, tmp_path):
    """A user's sketch set on a capture's base: two views drawn in the browser from the capture's own sketch
    cameras, aimed at where its hat goes. The saved set is in the data frame (the poses of transforms.json): its
    cameras stand where the capture's sketch cameras stand and its sketches meet at the hat, with no placement
    warning for views on the arc."""
    import warnings

    chromium = _chromium()
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO as SCALE

    from sked_ns.drawing.sketch_viewer import start_viewer, stop_viewer
    from sked_ns.method.edit_box import compute_edit_box
    from sked_ns.sketches.placement import check_camera_placement, meeting_point

    wanted = load_sketch_set(bust["sketches"])  # data frame, as write_benchmark's viewer-drawn views
    hat = meeting_point(wanted.views)
    out = tmp_path / "sketches"
    port = free_port()
    viewer, panel = start_viewer(bust["base"], out, port=port)
    model = wanted.in_model_frame(panel.session.transform)
    aim = meeting_point(model.views) * SCALE
    try:
        with _page(chromium, port, 900, 750) as page:
            page.get_by_role("button", name="Capture view").wait_for(timeout=120_000)
            try:
                for view in model.views:
                    _draw_view(page, viewer.viser_server, panel, tuple(view.camera_to_world[:, 3] * SCALE),
                               (0.45, 0.45, 0.55, 0.55), look_at=tuple(aim))
            except Exception:
                page.screenshot(path=str(ARTIFACTS / "sked_sketch_capture_failure.png"))
                raise
            page.get_by_role("button", name="Save sketch set").click()
            wait_for(lambda: (out / "sketches.json").exists(), "the saved sketch set", panel=panel)
    finally:
        stop_viewer(viewer)
    drawn = load_sketch_set(out)
    assert drawn.frame == "data" and len(drawn.views) == 2
    distance = np.linalg.norm(wanted.views[0].camera_to_world[:, 3] - hat)
    for got, view in zip(drawn.views, wanted.views):
        assert np.linalg.norm(got.camera_to_world[:, 3] - view.camera_to_world[:, 3]) < 0.01 * distance
    assert np.linalg.norm(meeting_point(drawn.views) - hat) < 0.05 * distance
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_camera_placement(drawn.views)
        assert compute_edit_box(drawn.views).contains(torch.tensor(hat[None])).all()


def _draw_view(page, server, panel, position, square, look_at=(0.0, 0.0, 0.0)) -> None:
    """Move the browser's camera to `position` (viser units) looking at `look_at`, capture the view, click the
    corners of `square` ((x0, y0, x1, y1) as fractions of the canvas), close the outline and add the view."""
    client = wait_for(lambda: next(iter(server.get_clients().values()), None), "the browser to connect")
    client.camera.position = position
    client.camera.look_at = look_at
    time.sleep(1.0)
    page.get_by_role("button", name="Capture view").click()  # pressed again while it renders it would be ignored
    wait_for(lambda: panel.session.pending is not None, "the captured view", timeout=300, panel=panel)
    # The panel's status follows the pointer-enable message on the same socket: once the page shows it, the canvas
    # sends clicks (a click before that is dropped by viser); viser gives the canvas a pointer cursor then.
    page.get_by_text("Click the points").first.wait_for(timeout=120_000)
    canvas = page.locator('canvas[style*="cursor: pointer"]')
    canvas.wait_for(timeout=120_000)
    box = canvas.bounding_box()
    x0, y0, x1, y1 = square
    for index, (x, y) in enumerate([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]):
        # A repeated click at the same spot adds a zero-length edge: the outline is unchanged.
        _click_until(lambda: page.mouse.click(box["x"] + x * box["width"], box["y"] + y * box["height"]),
                     lambda n=index + 1: len(panel.session.pending.points) >= n, f"click {index + 1}", panel)
    page.get_by_role("button", name="Close scribble").click()
    wait_for(lambda: panel.session.pending.mask.any(), "the filled outline", panel=panel)
    wanted = len(panel.session.views) + 1
    page.get_by_role("button", name="Add view").click()
    wait_for(lambda: len(panel.session.views) >= wanted, "the added view", panel=panel)
    page.get_by_text("view(s).").first.wait_for(timeout=120_000)  # pointer events off again
    # The camera steps back from where the view was taken, so its frustum does not fill the screen.
    from sked_ns.engine.viewer import STEP_BACK

    distance = np.linalg.norm(np.asarray(client.camera.position) - np.asarray(client.camera.look_at))
    assert distance == pytest.approx(STEP_BACK * np.linalg.norm(np.subtract(position, look_at)), rel=0.05)


def _opens_framed_and_moves_as_dragged(page, viewer) -> None:
    """The browser opens on the scene as its photos show it, the SKED panel above nerfstudio's controls; a drag and
    a wheel turn move the camera as they do for a user (the server sees the browser's camera)."""
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    from sked_ns.engine.viewer import scene_framing, training_poses

    client = wait_for(lambda: next(iter(viewer.viser_server.get_clients().values()), None), "the browser to connect")
    position, look_at, _ = scene_framing(training_poses(viewer.pipeline))
    wait_for(lambda: np.allclose(client.camera.position, position * VISER_NERFSTUDIO_SCALE_RATIO, atol=1e-2),
             "the framed opening view")
    assert np.allclose(client.camera.look_at, look_at * VISER_NERFSTUDIO_SCALE_RATIO, atol=1e-2)
    sked = page.get_by_text("SKED sketch").first.bounding_box()
    control = page.get_by_role("tab", name="Control").first.bounding_box()
    assert sked["y"] < control["y"], "the SKED panel is the sidebar's first"
    canvas = page.locator("canvas").first.bounding_box()
    x, y = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    before = np.asarray(client.camera.position)
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 150, y + 40, steps=10)
    page.mouse.up()
    wait_for(lambda: not np.allclose(client.camera.position, before, atol=1e-3), "the dragged camera")
    dragged = np.asarray(client.camera.position)
    distance = lambda: np.linalg.norm(np.asarray(client.camera.position) - np.asarray(client.camera.look_at))  # noqa: E731
    orbit = distance()
    page.mouse.wheel(0, -600)
    wait_for(lambda: abs(distance() - orbit) > 1e-3 * orbit, "the wheel's zoom")
    assert not np.allclose(client.camera.position, dragged)


OVERVIEW = (12.0, -16.0, 9.0)
"""Where the screenshots look from (viser units): the scene, the sketch views' frusta and the edit box."""


def _look_from(server, position) -> None:
    """The browser's camera at `position` (viser units), looking at the origin: the scene and the sketch views."""
    client = next(iter(server.get_clients().values()))
    client.camera.position = position
    client.camera.look_at = (0.0, 0.0, 0.0)
    time.sleep(3.0)  # the viewer renders the new view


def _type_prompt(page, text: str) -> None:
    field = page.locator("xpath=//*[normalize-space(text())='Prompt']/following::input[1]")
    field.fill(text)
    field.press("Enter")


def test_edit_session_in_a_real_browser(scene, tmp_path):
    """`ns-train sked` without --sketches: sketch two views, type the prompt, Start edit, watch the edit advance,
    Edit again with a second region and no prompt (carve); the saved round resumes from the command line and
    sked-eval reads it. Screenshots for docs/session.md go to test-artifacts/."""
    import subprocess
    import sys

    chromium = _chromium()
    from session_helpers import SessionThread, session_config
    from tiny_sd import build_tiny_stable_diffusion

    config = session_config(scene, tmp_path / "out", build_tiny_stable_diffusion(tmp_path / "sd"), iterations=6)
    port = config.viewer.websocket_port
    running = SessionThread(config)
    session = running.session
    panel, sketch, server = session.panel, session.panel.sketch, session.viewer.viser_server
    session.viewer.control_panel._max_res.value = 160  # the viewer's own renders, on this CPU, while the edit trains
    started = time.monotonic()

    def mark(what):
        print(f"[{time.monotonic() - started:6.1f} s] {what}", flush=True)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with _page(chromium, port, 1200, 800) as page:
            try:
                page.get_by_text("Training waits for a sketch set").first.wait_for(timeout=120_000)
                page.get_by_text("carves the sketched region away").first.wait_for(timeout=60_000)
                views = ((9.0, -9.0, 4.5), (-9.0, -9.0, 5.5))  # viser units: 10 x nerfstudio's
                for position in views:
                    _draw_view(page, server, sketch, position, (0.45, 0.40, 0.55, 0.50))
                _type_prompt(page, "a red chef hat")
                wait_for(lambda: panel.prompt() == "a red chef hat", "the typed prompt", panel=panel)
                page.get_by_text("fills the sketched region with the prompt").first.wait_for(timeout=60_000)
                mark("drawn")
                _look_from(server, OVERVIEW)
                page.screenshot(path=str(ARTIFACTS / "session_1_sketched.png"))
                page.get_by_role("button", name="Start edit").click()
                running.wait(lambda: len(session.rounds) == 1, "round 1")
                mark("round 1 set up")
                _look_from(server, OVERVIEW)
                page.get_by_text(re.compile(r"step [2-6] of 6")).first.wait_for(timeout=300_000)  # it advances
                page.screenshot(path=str(ARTIFACTS / "session_2_editing.png"))
                page.get_by_text("is done and saved").first.wait_for(timeout=300_000)
                mark("round 1 done")

                page.get_by_role("button", name="Edit again").click()
                page.get_by_text("Sketch the new region").first.wait_for(timeout=60_000)
                for position in views:
                    _draw_view(page, server, sketch, position, (0.46, 0.28, 0.54, 0.36))  # above the first region
                _type_prompt(page, "")
                page.get_by_text("carves the sketched region away").first.wait_for(timeout=60_000)
                _look_from(server, OVERVIEW)
                mark("drawn again")
                page.screenshot(path=str(ARTIFACTS / "session_3_edit_again.png"))
                page.get_by_role("button", name="Start edit").click()
                running.wait(lambda: len(session.rounds) == 2, "round 2")
                page.get_by_text("Round 2 is done and saved").first.wait_for(timeout=300_000)
                _look_from(server, OVERVIEW)
                page.get_by_text("round 2").first.wait_for(timeout=60_000)
                page.screenshot(path=str(ARTIFACTS / "session_4_round_2.png"))
                mark("round 2 done")
            except Exception:
                page.screenshot(path=str(ARTIFACTS / "session_failure.png"))
                raise
    finally:
        running.close()
    first, second = session.rounds
    prompts = [yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader).pipeline.model.prompt for run in (first, second)]
    assert prompts == ["a red chef hat", None]
    assert len(load_sketch_set(first / "sketches").views) == 2 and len(load_sketch_set(second / "sketches").views) == 2

    bin_dir = Path(sys.executable).parent
    resumed = subprocess.run(
        [str(bin_dir / "ns-train"), "sked", "--load-dir", str(second), "--max-num-iterations", "8", "--vis", "tensorboard",
         "--output-dir", str(tmp_path / "resumed")], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    assert "Resuming the SKED edit" in resumed.stdout
    mark("resumed")
    assert list((tmp_path / "resumed").rglob("step-000000007.ckpt")), "the resumed round ran to its new total"
    evaluated = subprocess.run(
        [str(bin_dir / "sked-eval"), str(second), "--device", "cpu", "--resolution", "32", "--cameras", "none",
         "--output", str(tmp_path / "eval.json")], capture_output=True, text=True, timeout=600)
    assert evaluated.returncode == 0, evaluated.stdout[-3000:] + evaluated.stderr[-3000:]
    assert "ios" in (tmp_path / "eval.json").read_text().lower()
    mark("evaluated")
    for name in ("session_1_sketched", "session_2_editing", "session_3_edit_again", "session_4_round_2"):
        assert (ARTIFACTS / f"{name}.png").stat().st_size > 10_000
