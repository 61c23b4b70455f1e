"""One writer per run folder and per output file: an advisory lock that ends with the process holding it.

Two `ns-train sked` runs given the same --output-dir, experiment and --timestamp (scripts that start edits in
the same second) would write one config.yml and one set of checkpoints. A writer holds `fcntl.flock` on a lock
file through a descriptor it keeps open: `.sked-writer.lock` inside a run folder for the run's life (`hold`), or
`.<name>.lock` beside an output file or folder while it is written (`writing`). The kernel drops the lock when
the process ends in any way, kill -9 included, so a killed writer leaves nothing that blocks the next one.
The file records who holds it (pid, host, process start time, command): for the message the next writer gets,
and for `holder`, which tells a live writer from an ended one without taking the lock (sked-batch).

On network file systems: NFSv4 and most cluster file systems take flock to the server, so it holds across
nodes; some mounts refuse it (ENOLCK: NFS without its lock daemon) or keep it per node (Lustre's localflock).
Where flock is refused, the record is the lock: a live process on this host (its pid and start time) holds
it, and a record from another host counts as held until that writer ends cleanly (clearing it) or the user
removes the file. Where flock is per node, two nodes can both write; the later one's record replaces the
first's, and `write_failure` names it when the first can no longer write.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import json
import os
import socket
import sys
from pathlib import Path
from typing import Dict, Iterator, Optional

from sked_ns.errors import SkedUserError

try:
    import fcntl
except ImportError:  # not a POSIX system: the record is the lock
    fcntl = None

LOCK_NAME = ".sked-writer.lock"
_UNSUPPORTED = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EINVAL}
_held: Dict[Path, int] = {}
"""Folders this process writes (`hold`), with the descriptor that holds each one's lock."""
_scoped: set = set()
"""Descriptors of the locks held while a file is written (`writing`)."""
_watching_forks = False
"""Whether `_forget_in_child` runs in forked children: registered with the first lock, so a process that takes
none (every ns-* command imports this module) gets no hook."""


class WriterBusy(SkedUserError):
    """Another live process writes there; `record` says which (empty when its record is not written yet)."""

    def __init__(self, message: str, record: dict) -> None:
        super().__init__(message)
        self.record = record


class _Taken(Exception):
    def __init__(self, record: dict, unsure: bool = False) -> None:
        super().__init__()
        self.record, self.unsure = record, unsure


def process_start(pid: int) -> Optional[str]:
    """The process's start time (Linux: clock ticks since boot), so a reused pid is not taken for the writer."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def this_process() -> dict:
    """The record this process writes into a lock it takes."""
    argv = [Path(sys.argv[0]).name, *sys.argv[1:]] if sys.argv and sys.argv[0] else []
    command = " ".join(argv)
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": process_start(os.getpid()),
            "since": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": command if len(command) <= 300 else command[:297] + "..."}


def alive(record: dict) -> Optional[bool]:
    """Whether the process a record names still runs; None when it ran on another host (cannot tell from here)."""
    if record.get("host") != socket.gethostname():
        return None
    pid = int(record.get("pid") or 0)
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        pass
    started = record.get("started")
    return started is None or process_start(pid) in (None, started)


def describe(record: dict) -> str:
    """`pid 123 on host since <time>: ns-train sked ...`, as far as the record tells."""
    if not record.get("pid"):
        return "its record is not written yet"
    text = f"pid {record['pid']} on {record.get('host', '?')}"
    if record.get("since"):
        text += f" since {record['since']}"
    return text + (f": {record['command']}" if record.get("command") else "")


def is_this_process(record: dict) -> bool:
    """The record names the process reading it."""
    return record.get("pid") == os.getpid() and record.get("host") == socket.gethostname()


def _read(fd: int) -> dict:
    try:
        record = json.loads(os.pread(fd, 65536, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _write(fd: int, record: dict) -> None:
    with contextlib.suppress(OSError):  # a lock file another user made is locked read-only: its record stays
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)


def _open(path: Path, create: bool) -> int:
    """The lock file, for writing its record where allowed (flock needs no write access on a local disk)."""
    cloexec = getattr(os, "O_CLOEXEC", 0)  # a command this process starts holds nothing
    try:
        return os.open(path, os.O_RDWR | (os.O_CREAT if create else 0) | cloexec, 0o666)
    except PermissionError:
        return os.open(path, os.O_RDONLY | cloexec)


def _names(fd: int, path: Path) -> bool:
    """The descriptor is the file now at `path` (not one its last holder removed)."""
    try:
        here, there = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def _lock(fd: int, wait: bool) -> None:
    if fcntl is not None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            return
        except BlockingIOError:
            raise _Taken(_read(fd)) from None
        except OSError as error:
            if error.errno not in _UNSUPPORTED:
                raise
    # The file system refuses flock: the record is the lock (the module's docstring).
    record = _read(fd)
    live = alive(record) if record.get("pid") else False
    if live is not False and not is_this_process(record):
        raise _Taken(record, unsure=live is None)


def _acquire(path: Path, wait: bool = False) -> int:
    """A descriptor holding the lock on `path` (created if missing), with this process's record in it."""
    _watch_forks()
    while True:
        fd = _open(path, create=True)
        try:
            _lock(fd, wait)
        except BaseException:
            os.close(fd)
            raise
        if _names(fd, path):
            _write(fd, this_process())
            return fd
        os.close(fd)  # its last holder removed the file after we opened it: lock the one there now


def _release(fd: int, remove: Optional[Path] = None) -> None:
    """Clear the record (no live process writes any more) or remove the file, then unlock by closing."""
    with contextlib.suppress(OSError):
        if remove is not None and _names(fd, remove):
            os.unlink(remove)  # while locked: whoever waits on this file finds it gone and locks the next one
        else:
            os.ftruncate(fd, 0)
    os.close(fd)


def _busy(target: Path, lock: Path, taken: _Taken, hint: str) -> WriterBusy:
    who = "another task of this process" if is_this_process(taken.record) else "another process"
    message = f"{target}: {who} is writing to it ({describe(taken.record)}). {hint}"
    if taken.unsure:
        message += f" If that process has ended, remove {lock}."
    return WriterBusy(message, taken.record)


def _key(folder: Path) -> Path:
    return Path(os.path.abspath(folder))


def hold(folder: Path, hint: str) -> None:
    """Be the one writer of `folder` until this process ends or calls `release` (again: nothing to do).
    WriterBusy (a user error) when another live process holds it; `hint` says what to do then."""
    folder = _key(folder)
    if folder in _held:
        return
    folder.mkdir(parents=True, exist_ok=True)
    try:
        _held[folder] = _acquire(folder / LOCK_NAME)
    except _Taken as taken:
        raise _busy(folder, folder / LOCK_NAME, taken, hint) from None


def release(folder: Path) -> None:
    """Stop being the writer of `folder` (the run ended; this process goes on)."""
    fd = _held.pop(_key(folder), None)
    if fd is not None:
        _release(fd)


@contextlib.contextmanager
def writing(target: Path, hint: str, wait: bool = False) -> Iterator[None]:
    """Be the one writer of the file or folder `target` while the block runs (its lock file beside it, removed
    after). WriterBusy when another process writes it, or with `wait`, wait for that one to end."""
    target = _key(target)
    lock = target.parent / f".{target.name}.lock"
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = _acquire(lock, wait)
    except _Taken as taken:
        raise _busy(target, lock, taken, hint) from None
    _scoped.add(fd)
    try:
        yield
    finally:
        _scoped.discard(fd)
        _release(fd, remove=lock)


def holder(folder: Path) -> Optional[dict]:
    """The record of the live process that holds `folder`'s lock (`hold`), or None. Read without taking the lock
    when that process is on this host, so a writer starting now is never refused because of the look."""
    path = Path(folder) / LOCK_NAME
    try:
        fd = _open(path, create=False)
    except OSError:
        return None
    try:
        record = _read(fd)
        if not record.get("pid"):
            return None  # cleared by a writer that ended (or one that has not written it yet)
        live = alive(record)
        if live is not None:
            return record if live else None
        try:  # another host: ask its lock
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return record
        except (OSError, AttributeError):
            return record  # the file system refuses flock: the record counts (the module's docstring)
        return None
    finally:
        os.close(fd)


def write_failure(path: Path, error: BaseException, what: str) -> SkedUserError:
    """Why `what` (`path`, in a folder this process holds) could not be written, as a user error: another
    writer in the same folder when the lock did not keep it out, else the disk."""
    for folder, fd in _held.items():
        if folder in _key(path).parents:
            record = _read(fd)
            if record.get("pid") and not is_this_process(record):
                return SkedUserError(
                    f"{path}: cannot write the {what} ({error}): another process is writing to {folder} too "
                    f"({describe(record)}; the file system did not keep it out). The run folder now holds files "
                    "of both: stop one of them, and give every run its own --timestamp or --output-dir.")
            if not folder.is_dir():
                return SkedUserError(f"{path}: cannot write the {what}: its run folder {folder} was removed while "
                                     "the edit ran.")
    return SkedUserError(f"{path}: cannot write the {what} ({error}); check the free space and --output-dir.")


def _forget_in_child() -> None:
    """A forked child (a data loader's worker) closes its copies: the lock stays the parent's, and ends with it."""
    for fd in [*_held.values(), *_scoped]:
        with contextlib.suppress(OSError):
            os.close(fd)
    _held.clear()
    _scoped.clear()


def _watch_forks() -> None:
    global _watching_forks
    if not _watching_forks and hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=_forget_in_child)
    _watching_forks = True
