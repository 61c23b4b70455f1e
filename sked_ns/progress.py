"""One line per finished item of long work, with what is left: `sked-eval: sketch view 2/4 (12 s, about 12 s left)`."""

from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Optional, TextIO

EVERY_SECONDS = 10.0
"""Work of many small items (a base's fitting steps) says how far it is at most this often."""


class Progress:
    """Counts finished items of a known total and says so on stderr (a log keeps every line)."""

    def __init__(self, command: str, what: str, total: int, stream: Optional[TextIO] = None,
                 every_seconds: float = 0.0):
        """`every_seconds`: at most one line that often (and the last), for many small items."""
        self.command, self.what, self.total = command, what, max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.done, self.started = 0, time.monotonic()
        self.every_seconds, self._said = every_seconds, float("-inf")
        self._lock = threading.Lock()  # sked-batch finishes jobs from several threads

    def line(self, done: int, elapsed: float, note: str = "") -> str:
        eta = f", about {_duration(elapsed / done * (self.total - done))} left" if 0 < done < self.total else ""
        return f"{self.command}: {self.what} {done}/{self.total} ({_duration(elapsed)}{eta}){note}"

    def step(self, note: str = "") -> None:
        with self._lock:
            self.done += 1
            now = time.monotonic()
            if now - self._said < self.every_seconds and self.done < self.total:
                return
            self._said = now
            print(self.line(self.done, now - self.started, note), file=self.stream, flush=True)


def _duration(seconds: float) -> str:
    seconds = max(seconds, 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


HEARTBEAT_SECONDS = 30.0
"""Work with no countable items (a compiler, one long render) says it is still at it this often."""


class Heartbeat:
    """`with Heartbeat("nerfacc", "compiling its CUDA kernels"):` says what is happening when it starts, then every
    `every_seconds` how long it has been at it, and how long it took when it ends (a thread, so the work needs no
    hooks). Lines go to stderr as `command: line`, or to `say` (e.g. a viewer's status text)."""

    def __init__(self, command: str, what: str, stream: Optional[TextIO] = None,
                 every_seconds: float = HEARTBEAT_SECONDS, expected: str = "",
                 say: Optional[Callable[[str], None]] = None):
        self.command, self.what, self.expected = command, what, expected
        self.stream = stream if stream is not None else sys.stderr
        self.every_seconds = every_seconds
        self.say = say
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def _say(self, line: str) -> None:
        if self.say is not None:
            self.say(line)
        else:
            print(f"{self.command}: {line}", file=self.stream, flush=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.every_seconds):
            self._say(f"still {self.what} ({_duration(time.monotonic() - self.started)})")

    def __enter__(self) -> "Heartbeat":
        self.started = time.monotonic()
        self._say(f"{self.what}{' (' + self.expected + ')' if self.expected else ''}...")
        self._thread = threading.Thread(target=self._beat, name=f"{self.command} heartbeat", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, kind, error, traceback) -> None:
        self._stop.set()
        self._thread.join()
        if kind is None:
            self._say(f"done {self.what} ({_duration(time.monotonic() - self.started)})")
