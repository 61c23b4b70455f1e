"""User errors: a mistake in what was typed or pointed at, printed as one message without a traceback.

Raise `SkedUserError` (or `SkedFileNotFoundError` for a missing file) with a message that names the
file or flag as the user types it and says what to do. Every `ns-*` command imports the plugin, and
every `sked-*` command is part of it; importing it installs `excepthook`: such an error prints
`error: <message>` alone, on one line (set SKED_TRACEBACK=1 for the traceback), and Ctrl-C in a sked-* command
one `interrupted:` line; any other exception keeps Python's (or the previous hook's) full report. Where a library reads a file the user pointed
at, `reading` turns its failure into such an error; `ArgumentParser` does the same for argparse's.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Iterator, List, Mapping, Optional, Sequence, Tuple, Type

TRACEBACK_ENV = "SKED_TRACEBACK"


class SkedUserError(ValueError):
    """A mistake in the command line or its files; the message says which and what to do."""


class SkedFileNotFoundError(SkedUserError, FileNotFoundError):
    """A file or folder the user named (or one it must hold) is missing."""


class SkedFileExistsError(SkedUserError, FileExistsError):
    """An output the user named already holds something that is never replaced."""


READ_ERRORS: Tuple[Type[BaseException], ...] = (OSError, ValueError, KeyError, IndexError, TypeError, AssertionError)
"""What nerfstudio, diffusers and torch raise on a file they cannot make sense of."""


@contextlib.contextmanager
def reading(what: str, fix: str, errors: Tuple[Type[BaseException], ...] = READ_ERRORS) -> Iterator[None]:
    """Where a library reads a file or folder the user pointed at (`what`: the flag and the value typed), its
    failure is the user's input, not a bug: say so in one line, with what to do (`fix`)."""
    try:
        yield
    except SkedUserError:
        raise
    except errors as error:
        detail = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise SkedUserError(f"{what}: cannot read it ({type(error).__name__}{': ' + detail if detail else ''}). "
                            f"{fix}") from error


class ArgumentParser(argparse.ArgumentParser):
    """argparse with its errors (an unknown flag, a value of the wrong type) as one `error:` line."""

    def error(self, message: str):
        raise SkedUserError(f"{self.prog}: {message} (see {self.prog} --help).")


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's `(default: X)` where the help does not already say its default, and never `(default: None)`."""

    def _get_help_string(self, action) -> str:
        help_text = action.help or ""
        if "default" in help_text or action.default is None or action.default is argparse.SUPPRESS:
            return help_text
        return super()._get_help_string(action)


def excepthook(kind, error, traceback) -> None:
    if os.environ.get(TRACEBACK_ENV, "") in ("", "0"):
        if issubclass(kind, SkedUserError):
            print(f"error: {one_line(str(error))}", file=sys.stderr)
            return
        command = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
        if issubclass(kind, KeyboardInterrupt) and command.startswith("sked-"):  # other commands keep their report
            # Python still exits as killed by SIGINT: status 130.
            print(f"interrupted: {command} stopped by Ctrl-C; what it had written whole is kept.", file=sys.stderr)
            return
    _previous_excepthook(kind, error, traceback)


_previous_excepthook = sys.excepthook


def one_line(message: str) -> str:
    """A message listing several problems on lines of their own, as one line (a log greps it whole)."""
    return " ".join(line.strip() for line in message.splitlines() if line.strip())


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
        check_name_lengths(folder, flag)  # a name too long: said as such, not as an unwritable place
        where = "" if typed is None or Path(typed) == folder else f" (the run folder {folder})"
        raise SkedUserError(f"{flag} {folder if typed is None else typed}: cannot write there{where}: "
                            f"{error.strerror or error} ({error.filename or folder}). Pass a writable {flag}.") from error


NAME_SHOWN = 24
"""Characters of an over-long file or folder name quoted in its error."""


def existing_folder(path: Path) -> Path:
    """The nearest of `path` and its parents that exists (a name too long for the file system exists nowhere)."""
    path = Path(path).expanduser().absolute()
    while path.parent != path:
        with contextlib.suppress(OSError):
            if path.exists():
                break
        path = path.parent
    return path


def _file_system_limit(folder: Path, name: str, default: int) -> int:
    try:
        return os.pathconf(folder, name)
    except (OSError, ValueError, AttributeError):  # not reported there (or no pathconf): the usual Linux limits
        return default


def name_too_long(path: Path) -> "str | None":
    """Why `path` can name no file on its file system (every operation on it fails with ENAMETOOLONG), or None."""
    path = Path(path).expanduser().absolute()
    existing = existing_folder(path)
    longest = _file_system_limit(existing, "PC_NAME_MAX", 255)
    for name in path.parts[1:]:
        size = len(os.fsencode(name))
        if size > longest:
            shown = name if len(name) <= NAME_SHOWN else name[:NAME_SHOWN] + "..."
            return f"the name {shown!r} is {size} bytes long, and the file system under {existing} allows {longest}"
    size = len(os.fsencode(str(path)))
    if size > _file_system_limit(existing, "PC_PATH_MAX", 4096):
        return f"the path is {size} bytes long, more than this system allows"
    return None


def check_name_lengths(path: Path, flag: str) -> None:
    """Refuse a path the user typed for `flag` that can name no file (a name too long), before it is looked for."""
    why = name_too_long(path)
    if why:
        raise SkedUserError(f"{flag}: {why}. Pass a shorter {flag}.")


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


# ---- settings: the model's and datamanager's flags, checked by method/validation.py and each guidance ----

MODEL_FLAGS = "--pipeline.model."
DATAMANAGER_FLAGS = "--pipeline.datamanager."


class SkedOptionError(SkedUserError):
    """A setting out of its legal range; the message names the flag as typed and what to pass."""


class SkedOptionWarning(SkedWarning):
    """A legal setting that almost surely defeats the edit."""


def flag(name: str, prefix: str = MODEL_FLAGS) -> str:
    """A config field as the user types it: `lambda_pres` -> `--pipeline.model.lambda-pres`."""
    return prefix + name.replace("_", "-")


def is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def refuse(problems: Sequence[str]) -> None:
    """The one place a bad setting is refused (all problems at once, so one fix-up run is enough)."""
    if problems:
        raise SkedOptionError("Bad SKED setting" + ("s" if len(problems) > 1 else "") + ":\n  " + "\n  ".join(problems))


def warn_option(message: str) -> None:
    """A legal setting that almost surely defeats the edit: warned at the caller's caller (where it was read)."""
    warnings.warn(message, SkedOptionWarning, stacklevel=3)


@dataclass(frozen=True)
class UsualRange:
    """Where a legal value is meant: outside [low, high] it is almost surely a typo or a wrong unit, warned with why."""

    low: float
    high: float
    below: str
    above: str


def unusual(name: str, value, usual: UsualRange, default: Optional[float] = None) -> Optional[str]:
    """The warning for VALUE of the flag NAME (as typed) outside USUAL, or None; 0, where legal, means off."""
    if not is_number(value) or value == 0 or usual.low <= value <= usual.high:
        return None
    why = usual.below if value < usual.low else usual.above
    said_default = f", default {default:g}" if is_number(default) else ""
    return f"{name} {value:g}: {why} (usual {usual.low:g} to {usual.high:g}{said_default})."


def unusual_settings(config, ranges: Mapping[str, UsualRange], prefix: str = MODEL_FLAGS) -> List[str]:
    """The one check of usual ranges, for SKED's options and each guidance's (`ranges`: field name -> its range):
    a value outside its field's range is warned, named as typed with its default; one set but not a finite number
    is refused, as no range holds it."""
    defaults = {item.name: item.default for item in fields(config)}
    refuse([f"{flag(name, prefix)} {getattr(config, name)!r}: must be a finite number (usual {usual.low:g} to "
            f"{usual.high:g})." for name, usual in ranges.items()
            if getattr(config, name) is not None and not is_number(getattr(config, name))])
    messages = [unusual(flag(name, prefix), getattr(config, name), usual, defaults.get(name))
                for name, usual in ranges.items()]
    return [message for message in messages if message]
