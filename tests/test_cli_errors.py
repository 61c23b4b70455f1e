"""A user error in an `ns-*` command prints its message alone; the traceback only on request."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from sked_ns import errors
from sked_ns.errors import SkedFileNotFoundError, SkedUserError


def test_ns_train_sked_prints_a_user_error_without_traceback(tmp_path):
    ns_train = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    missing = tmp_path / "no-such-run"
    result = subprocess.run(
        [ns_train, "sked", "--load-dir", str(missing), "--sketches", str(tmp_path), "--output-dir", str(tmp_path / "out"),
         "nerfstudio-data", "--data", str(tmp_path)], capture_output=True, text=True, timeout=300,
    )
    assert result.returncode != 0
    assert f"error: --load-dir {missing}: no such file or folder." in result.stderr, result.stderr[-3000:]
    assert "Traceback" not in result.stderr + result.stdout, result.stderr[-3000:]
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_the_hook_prints_user_errors_alone_and_chains_the_rest(monkeypatch, capsys):
    seen = []
    monkeypatch.setattr(errors, "_previous_excepthook", lambda *report: seen.append(report[0]))
    monkeypatch.delenv(errors.TRACEBACK_ENV, raising=False)
    errors.excepthook(SkedFileNotFoundError, SkedFileNotFoundError("--data x: no such file or folder."), None)
    assert capsys.readouterr().err == "error: --data x: no such file or folder.\n" and not seen
    errors.excepthook(KeyError, KeyError("a bug"), None)  # not a user error: the full report
    assert seen == [KeyError]
    monkeypatch.setenv(errors.TRACEBACK_ENV, "1")
    errors.excepthook(SkedUserError, SkedUserError("--x: bad"), None)
    assert seen == [KeyError, SkedUserError] and capsys.readouterr().err == ""


def test_the_plugin_installs_the_hook_once():
    import sked_ns  # noqa: F401  (every ns-* command imports it through the method registry)

    assert sys.excepthook is errors.excepthook
    errors.install_excepthook()
    assert errors._previous_excepthook is not errors.excepthook  # no loop to itself
