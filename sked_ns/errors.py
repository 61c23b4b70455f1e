"""User errors: a mistake in what was typed or pointed at, printed as one message without a traceback.

Raise `SkedUserError` (or `SkedFileNotFoundError` for a missing file) with a message that names the
file or flag as the user types it and says what to do. Every `ns-*` command imports the plugin, which
installs `excepthook`: such an error prints `error: <message>` alone (set SKED_TRACEBACK=1 for the
traceback); any other exception keeps Python's (or the previous hook's) full report.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

TRACEBACK_ENV = "SKED_TRACEBACK"


class SkedUserError(ValueError):
    """A mistake in the command line or its files; the message says which and what to do."""


class SkedFileNotFoundError(SkedUserError, FileNotFoundError):
    """A file or folder the user named (or one it must hold) is missing."""


def excepthook(kind, error, traceback) -> None:
    if issubclass(kind, SkedUserError) and os.environ.get(TRACEBACK_ENV, "") in ("", "0"):
        print(f"error: {error}", file=sys.stderr)
        return
    _previous_excepthook(kind, error, traceback)


_previous_excepthook = sys.excepthook


def install_excepthook() -> None:
    """Print user errors without a traceback; chain to the hook in place for everything else (idempotent)."""
    global _previous_excepthook
    if sys.excepthook is not excepthook:
        _previous_excepthook = sys.excepthook
        sys.excepthook = excepthook


def check_writable_folder(folder: Path, flag: str, typed=None) -> None:
    """Create `folder` and write a probe file in it, so a folder that cannot hold the outputs is refused up front,
    naming the `flag` and the value `typed` for it (default: the folder). By trying: permission bits do not stop
    root, and a parent that is a file only shows on mkdir."""
    folder = Path(folder)
    probe = folder / f".sked-write-probe-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        where = "" if typed is None or Path(typed) == folder else f" (the run folder {folder})"
        raise SkedUserError(f"{flag} {folder if typed is None else typed}: cannot write there{where}: "
                            f"{error.strerror or error} ({error.filename or folder}). Pass a writable {flag}.") from error


class SkedWarning(UserWarning):
    """A legal input that is almost surely a mistake: the command goes on after one `warning: <message>` line."""


def warn(message: str) -> None:
    warnings.warn(message, SkedWarning, stacklevel=2)


def show_warnings_as_lines() -> None:
    """Print SkedWarnings as `warning: <message>` (the user's input, not our source line); others as before."""
    previous = warnings.formatwarning
    if getattr(previous, "sked_lines", False):
        return

    def format_warning(message, category, filename, lineno, line=None):
        if issubclass(category, SkedWarning):
            return f"warning: {message}\n"
        return previous(message, category, filename, lineno, line)

    format_warning.sked_lines = True
    warnings.formatwarning = format_warning
