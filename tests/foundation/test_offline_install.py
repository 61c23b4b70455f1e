"""The offline wheelhouse lists cover what the commands import (else an offline node fails at run time)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

OFFLINE = Path(__file__).resolve().parents[2] / ".ci" / "offline"
sys.path.insert(0, str(OFFLINE))

import lists  # noqa: E402


def test_runtime_list_covers_every_import_of_the_commands():
    result = subprocess.run([sys.executable, str(OFFLINE / "lists.py"), "imports", "runtime"], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    imported = set(result.stdout.split())
    listed = set(lists.read_list(OFFLINE / "runtime.txt"))
    assert {"nerfstudio", "diffusers", "transformers", "nerfacc", "viser"} <= imported
    missing = imported - listed
    assert not missing, f"imported but not in .ci/offline/runtime.txt: {sorted(missing)}; run `python .ci/offline/lists.py lock`"


def test_lists_are_pinned_and_leave_the_nodes_torch_alone():
    runtime, export = lists.read_list(OFFLINE / "runtime.txt"), lists.read_list(OFFLINE / "export.txt")
    assert all(runtime.values()) and all(export.values()), "every line is name==version"
    assert not {"torch", "torchvision", "numpy", "pillow"} & (set(runtime) | set(export))
    assert not set(runtime) & set(export)
    assert "open3d" in export and "open3d" not in runtime
    # One distribution per module: both OpenCV wheels install `cv2`, and the last one installed wins.
    assert "opencv-python-headless" not in runtime and "opencv-contrib-python-headless" in runtime
