"""`ns-train sked`'s mistyped flags: one `error:` line with the flags meant, and tyro's own box for other methods."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Literal, Tuple

import pytest
import tyro

from sked_ns.engine import parse_errors
from sked_ns.engine.command_line import CommandLine, flags_of
from sked_ns.engine.parse_errors import close_flags, describe, misspelt_sked_method, sked_train_method
from sked_ns.guidance import guidance_components
from sked_ns.session.methods import SESSION_METHODS

tyro_errors = pytest.importorskip("tyro._errors", reason="a tyro without its parse-error hook keeps its box")

SD, REFERENCE = "pipeline.model.guidance:stable-diffusion", "pipeline.model.guidance:reference"
REFERENCE_SETTINGS = [f"--pipeline.model.guidance.{item.name.replace('_', '-')}"
                      for item in dataclasses.fields(guidance_components()["reference"]) if item.init and item.name[0] != "_"]


def test_only_an_ns_train_of_a_sked_method_is_recognised():
    methods = list(SESSION_METHODS)
    assert sked_train_method(["/x/bin/ns-train", "sked", "--help"], methods) == "sked"
    assert sked_train_method(["/x/nerfstudio/scripts/train.py", "sked-fast"], methods) == "sked-fast"
    assert sked_train_method(["/x/bin/ns-train", "nerfacto", "--data", "sked"], methods) is None
    assert sked_train_method(["/x/bin/ns-render", "sked"], methods) is None
    assert sked_train_method(["/x/bin/ns-train"], methods) is None


@pytest.fixture(scope="module")
def line():
    return CommandLine.of(SESSION_METHODS["sked"].config)


@pytest.fixture(scope="module")
def flags(line):
    return sorted(set(line.flags))


def test_the_flags_are_tyros_names_each_after_the_subcommand_it_follows(flags, line):
    assert {"--prompt", "--load-dir", "--max-num-iterations", "--pipeline.model.sketches",
            f"{SD} --pipeline.model.guidance.guidance-scale", f"{REFERENCE} --pipeline.model.guidance.target",
            "nerfstudio-data --downscale-factor", "--optimizers.fields.optimizer.lr"} <= set(flags)
    assert sorted(set(flags_of(SESSION_METHODS["sked"].config))) == flags
    assert not [flag for flag in flags if flag.startswith("--pipeline.datamanager.dataparser.")]
    assert not [flag for flag in flags if "_" in flag]
    # The base's architecture is hidden from tyro (copied from the base): offered nowhere, known as the base's.
    assert "--pipeline.model.use-average-appearance-embedding" in line.hidden
    assert not [flag for flag in flags if "use-average-appearance-embedding" in flag]
    assert line.defaults == {"pipeline.model.guidance": SD, "dataparser": "nerfstudio-data"}
    assert {SD, REFERENCE, "nerfstudio-data", "blender-data"} <= set(line.subcommands)


@pytest.mark.parametrize("typed, meant", [
    ("--max-num-iteration", ["--max-num-iterations"]),
    ("--promt", ["--prompt"]),
    ("--pipeline.model.guidance-scale", [f"{SD} --pipeline.model.guidance.guidance-scale"]),
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


def _unrecognized(line, tokens, words):
    return describe(tyro_errors.UnrecognizedArgs(prog="ns-train", tokens=tokens), line, words)


@pytest.mark.parametrize("words, tokens, said", [
    # A misspelt subcommand: the subcommands tyro offers in its group, the nearest first.
    (["pipeline.model.guidance:refrence"], None, f"unknown subcommand pipeline.model.guidance:refrence (did you "
                                                 f"mean {REFERENCE}?); the guidance subcommands are {SD}, {REFERENCE}"),
    (["pipeline.model.guidanc:reference"], None, f"unknown subcommand pipeline.model.guidanc:reference "
                                                 f"(did you mean {REFERENCE}?)"),
    (["nerfstudio-dat"], None, "unknown subcommand nerfstudio-dat (did you mean nerfstudio-data?)"),
    # The options after a misspelt subcommand were not recognised because it was not: it alone is said.
    ([REFERENCE, "nerfstudio-dat", "--data", "D"], ["nerfstudio-dat", "--data", "D"],
     "unknown subcommand nerfstudio-dat (did you mean nerfstudio-data?)"),
    (["nerfstudio-dat", "--data", "D", "--downscale-factor", "2"], ["nerfstudio-dat", "--downscale-factor", "2"],
     "unknown subcommand nerfstudio-dat (did you mean nerfstudio-data?)"),
    (["colmap-dat", "--data", "D", "--colmap-path", "x"], ["colmap-dat", "--colmap-path", "x"],
     "unknown subcommand colmap-dat (did you mean colmap?)"),
    (["pipeline.model.guidance:refrence", "--pipeline.model.guidance.target", "vase"], None,
     f"unknown subcommand pipeline.model.guidance:refrence (did you mean {REFERENCE}?); the guidance subcommands are "
     f"{SD}, {REFERENCE}"),
    (["--promt", "x", "nerfstudio-dat", "--data", "D"], ["--promt", "x", "nerfstudio-dat"],
     "unrecognized option --promt (did you mean --prompt?); unknown subcommand nerfstudio-dat (did you mean "
     "nerfstudio-data?)"),
    ([REFERENCE, SD], [SD], f"{SD}: {REFERENCE} was already given (one guidance at a time)"),
    # A word processor's dash, an en dash, one hyphen: the flag with two ASCII hyphens.
    (["\u2014prompt", "a hat"], None, "\u2014prompt begins with a typographic dash (em dash, what word processors "
                                      "make of --): type --prompt (two ASCII hyphens)"),
    (["\u2013prompt=a hat"], None, "\u2013prompt begins with a typographic dash (en dash, what word processors "
                                   "make of --): type --prompt (two ASCII hyphens)"),
    (["\u2014promt", "a hat"], None, "\u2014promt begins with a typographic dash (em dash, what word processors "
                                     "make of --), not two ASCII hyphens (did you mean --prompt?)"),
    (["-prompt", "x"], None, "-prompt begins with one hyphen: type --prompt (two ASCII hyphens)"),
    # A guidance's setting where that guidance is not the one chosen, or before it is named.
    ([REFERENCE, "--pipeline.model.guidance.guidance-scale", "5"], ["--pipeline.model.guidance.guidance-scale", "5"],
     f"the guidance {REFERENCE} has no setting --pipeline.model.guidance.guidance-scale (a setting of {SD}, the "
     f"default guidance); its settings are {', '.join(REFERENCE_SETTINGS)}"),
    (["--pipeline.model.guidance.guidance-scale", "5"], None,
     f"--pipeline.model.guidance.guidance-scale is a setting of {SD}, the default guidance: name the guidance "
     f"before it ({SD} --pipeline.model.guidance.guidance-scale ...)"),
    (["--pipeline.model.guidance.target", "vase", REFERENCE], ["--pipeline.model.guidance.target", "vase"],
     f"--pipeline.model.guidance.target at that place: it goes right after {REFERENCE}, before the dataparser's name"),
    # Options of the dataparser before its name, of the edit after a subcommand, of the base.
    (["--downscale-factor", "2"], None,
     "--downscale-factor is an option of the dataparser: it goes after its name (nerfstudio-data --downscale-factor ...)"),
    (["--pipeline.model.use-average-appearance-embedding", "False"], None,
     "--pipeline.model.use-average-appearance-embedding is the base's: an edit keeps its base's model settings "
     "(train the base with it instead)"),
    (["--pipeline.model.base-kept", "x"], None, "--pipeline.model.base-kept is not an option: the edit sets it itself"),
    # A flag whose value was left out took the next subcommand: what follows it is unrecognised for that alone.
    (["--max-num-iterations", REFERENCE, "--pipeline.model.guidance.target", "vase"],
     ["--pipeline.model.guidance.target", "vase"],
     f"--max-num-iterations needs a value; it was followed by {REFERENCE}, which it took as its value"),
    (["--prompt=a", REFERENCE, "--pipeline.model.guidance.target", "vase"], ["--pipeline.model.guidance.target", "vase"],
     f"--pipeline.model.guidance.target at that place: it goes right after {REFERENCE}, before the dataparser's name"),
    (["--promt", "x", "--max-num-iteration", "3"], None,
     "unrecognized options --promt --max-num-iteration (did you mean --prompt or --max-num-iterations?)"),
])
def test_an_unrecognized_word_says_what_it_was_and_what_to_type(line, words, tokens, said):
    assert _unrecognized(line, tokens or words, words) == said


@dataclasses.dataclass
class Small:
    """Each kind of value a flag of `ns-train sked` takes, parsed by tyro as nerfstudio's `ns-train` has it."""

    steps: int = 1
    device: Literal["cpu", "cuda", "mps"] = "cpu"
    sampling: Literal["as-rendered", "pixel-centre"] = "as-rendered"
    compile: bool = True
    azimuth: Tuple[float, float] = (0.0, 360.0)


class _Stop(Exception):
    pass


@dataclasses.dataclass
class WithFixed:
    kept: tyro.conf.Fixed[int] = 3


def _event(words, config=tyro.conf.FlagConversionOff[Small]):
    """The event tyro fires for `words` (given after `ns-train sked`) on `Small`'s flags."""

    def stop(event):
        raise _Stop(event)

    with pytest.raises(_Stop) as stopped, tyro_errors.on_parse_error(stop):
        tyro.cli(config, args=list(words))
    return stopped.value.args[0]


@pytest.mark.parametrize("words, said", [
    # A flag whose value was left out swallows the next word, or is followed by a flag or nothing.
    (["--steps", REFERENCE], f"--steps needs a value (an integer); it was followed by {REFERENCE}"),
    (["--steps", "nerfstudio-data"], "--steps needs a value (an integer); it was followed by nerfstudio-data"),
    (["--steps=", "--device", "cpu"], "--steps needs a value (an integer); none was given"),
    (["--steps", "--device", "cpu"], "--steps needs a value (an integer); it was followed by --device"),
    (["--device", "--steps", "3"], "--device needs a value (one of cpu, cuda, mps); it was followed by --steps"),
    (["--compile", REFERENCE], f"--compile needs a value (True or False); it was followed by {REFERENCE}"),
    (["--steps"], "--steps needs a value (an integer); none was given"),
    (["--azimuth", "10"], "--azimuth needs 2 values (2 numbers); it was given only 10"),
    (["--azimuth", "10", "--steps", "3"], "--azimuth needs 2 values (2 numbers); it was given only 10, then --steps"),
    # A value the flag does not read: what it takes, and the choice it likely meant.
    (["--steps", "3.5"], "--steps takes an integer, not '3.5'"),
    (["--azimuth", "10", "east"], "--azimuth takes 2 numbers, not '10 east'"),
    (["--compile", "maybe"], "--compile takes True or False, not 'maybe'"),
    (["--compile", "true"], "--compile takes True or False, not 'true' (did you mean True?)"),
    (["--device", "cdua"], "--device takes one of cpu, cuda, mps, not 'cdua' (did you mean cuda?)"),
    (["--device", "tpu"], "--device takes one of cpu, cuda, mps, not 'tpu'"),
    (["--sampling", "centre"], "--sampling takes one of as-rendered, pixel-centre, not 'centre' "
                               "(did you mean pixel-centre?)"),
])
def test_a_bad_value_says_what_the_flag_takes_and_what_followed_it(line, words, said):
    assert describe(_event(words), line, words) == said


def test_a_value_for_a_fixed_flag_is_named():
    assert describe(_event(["--kept", "5"], WithFixed)) == "--kept is fixed and takes no value: leave out '5' after it"


def _ns_train(*argv, **env):
    program = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    return subprocess.run([program, *argv], capture_output=True, text=True, timeout=300, env={**os.environ, **env})


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
    assert "--machine.device-type takes one of cpu, cuda, mps, not 'tpu'" in result.stderr
    stock = _ns_train("nerfacto", "--max-num-iteration", "3")  # the plugin changes nothing outside SKED
    assert stock.returncode == 2 and "error: ns-train" not in stock.stderr
    assert "Unrecognized options" in stock.stderr and "╭" in stock.stderr


@pytest.mark.slow
@pytest.mark.parametrize("argv, said", [
    (["--max-num-iterations", REFERENCE, "--pipeline.model.guidance.target", "vase"],
     f"--max-num-iterations needs a value; it was followed by {REFERENCE}, which it took as its value"),
    (["--max-num-iterations", REFERENCE], f"--max-num-iterations needs a value (an integer); it was followed by {REFERENCE}"),
    (["pipeline.model.guidance:refrence"], f"did you mean {REFERENCE}?"),
    (["\u2014prompt", "a hat"], "type --prompt (two ASCII hyphens)"),
    ([REFERENCE, "--pipeline.model.guidance.guidance-scale", "5"],
     f"the guidance {REFERENCE} has no setting --pipeline.model.guidance.guidance-scale"),
    ([REFERENCE, "nerfstudio-dat", "--data", "D"], "unknown subcommand nerfstudio-dat (did you mean nerfstudio-data?)"),
])
def test_ns_train_sked_says_what_was_typed_wrong_and_what_to_type(argv, said):
    result = _ns_train("sked", *argv)
    assert result.returncode == 2
    assert len(_own_lines(result.stderr)) == 1 and said in result.stderr, result.stderr


@pytest.mark.slow
def test_the_flags_read_from_the_config_are_those_ns_train_sked_lists(line):
    listed = _ns_train("sked", "--help", COLUMNS="400")
    assert listed.returncode == 0, listed.stderr
    shown = {flag.rstrip(".") for flag in re.findall(r"(?<![\w.-])--[a-z][\w.-]*", listed.stdout)} - {"--help"}
    assert shown == {flag for flag in line.flags if " " not in flag}


def test_a_word_near_a_sked_method_alone_is_taken_for_it():
    methods = list(SESSION_METHODS)
    assert misspelt_sked_method(["/x/bin/ns-train", "skd"], methods) == "sked"
    assert misspelt_sked_method(["/x/bin/ns-train", "sked-fst", "--load-dir", "x"], methods) == "sked-fast"
    assert misspelt_sked_method(["/x/bin/ns-train", "SKED"], methods) == "sked"
    for argv in (["/x/bin/ns-train", "sked"], ["/x/bin/ns-train", "nerfacto"], ["/x/bin/ns-train", "nesu"],
                 ["/x/bin/ns-train", "--help"], ["/x/bin/ns-render", "skd"], ["/x/bin/ns-train"]):
        assert misspelt_sked_method(argv, methods) is None, argv


def test_an_unknown_method_near_a_sked_one_is_one_line_and_every_other_report_is_tyros(capsys):
    methods = list(SESSION_METHODS)
    with pytest.raises(SystemExit) as stopped:
        parse_errors.unknown_method_hook("skd", methods)(
            tyro_errors.UnrecognizedArgs(prog="ns-train", tokens=["skd", "--load-dir", "x"]))
    assert stopped.value.code == 2
    assert capsys.readouterr().err == ("error: ns-train: no method skd (did you mean ns-train sked? SKED's methods are "
                                       "sked, sked-fast, sked-quality; see ns-train --help for all).\n")
    # A registered method's own errors, a misspelling nearer a stock method, another event: tyro's box, as stock.
    for word, event in [("sked", tyro_errors.UnrecognizedArgs(prog="ns-train", tokens=["sked", "--x"])),
                        ("neus-fact", tyro_errors.UnrecognizedArgs(prog="ns-train", tokens=["neus-fact"])),
                        ("skd", tyro_errors.UnrecognizedArgs(prog="ns-train", tokens=["--max-num-iteration"])),
                        ("skd", tyro_errors.MissingArgs(prog="ns-train", missing_arguments=[], unrecognized_tokens=[],
                                                        partial_output={}))]:
        assert parse_errors.unknown_method_hook(word, methods)(event) is None, word
    assert capsys.readouterr().err == ""


@pytest.mark.slow
def test_ns_train_of_a_misspelt_sked_method_says_the_method_meant_and_stock_misspellings_keep_tyros_box():
    result = _ns_train("skd", "--load-dir", "x")
    assert result.returncode == 2
    assert _own_lines(result.stderr) == ["error: ns-train: no method skd (did you mean ns-train sked? SKED's methods "
                                         "are sked, sked-fast, sked-quality; see ns-train --help for all)."], result.stderr
    stock = _ns_train("nerfactoo")
    assert stock.returncode == 2 and "error: ns-train" not in stock.stderr and "╭" in stock.stderr


@pytest.mark.parametrize("method, one_line", [("sked", True), ("sked-fast", True), ("nerfacto", False)])
def test_ns_train_sked_says_each_of_its_warnings_in_one_line_and_other_methods_keep_pythons(method, one_line):
    script = ("import sys, warnings; sys.argv = ['ns-train', %r]; import sked_ns.session.methods; "
              "from sked_ns.errors import SkedOptionWarning; from sked_ns.method.options import SkedSettingsWarning; "
              "from sked_ns.method.photo_anchor import SkedPhotoWarning; "
              "[warnings.warn('said ' + c.__name__, c) for c in (SkedOptionWarning, SkedSettingsWarning, SkedPhotoWarning)]")
    result = subprocess.run([sys.executable, "-c", script % method], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    said = [line for line in result.stderr.splitlines() if "said Sked" in line]
    if one_line:
        assert said == [f"warning: said {name}" for name in ("SkedOptionWarning", "SkedSettingsWarning", "SkedPhotoWarning")]
    else:
        assert len(said) == 3 and all("Warning: said" in line and not line.startswith("warning:") for line in said), said
