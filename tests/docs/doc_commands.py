"""The command lines in README.md and docs/*.md: what tests/docs/test_docs.py checks against the real parsers."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Dict, Iterator, List, Tuple

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMANDS = {"ns-train", "ns-viewer", "ns-render", "ns-export", "sked-sketch", "sked-eval", "sked-batch", "sked-demo",
            "sked-import-authors"}
SUBCOMMANDED = {"ns-render", "ns-export", "sked-sketch", "sked-batch"}
"""Commands whose first word after the name picks a subcommand with its own flags."""


def code_lines(page: Path) -> Iterator[Tuple[int, str]]:
    """Shell lines of the page's ``` blocks (continuations joined), with their line numbers."""
    fence, pending, start = None, "", 0
    for number, line in enumerate(page.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            fence = None if fence is not None else line.strip()[3:]
            continue
        if fence is None or fence not in ("", "bash", "sh", "shell", "console"):
            continue
        if not pending:
            start = number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""


def commands(page: Path) -> Iterator[Tuple[int, List[str]]]:
    """Each known command typed on the page, as its words (comments and prompts dropped)."""
    for number, line in code_lines(page):
        line = re.sub(r"(^|\s)#.*$", "", line).strip()
        for part in re.split(r"&&|;|\|", line):
            try:
                words = shlex.split(part)
            except ValueError:
                continue
            while words and (words[0] in ("$", "sudo") or "=" in words[0] and not words[0].startswith("-")):
                words = words[1:]
            if words and words[0] in COMMANDS:
                yield number, words


def parser_key(words: List[str]) -> Tuple[str, ...]:
    """Which help text a command's flags are in: the command, its method (ns-train) or subcommand, and for
    ns-train the dataparser typed after the flags."""
    name, rest = words[0], words[1:]
    positional = [w for w in rest if not w.startswith("-")]
    if name == "ns-train":
        method = positional[0] if positional else "sked"
        known = _dataparsers()
        chosen = [w for w in positional[1:] if ":" in w or w in known]  # subcommands: a guidance, the dataparser
        return (name, method, *chosen)
    if name in SUBCOMMANDED and rest and not rest[0].startswith("-") and rest[0] in _subcommands(name):
        return (name, rest[0])
    return (name,)


def flags(words: List[str]) -> List[str]:
    return [w.split("=")[0] for w in words[1:] if w.startswith("--") and len(w) > 2]


def _dataparsers() -> set:
    from nerfstudio.configs.dataparser_configs import all_dataparsers

    return set(all_dataparsers)


SUBCOMMANDS: Dict[str, set] = {
    "ns-render": {"camera-path", "interpolate", "spiral", "dataset"},
    "ns-export": {"pointcloud", "tsdf", "poisson", "marching-cubes", "cameras", "gaussian-splat"},
    "sked-sketch": {"canvases", "import", "check"},
    "sked-batch": {"run", "status", "report", "slurm", "local"},
}


def _subcommands(name: str) -> set:
    return SUBCOMMANDS.get(name, set())
