"""A benchmark's results file and work folder have one writer at a time.

Two benchmarks started on the same `--output` (or the same work folder, whose bases and edits they reuse) would
interleave their writes. Each script claims both through the run lock the edits themselves take (sked_ns/run_lock.py)
before it measures anything, so the second is refused in one `error:` line naming the first; the locks end with
the process, however it ends.
"""

from __future__ import annotations

import atexit
import contextlib
from pathlib import Path
from typing import Optional

from sked_ns import run_lock


def claim(script: str, output: Path, work: Optional[Path] = None) -> None:
    """Be the one writer of `output` and of `work` (when given) until this process ends."""
    held = contextlib.ExitStack()
    try:
        held.enter_context(run_lock.writing(output, f"Another {script} writes it: wait for it, or give another "
                                                    "output file."))
        if work is not None:
            run_lock.hold(work, "Another benchmark uses it: wait for it, or give another work folder.")
            held.callback(run_lock.release, work)
    except BaseException:
        held.close()
        raise
    atexit.register(held.close)
