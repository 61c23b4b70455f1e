"""The docs say what is true: every relative link resolves, and every command line they show exists with the flags
they give it (checked against the command's own --help)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from doc_commands import PAGES, ROOT, commands, flags, parser_key

LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
INLINE_CODE = re.compile(r"`([^`]+)`")
MODEL_FLAG = re.compile(r"--pipeline\.[\w.-]+")


def inline_sked_flags(text: str):
    """`--pipeline.*` flags named in inline code, but for a base's own command (`ns-train nerfacto ...`)."""
    for span in INLINE_CODE.findall(text):
        words = span.split()
        if words[:1] == ["ns-train"] and len(words) > 1 and not words[1].startswith("sked"):
            continue
        yield from MODEL_FLAG.findall(span)


def test_the_readme_fits_on_a_few_screens():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_every_relative_link_resolves(page):
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"^[a-z]+:", target) or target.startswith("#") or target.startswith("<"):
            continue
        if not (page.parent / target.split("#")[0]).exists():
            broken.append(target)
    assert broken == []


def test_the_extraction_finds_what_a_page_types(tmp_path):
    """The checks below can fail: a made-up page's command, flags and dataparser are found."""
    page = tmp_path / "page.md"
    page.write_text("text\n```bash\nns-train sked --load-dir runs/a \\\n  --no-such-flag 3 nerfstudio-data --data d  # c\n"
                    "sked-sketch check my-sketches/\n```\n")
    found = list(commands(page))
    assert [parser_key(words) for _, words in found] == [("ns-train", "sked", "nerfstudio-data"), ("sked-sketch", "check")]
    assert flags(found[0][1]) == ["--load-dir", "--no-such-flag", "--data"]
    inline = "`--pipeline.model.beta 0.1` and `ns-train nerfacto --pipeline.model.hidden-dim 8` and `ns-train sked --pipeline.x`"
    assert list(inline_sked_flags(inline)) == ["--pipeline.model.beta", "--pipeline.x"]


_helps = {}


def help_text(key) -> str:
    """The --help of a command (for ns-train: the method's, plus its dataparser's when one is typed)."""
    if key not in _helps:
        parts = [key] if key[0] != "ns-train" else [key[:i] for i in range(2, len(key) + 1)]
        text = ""
        for words in parts:
            program = str(Path(sys.executable).parent / words[0])
            result = subprocess.run([program, *words[1:], "--help"], capture_output=True, text=True, timeout=300,
                                    env={**os.environ, "COLUMNS": "250"})
            assert result.returncode == 0, f"{' '.join(words)} --help: {result.stderr[-1500:]}"
            text += result.stdout
        _helps[key] = text
    return _helps[key]


@pytest.mark.slow
def test_every_command_in_the_docs_exists_with_its_flags():
    missing = []
    for page in PAGES:
        for number, words in commands(page):
            key = parser_key(words)
            text = help_text(key)
            for flag in flags(words):
                if flag != "--help" and not re.search(re.escape(flag) + r"(?![\w.-])", text):
                    missing.append(f"{page.name}:{number}: {' '.join(key)} {flag}")
    assert missing == []


@pytest.mark.slow
def test_every_model_flag_the_docs_name_exists():
    text = "".join(help_text(("ns-train", "sked", f"pipeline.model.guidance:{guidance}"))
                   for guidance in ("stable-diffusion", "reference"))
    missing = sorted({f"{page.name}: {flag}" for page in PAGES for flag in inline_sked_flags(page.read_text())
                      if not re.search(re.escape(flag.rstrip(".")) + r"(?![\w-])", text)})
    assert missing == []


HARDWARE_ROWS = {
    "`sked`, nerfacto base (128 px)": "nerfacto@128",
    "`sked`, instant-ngp base (128 px)": "instant-ngp@128",
    "`sked`, splatfacto base (128 px": "splatfacto@128",
    "`sked-fast`, nerfacto base (64 px)": "nerfacto@64",
}


def test_the_readmes_hardware_table_is_the_memory_benchmarks():
    """Each row's figures are benchmarks/results/memory.json's, rounded: a rerun that moves them fails here until the
    README follows."""
    import json

    steps = json.loads((ROOT / "benchmarks" / "results" / "memory.json").read_text())["steps"]
    lines = (ROOT / "README.md").read_text().splitlines()
    for label, key in HARDWARE_ROWS.items():
        row = next((line for line in lines if line.strip().startswith(f"| {label}")), None)
        assert row is not None, f"README's hardware table has no row {label!r}"
        entry = steps[key]
        cells = [cell.strip() for cell in row.strip().strip("|").split("|")]
        expected = [f"{entry[name]:.1f} GB" for name in ("nerf_side_peak_gb", "total_fp32_gb", "projected_fp16_total_gb")]
        assert cells[1:4] == expected, f"{label}: README says {cells[1:4]}, memory.json {expected}"
