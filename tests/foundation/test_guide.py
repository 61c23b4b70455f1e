"""Messages and --help name guide pages by paths that exist where the user is: the installed copy or the sources."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from sked_ns.guide import guide

PACKAGE = Path(__file__).resolve().parents[2] / "sked_ns"


def test_every_page_the_code_names_exists():
    named = {node.args[0].value for path in PACKAGE.rglob("*.py") for node in ast.walk(ast.parse(path.read_text()))
             if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "guide" and node.args
             and isinstance(node.args[0], ast.Constant)}
    assert {"batch.md", "troubleshooting.md", "benchmarks.md"} <= named
    for page in named:
        assert Path(guide(page)).is_file(), page


def test_no_message_names_a_path_inside_the_repository():
    """`docs/x.md` in a string a user sees means nothing to an installed user: guide() gives the real path."""
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Call,)) and getattr(node.func, "id", "") in ("SkedUserError", "SkedFileNotFoundError",
                                                                                  "warn", "print"):
                text = ast.unparse(node)
                offenders += [f"{path.relative_to(PACKAGE)}: {text[:80]}"] if "docs/" in text else []
    assert not offenders, offenders


def test_an_installed_package_reads_its_own_copy_of_the_guide(tmp_path):
    source = tmp_path / "source"  # setuptools builds in the tree it is given: a copy, not the checkout
    for name in ("sked_ns", "configs", "docs"):
        shutil.copytree(PACKAGE.parent / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (PACKAGE.parent / name).exists():
            shutil.copy(PACKAGE.parent / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(source),
                    "-w", str(tmp_path / "wheel")], check=True, capture_output=True, timeout=600)
    (wheel,) = (tmp_path / "wheel").glob("sked_ns-*.whl")
    zipfile.ZipFile(wheel).extractall(tmp_path / "site")
    installed = tmp_path / "site" / "sked_ns" / "docs" / "batch.md"
    assert installed.read_text() == (PACKAGE.parent / "docs" / "batch.md").read_text()
    found = subprocess.run([sys.executable, "-c", "from sked_ns.guide import guide; print(guide('batch.md'))"],
                           cwd=tmp_path, env={"PYTHONPATH": str(tmp_path / "site"), "PATH": "/usr/bin:/bin"},
                           capture_output=True, text=True, timeout=300)
    assert found.stdout.strip() == str(installed.resolve()), found.stderr[-2000:]
