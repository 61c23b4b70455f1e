"""The edit's own hold on its base's checkpoint.

An edit is its changes to one base checkpoint, read whenever the edit is loaded (the frozen base is not copied into
the edit's checkpoints). A base run that trains on with `save_only_latest_checkpoint` (nerfstudio's default) removes
that file at its next save. So when an edit starts, its run folder gets a hard link to it, `<edit run>/base/step-*.ckpt`:
no second copy on disk, and the base's files are neither moved nor changed (the base's config and data frame are
still read from its run, which a later save leaves in place). Where the file system refuses a link, the
edit says so and reads the base run's file as before.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

from sked_ns.errors import warn

KEPT = "base"
"""The folder in the edit's run that holds the link (no config.yml: it is not a run of its own)."""


def keep_base(model, run_dir: Path) -> None:
    """Link the edit's base checkpoint into `run_dir` and record it on the model config (`base_kept`)."""
    if model.base_checkpoint is None:
        return
    checkpoint = Path(model.base_checkpoint)
    kept = (Path(run_dir) / KEPT / checkpoint.name).absolute()
    if model.base_kept is not None and Path(model.base_kept).exists():
        return  # a resumed edit keeps what its start kept
    if not checkpoint.exists():
        return  # base_weights names it when the edit loads
    try:
        kept.parent.mkdir(parents=True, exist_ok=True)
        if not kept.exists():
            os.link(checkpoint, kept)
    except OSError as error:
        shutil.rmtree(kept.parent, ignore_errors=True)
        why = "another file system" if error.errno == errno.EXDEV else (error.strerror or str(error))
        warn(f"{checkpoint}: the edit reads this base checkpoint whenever it is loaded and could not keep a link to "
             f"it in its own folder ({why}). Keep the base run as it is: a base trained on replaces that file.")
        return
    model.base_kept = kept
