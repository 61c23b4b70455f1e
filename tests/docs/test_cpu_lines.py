"""The README's lines for a machine without a GPU: the flags nerfstudio needs there, cheap settings for what is slow
on a CPU, and the demo's own folders (what `sked-demo` writes is where the lines look)."""

from __future__ import annotations

import re

from doc_commands import ROOT, code_lines


def cpu_lines() -> list:
    """The words of each command in the README's section "Without a GPU" (comments dropped)."""
    page = ROOT / "README.md"
    lines = page.read_text().splitlines()
    start = lines.index("## Without a GPU") + 1
    end = next(number for number, line in enumerate(lines[start:], start + 1) if line.startswith("## "))
    return [re.sub(r"\s+#.*$", "", line).split() for number, line in code_lines(page) if start < number < end]


def test_every_ns_train_line_runs_on_the_cpu_without_the_viewer_waiting():
    lines = cpu_lines()
    trains = [words for words in lines if words[0] == "ns-train"]
    assert trains
    for words in trains:
        assert words[words.index("--machine.device-type") + 1] == "cpu"
        assert words[words.index("--vis") + 1] == "tensorboard"
        assert "pipeline.model.guidance:reference" in words  # no Stable Diffusion weights needed


def test_what_is_slow_on_a_cpu_is_given_a_cheap_setting():
    lines = {words[0]: words for words in cpu_lines()}
    assert int(lines["ns-export"][lines["ns-export"].index("--num-points") + 1]) <= 10_000
    for flag in ("--resolution", "--novel-resolution"):
        assert int(lines["sked-eval"][lines["sked-eval"].index(flag) + 1]) <= 128


def test_the_lines_read_what_the_demo_writes():
    from sked_ns.demo.rerun import base_folder

    [train] = [words for words in cpu_lines() if words[0] == "ns-train"]
    output = "demo_output"  # sked-demo's default --output
    assert train[train.index("--load-dir") + 1] == str(base_folder(output, "nerfacto") / "nerfacto" / "base")
    assert train[train.index("--sketches") + 1] == f"{output}/sketches"
    assert train[train.index("--data") + 1] == f"{output}/data"
