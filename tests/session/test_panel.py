"""The session panel on its own (a viser server, no model): what Start edit hands on, when it may be pressed, and
what it says about the prompt and the rounds."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import look_at
from session_helpers import free_port

from sked_ns.sketches.cameras import PinholeCamera
from sked_ns.sketches.sketch_set import DataparserTransform, SketchView


@pytest.fixture
def panel():
    import viser

    from sked_ns.drawing.sketching import SketchSession
    from sked_ns.session.panel import SessionPanel

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    blank = lambda camera: np.zeros((camera.height, camera.width, 3))  # noqa: E731 - the canvases are not looked at
    yield SessionPanel(server, lambda: SketchSession(blank, DataparserTransform()), prompt=None)
    server.stop()


def centred_view(position) -> SketchView:
    """A 32 px view of the origin from `position`, its middle sketched."""
    mask = np.zeros((32, 32), dtype=bool)
    mask[12:20, 12:20] = True
    return SketchView(mask=mask, camera_to_world=look_at(np.array(position, dtype=float), np.zeros(3)),
                      fl_x=32.0, fl_y=32.0, cx=16.0, cy=16.0)


def test_start_needs_two_views_that_meet_and_hands_on_the_set_and_prompt(panel):
    assert panel.start_button.disabled and panel.prompt() is None and "carves" in panel.prompt_note.content
    views = panel.sketch.session.views
    views.append(centred_view((2.0, 0.0, 0.5)))
    panel._guarded(panel.start)
    assert "at least two" in panel.last_message and panel.requests.empty()
    views.append(centred_view((0.0, 2.0, 0.5)))
    panel.sketch.session.capture(PinholeCamera.from_view(views[0]))  # a third view captured, not added
    panel._guarded(panel.start)
    assert "not added yet" in panel.last_message and panel.requests.empty()
    panel.sketch.session.pending = None
    panel.sketch._set_drawing(False)
    assert not panel.start_button.disabled
    panel.prompt_text.value = "  a red chef hat "
    panel._prompt_changed()
    assert "Stable Diffusion" in panel.prompt_note.content
    request = panel.start()
    assert request.prompt == "a red chef hat" and request.source is None and len(request.sketches.views) == 2
    assert panel.requests.get_nowait() is request
    assert panel.start_button.disabled and panel.sketch.capture_button.disabled, "nothing to draw while a round starts"


def test_rounds_are_listed_and_edit_again_offers_each_and_the_base(panel):
    from pathlib import Path

    pauses = []
    panel.on_edit_again = lambda: pauses.append(True)
    panel.show_round(1, Path("out/edit/sked/2026-01-01_000000"), "a hat")
    assert panel.start_button.disabled and not panel.again_button.disabled and not panel.source.visible
    panel.show_round(2, Path("out/edit/sked/2026-01-01_000000_round2"), None)
    assert "round 2**: carve" in panel.rounds_text.content and "2026-01-01_000000_round2/" in panel.rounds_text.content
    panel.edit_again()
    assert pauses == [True] and panel.source.visible and list(panel.source.options) == ["round 2", "round 1", "the base"]
    assert panel.source.value == "round 2" and not panel.sketch.capture_button.disabled and panel.start_button.disabled
    panel.source.value = "the base"
    panel.sketch.session.views.extend([centred_view((2.0, 0.0, 0.5)), centred_view((0.0, 2.0, 0.5))])
    assert panel.start().source is None
    panel.refused("the views hold too few pixels")
    assert panel.last_message == "**Error:** the views hold too few pixels" and not panel.start_button.disabled


def test_the_prompt_note_says_what_start_edit_does_under_each_guidance():
    from sked_ns.guidance import guidance_config
    from sked_ns.session.panel import CARVE_NOTE, PROMPT_NOTE, prompt_note

    stable_diffusion, reference = guidance_config("stable-diffusion"), guidance_config("reference")
    assert prompt_note("a hat", stable_diffusion) == PROMPT_NOTE and prompt_note("  ", stable_diffusion) == CARVE_NOTE
    assert prompt_note(None, None) == CARVE_NOTE
    for prompt in ("a hat", None):
        note = prompt_note(prompt, reference)
        assert "`reference` guidance uses no prompt" in note and "Stable Diffusion" not in note
