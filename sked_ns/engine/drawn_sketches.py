"""Sketches drawn in the edit's own viewer: where a session saves them, and whether they are still to be drawn.

`ns-train sked` without --sketches, with the viewer on, edits in a session (`sked_ns.session`): the sketch set is
drawn in the viewer and saved in the run folder, and only then checked and used as --sketches would be.
"""

from __future__ import annotations

from pathlib import Path

from sked_ns.errors import SkedUserError
from sked_ns.sketches.sketch_set import SKETCHES_JSON

SESSION_SKETCHES = "sketches"
"""A session round's sketch set: this folder inside the round's run folder."""


def session_sketches(config) -> Path:
    return config.get_base_dir() / SESSION_SKETCHES


def sketches_pending(config) -> bool:
    """Whether this run's sketch set is still to be drawn in its viewer (a session's first round before Start edit)."""
    sketches = config.pipeline.model.sketches
    return (sketches is not None and Path(sketches) == session_sketches(config)
            and not (Path(sketches) / SKETCHES_JSON).exists())


def no_sketches(config) -> SkedUserError:
    """A new edit without --sketches that cannot draw them in its viewer (the viewer off, or built from Python)."""
    return SkedUserError(
        f"--vis {config.vis}: no sketches to edit with. Pass --sketches <folder with sketches.json> (draw one with "
        "sked-sketch), or leave --sketches out with the viewer on (--vis viewer, the default) to draw them in "
        "this edit's viewer.")
