"""Files that a kill cannot leave half-written: written beside, synced, then renamed into place."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Callable


def publish_atomically(written: Path, path: Path) -> None:
    """Move a finished file to `path` so that readers see the old state or the whole new file, even after a kill."""
    with open(written, "rb") as file:
        os.fsync(file.fileno())  # the data is on disk before the name points at it
    os.replace(written, path)
    with contextlib.suppress(OSError):  # and the new name survives a power cut (not every file system allows it)
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)


def write_atomically(path: Path, write: Callable[[str], None]) -> None:
    """`write(partial)` to a file beside `path`, then published as `path`: a kill mid-write leaves the previous file
    (or none), never half of the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, written = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)  # same file system
    os.close(handle)
    try:
        write(written)
        publish_atomically(Path(written), path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(written)
        raise


def write_text_atomically(path: Path, text: str) -> None:
    """`path.write_text(text)`, except that a kill mid-write leaves the previous file (results a rerun continues from)."""
    write_atomically(path, lambda written: Path(written).write_text(text))
