"""The SKED session folder in the viewer: the prompt, Start edit, Edit again and the rounds of an edit session.

It knows nothing about training: pressing **Start edit** hands a `StartRequest` (the drawn sketch set, the prompt and
the round to start from) to whoever waits on `requests` (`sked_ns.session.rounds.EditSession`, on the trainer's
thread), which answers with `show_round`, `round_done` or `refused`. The sketch tools are `SketchPanel`'s, without
its Save controls: a session saves each round's set in that round's run folder.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Optional

from sked_ns.drawing.sketch_viewer import SketchPanel, guarded
from sked_ns.drawing.sketching import SketchSession

CARVE_NOTE = "No prompt: **Start edit** carves the sketched region away."
PROMPT_NOTE = "Stable Diffusion fills the sketched region with the prompt."
NO_PROMPT_NOTE = "The `{name}` guidance uses no prompt: **Start edit** fills the sketched region as it steers."


def prompt_note(prompt: Optional[str], guidance=None) -> str:
    """What Start edit will do with this prompt under this guidance (a config; None: Stable Diffusion's)."""
    if guidance is not None and not guidance.uses_prompt:
        from sked_ns.guidance import guidance_name

        return NO_PROMPT_NOTE.format(name=guidance_name(guidance))
    return PROMPT_NOTE if prompt and prompt.strip() else CARVE_NOTE
BASE_CHOICE = "the base"


@dataclass
class StartRequest:
    """What the user asked for when pressing Start edit."""

    sketches: SketchSession
    """The drawn views (model frame), saved by the session into the round's folder."""
    prompt: Optional[str]
    """None: carve."""
    source: Optional[int]
    """The round to continue from (its number), or None for the base."""


def round_label(number: int) -> str:
    return f"round {number}"


SESSION_PANEL_ORDER = -2.0
"""The session's folder first in the viewer's sidebar, the sketch tools under it, nerfstudio's controls after."""

class SessionPanel:
    """Prompt, Start edit, Edit again, the round to start from and the list of rounds, above the sketch tools."""

    def __init__(self, server, new_sketches: Callable[[], SketchSession], prompt: Optional[str], guidance=None) -> None:
        self.server, self.new_sketches, self.guidance = server, new_sketches, guidance
        self.requests: "queue.Queue[StartRequest]" = queue.Queue()
        self.rounds: List[str] = []  # one line per round: its number, prompt and folder
        self.on_edit_again: Callable[[], None] = lambda: None  # the session pauses the round being trained
        self.on_start: Callable[[], None] = lambda: None  # ... and ends it when the next one is asked for
        self.last_message = ""
        self.sketching = True  # a set is being drawn (before round 1, after Edit again); else a round trains
        self._lock = threading.Lock()  # one press handled at a time
        gui = server.gui
        with gui.add_folder("SKED session", order=SESSION_PANEL_ORDER):
            self.status = gui.add_markdown("")
            self.prompt_text = gui.add_text("Prompt", initial_value=prompt or "")
            self.prompt_note = gui.add_markdown(prompt_note(prompt, guidance))
            self.source = gui.add_dropdown("Start from", options=[BASE_CHOICE], initial_value=BASE_CHOICE, visible=False)
            self.start_button = gui.add_button("Start edit", disabled=True)
            self.again_button = gui.add_button("Edit again", disabled=True)
            self.rounds_text = gui.add_markdown("")
        self.sketch = SketchPanel(server, new_sketches(), out=None)
        self.sketch.on_views_changed = self._views_changed
        self.prompt_text.on_update(lambda _: self._prompt_changed())
        self.start_button.on_click(lambda _: self._guarded(self.start))
        self.again_button.on_click(lambda _: self._guarded(self.edit_again))
        self._say("Training waits for a sketch set: move to a view of the region, **Capture view** and outline it; "
                  "do the same from a second viewpoint, type the prompt, then **Start edit**.")

    # ---- actions (also called directly by tests) ---------------------------------------------
    def prompt(self) -> Optional[str]:
        """The typed prompt; None when empty (carve)."""
        return self.prompt_text.value.strip() or None

    def start(self) -> StartRequest:
        """Hand the drawn set to the session: the edit box must exist (two views that meet)."""
        sketches = self.sketch.session
        if sketches.pending is not None:
            raise ValueError("A captured view is not added yet: **Add view** (or **Remove last view**) first.")
        if len(sketches.views) < 2:
            raise ValueError(f"{len(sketches.views)} view(s): sketch the region from at least two viewpoints.")
        sketches.edit_box()  # sketches that do not meet in 3D: refused here, with the views kept to fix
        source = None if self.source.value == BASE_CHOICE else int(self.source.value.split()[-1])
        request = StartRequest(sketches=sketches, prompt=self.prompt(), source=source)
        self.sketching = False
        self.sketch.set_enabled(False)
        self._say("Starting the edit...")
        self.requests.put(request)
        self.on_start()
        return request

    def edit_again(self) -> None:
        """Sketch a new region over the scene as it is now; the round being trained pauses."""
        self.on_edit_again()
        self.sketching = True
        self.again_button.disabled = True
        self.source.visible = True
        self.sketch.restart(self.new_sketches(), "Move to a view of the new region, then **Capture view**.")
        self.sketch.set_enabled(True)
        self._say("Sketch the new region from two viewpoints, then **Start edit**: it continues from the round "
                  "chosen under *Start from* (the latest by default; an earlier one, or the base, to go back).")

    # ---- what the session tells the panel ----------------------------------------------------
    def show_round(self, number: int, folder: Path, prompt: Optional[str]) -> None:
        """Round `number` is being trained in `folder`."""
        label = round_label(number)
        self.rounds.append(f"- **{label}**: {prompt or 'carve'} ({folder.name}/)")
        self.rounds_text.content = "Rounds (each a run folder; `ns-train sked --load-dir` resumes one):\n" + "\n".join(
            self.rounds)
        options = [round_label(n) for n in range(len(self.rounds), 0, -1)] + [BASE_CHOICE]
        self.source.options = options
        self.source.value = options[0]
        self.source.visible = False
        self.again_button.disabled = False
        self.sketch.set_enabled(False)
        self._say(f"Editing ({label}): the viewer shows the edit as it trains. **Edit again** sketches another region.")

    def progress(self, number: int, step: int, total: int) -> None:
        self._say(f"Editing ({round_label(number)}): step {step} of {total}. **Edit again** sketches another region.")

    def round_done(self, number: int, folder: Path) -> None:
        self._say(f"{round_label(number).capitalize()} is done and saved in {folder.name}/. Look around, compare "
                  "with the base (*SKED show the base*), or **Edit again**.")

    def refused(self, message: str) -> None:
        """The session could not start the round: say why, and let the user fix the sketches or the prompt."""
        self.sketching = True
        self.sketch.set_enabled(True)
        self._say(f"**Error:** {message}")

    # ---- display ------------------------------------------------------------------------
    def _views_changed(self) -> None:
        self.start_button.disabled = not self.sketching or len(self.sketch.session.views) < 2

    def _prompt_changed(self) -> None:
        self.prompt_note.content = prompt_note(self.prompt(), self.guidance)

    def _guarded(self, action) -> None:
        with self._lock:
            guarded(action, self._say)

    def _say(self, message: str) -> None:
        self.status.content = message
        self.last_message = message
