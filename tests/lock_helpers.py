"""Other processes holding a run folder or writing a file, as the run-lock tests and sked-batch's tests need."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

HOLD = "import sys, time; from sked_ns.run_lock import hold; hold(sys.argv[1], ''); print('held', flush=True); time.sleep(900)"
"""Another process holding a folder as an edit does, until it is killed."""
WRITE = ("import sys, time; from sked_ns.run_lock import writing\nwith writing(sys.argv[1], ''):\n"
         " print('held', flush=True); time.sleep(900)")
"""Another process writing a file (or a folder's files), until it is killed."""


def holding(folder: Path, code: str = HOLD, *args: str) -> subprocess.Popen:
    child = subprocess.Popen([sys.executable, "-c", code, str(folder), *args], stdout=subprocess.PIPE, text=True)
    for line in child.stdout:  # after what the command prints itself
        child.said = line.split()
        if child.said[-1:] == ["held"]:
            return child
    pytest.fail(f"the child did not take the lock (exit code {child.wait()})")


def killed(child: subprocess.Popen) -> None:
    child.send_signal(signal.SIGKILL)
    child.wait()
