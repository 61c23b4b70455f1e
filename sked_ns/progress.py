"""One line per finished item of long work, with what is left: `sked-eval: sketch view 2/4 (12 s, about 12 s left)`."""

from __future__ import annotations

import sys
import threading
import time
from typing import Optional, TextIO


class Progress:
    """Counts finished items of a known total and says so on stderr (a log keeps every line)."""

    def __init__(self, command: str, what: str, total: int, stream: Optional[TextIO] = None):
        self.command, self.what, self.total = command, what, max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.done, self.started = 0, time.monotonic()
        self._lock = threading.Lock()  # sked-batch finishes jobs from several threads

    def line(self, done: int, elapsed: float, note: str = "") -> str:
        eta = f", about {_duration(elapsed / done * (self.total - done))} left" if 0 < done < self.total else ""
        return f"{self.command}: {self.what} {done}/{self.total} ({_duration(elapsed)}{eta}){note}"

    def step(self, note: str = "") -> None:
        with self._lock:
            self.done += 1
            print(self.line(self.done, time.monotonic() - self.started, note), file=self.stream, flush=True)


def _duration(seconds: float) -> str:
    seconds = max(seconds, 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
