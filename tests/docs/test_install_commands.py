"""The scripts docs/install.md tells its reader to run answer --help as printed: a usage text and status 0, without
starting their work (test_docs.py checks the ns-* and sked-* commands' flags)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "install.md"
BIN = Path(sys.executable).parent
SCRIPT = re.compile(r"(?:(?:bash|python) )?((?:\.ci|benchmarks)/[\w./-]*\w)|python -m ([\w.]+)|\b(hf) download\b")
SET_UP_FIRST = {".ci/demo", ".ci/test"}
"""Scripts that build .venv before passing their arguments on (to sked-demo, pytest): their --help is those
commands' own, which test_docs.py and pytest answer."""


def named_scripts() -> set:
    return {next(group for group in match.groups() if group) for match in SCRIPT.finditer(PAGE.read_text())}


def help_command(script: str) -> list:
    if script == "hf":
        return [str(BIN / "hf"), "download", "--help"]
    if script.endswith(".py"):
        return [sys.executable, script, "--help"]
    if "/" not in script:
        return [sys.executable, "-m", script, "--help"]
    return ["bash", script, "--help"]


def test_the_page_names_the_scripts_this_test_runs():
    assert {".ci/offline/wheelhouse", ".ci/offline/lists.py", "benchmarks/gpu_check.py", "hf",
            "sked_ns.models.nerf.nerfacc_kernels"} <= named_scripts()


@pytest.mark.parametrize("script", sorted(named_scripts() - SET_UP_FIRST))
def test_each_script_the_page_names_answers_help(script):
    # A guard, not a measure: a script that ignores --help starts its work (minutes), and is stopped here.
    result = subprocess.run(help_command(script), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"{script} --help: status {result.returncode}\n{result.stderr[-2000:]}"
    assert re.search(r"usage|Usage", result.stdout), f"{script} --help printed no usage:\n{result.stdout[-2000:]}"


@pytest.mark.parametrize("arguments", [["lock", "--help"], ["imports", "--help"]])
def test_the_lists_subcommands_answer_help(arguments):
    result = subprocess.run([sys.executable, ".ci/offline/lists.py", *arguments], cwd=ROOT, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0 and "usage: python .ci/offline/lists.py " + arguments[0] in result.stdout


@pytest.mark.parametrize("command, said", [
    (["bash", ".ci/offline/wheelhouse", "--bogus"], "error: unknown option --bogus"),
    (["bash", ".ci/offline/wheelhouse", "--python"], "error: --python needs a value"),
    ([sys.executable, ".ci/offline/lists.py", "imports", "bogus"], "invalid choice: 'bogus'"),
])
def test_a_wrong_argument_is_one_error_before_any_work(command, said):
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and said in result.stderr, result.stderr[-2000:]
