"""`ns-train sked`'s mistyped flags: one `error:` line with the flags meant, and tyro's own box for other methods."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sked_ns.engine import parse_errors
from sked_ns.engine.parse_errors import close_flags, flags_of, sked_train_method
from sked_ns.session.methods import SESSION_METHODS

tyro_errors = pytest.importorskip("tyro._errors", reason="a tyro without its parse-error hook keeps its box")


def test_only_an_ns_train_of_a_sked_method_is_recognised():
    methods = list(SESSION_METHODS)
    assert sked_train_method(["/x/bin/ns-train", "sked", "--help"], methods) == "sked"
    assert sked_train_method(["/x/nerfstudio/scripts/train.py", "sked-fast"], methods) == "sked-fast"
    assert sked_train_method(["/x/bin/ns-train", "nerfacto", "--data", "sked"], methods) is None
    assert sked_train_method(["/x/bin/ns-render", "sked"], methods) is None
    assert sked_train_method(["/x/bin/ns-train"], methods) is None


@pytest.fixture(scope="module")
def flags():
    return sorted(set(flags_of(SESSION_METHODS["sked"].config)))


def test_the_flags_are_tyros_names_with_the_dataparser_after_its_subcommand(flags):
    assert {"--prompt", "--load-dir", "--max-num-iterations", "--pipeline.model.sketches",
            "--pipeline.model.guidance.guidance-scale", "nerfstudio-data --downscale-factor"} <= set(flags)
    assert not [flag for flag in flags if flag.startswith("--pipeline.datamanager.dataparser.")]
    assert not [flag for flag in flags if "_" in flag]


@pytest.mark.parametrize("typed, meant", [
    ("--max-num-iteration", ["--max-num-iterations"]),
    ("--promt", ["--prompt"]),
    ("--pipeline.model.guidance-scale", ["--pipeline.model.guidance.guidance-scale"]),
    ("--pipeline.model.sketch", ["--pipeline.model.sketches"]),
    ("--downscale-factor", ["nerfstudio-data --downscale-factor"]),
    ("--no-such-thing-at-all", []),
])
def test_a_mistyped_flag_is_answered_with_the_flags_it_meant(flags, typed, meant):
    assert close_flags(typed, flags)[:1] == meant


def test_each_kind_of_parse_error_is_one_line_and_unknown_kinds_fall_through(flags, capsys):
    hook = parse_errors.one_line_hook("ns-train sked", SESSION_METHODS["sked"].config)
    with pytest.raises(SystemExit) as stopped:
        hook(tyro_errors.UnrecognizedArgs(prog="ns-train sked", tokens=["--promt", "x"]))
    assert stopped.value.code == 2
    said = capsys.readouterr().err
    assert said == "error: ns-train sked: unrecognized option --promt (did you mean --prompt?) " \
                   "(see ns-train sked --help).\n"
    with pytest.raises(SystemExit):
        hook(tyro_errors.UnrecognizedArgs(prog="ns-train sked", tokens=["--prompt"]))
    assert "at that place" in capsys.readouterr().err

    class Unknown(tyro_errors.ParseErrorEvent):
        pass

    assert hook(Unknown(prog="ns-train sked")) is None  # tyro draws its own box for what this does not know
    assert capsys.readouterr().err == ""


def _ns_train(*argv):
    program = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    return subprocess.run([program, *argv], capture_output=True, text=True, timeout=300)


def _own_lines(stderr: str) -> list:
    """stderr without the libraries' import-time FutureWarnings (a warning line and its indented source line)."""
    return [line for line in stderr.splitlines() if line.strip() and "Warning" not in line and line[:1] != " "]


@pytest.mark.slow
def test_ns_train_sked_says_a_parse_error_in_one_line_and_other_methods_keep_tyros_box():
    result = _ns_train("sked", "--max-num-iteration", "3")
    assert result.returncode == 2
    assert _own_lines(result.stderr) == ["error: ns-train sked: unrecognized option --max-num-iteration (did you "
                                         "mean --max-num-iterations?) (see ns-train sked --help)."], result.stderr
    result = _ns_train("sked", "--machine.device-type", "tpu")
    assert result.returncode == 2 and len(_own_lines(result.stderr)) == 1, result.stderr
    assert "--machine.device-type: invalid choice 'tpu'" in result.stderr
    stock = _ns_train("nerfacto", "--max-num-iteration", "3")  # the plugin changes nothing outside SKED
    assert stock.returncode == 2 and "error: ns-train" not in stock.stderr
    assert "Unrecognized options" in stock.stderr and "╭" in stock.stderr
