"""A user error in an `ns-*` command prints its message alone; the traceback only on request."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sked_ns import errors
from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.guidance.hub import hub_cli


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
    assert "TrainerConfig" not in result.stdout, "the error comes before nerfstudio's config dump"
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


def test_ctrl_c_in_a_sked_command_is_one_line_with_status_130_and_elsewhere_untouched(tmp_path):
    import subprocess

    script = tmp_path / "sked-eval"  # a command named as the installed ones are
    script.write_text("import time, sked_ns\nraise KeyboardInterrupt\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert result.stderr == "interrupted: sked-eval stopped by Ctrl-C; what it had written whole is kept.\n"
    assert result.returncode == -2  # killed by SIGINT, as a shell reports with status 130
    other = tmp_path / "ns-render"
    other.write_text(script.read_text())
    result = subprocess.run([sys.executable, str(other)], capture_output=True, text=True, timeout=300)
    assert "Traceback" in result.stderr and "interrupted:" not in result.stderr  # not SKED's: not ours to change


def test_the_plugin_installs_the_hook_once():
    import sked_ns  # noqa: F401  (every ns-* command imports it through the method registry)

    assert sys.excepthook is errors.excepthook
    errors.install_excepthook()
    assert errors._previous_excepthook is not errors.excepthook  # no loop to itself


# ---- every input of `ns-train sked` and the sked-* commands: one `error:` line, before anything is written ----
def _command(name: str) -> str:
    return shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)


def _run(*argv, env=None) -> subprocess.CompletedProcess:
    environment = None if env is None else {**os.environ, **env}
    return subprocess.run([_command(argv[0]), *argv[1:]], capture_output=True, text=True, timeout=600,
                          env=environment)


def assert_refused(result: subprocess.CompletedProcess, untouched: Path, *named: str) -> None:
    """Exit status != 0, exactly one `error:` line naming what the user typed, no traceback, nothing written."""
    report = result.stderr[-3000:]
    assert result.returncode != 0, report
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and all(name in errors[0] for name in named), report
    assert "Traceback" not in result.stderr + result.stdout, report
    assert not untouched.exists(), f"{untouched} was written"


def sked_edit(scene, out: Path, sketches: Path, *flags: str) -> list:
    """`ns-train sked` on the scene's base, its data after every other flag."""
    return ["ns-train", "sked", "--load-dir", str(scene["base"]), "--sketches", str(sketches), "--output-dir",
            str(out), "--machine.device-type", "cpu", "--vis", "tensorboard", "--max-num-iterations", "2", *flags,
            "nerfstudio-data", "--data", str(scene["data"])]


def broken_copy(sketches: Path, folder: Path, breakage: str) -> Path:
    """A copy of a sketch set with one thing wrong in it."""
    shutil.copytree(sketches, folder)
    meta = json.loads((folder / "sketches.json").read_text())
    view = meta["views"][1]
    if breakage == "nan pose":
        view["transform_matrix"][0][0] = float("nan")
    elif breakage == "singular pose":
        view["transform_matrix"] = [[0.0] * 3 + [row[3]] for row in view["transform_matrix"][:3]] + [[0, 0, 0, 1]]
    elif breakage == "missing intrinsics":
        del view["fl_x"]
    elif breakage == "mask of another size":
        view["w"] += 8
    elif breakage == "empty mask":
        cv2.imwrite(str(folder / view["mask_path"]), np.zeros((view["h"], view["w"]), np.uint8))
    elif breakage == "frame":
        meta["frame"] = "model"  # poses copied from transforms.json, declared in nerfstudio's frame
    (folder / "sketches.json").write_text(json.dumps(meta))
    return folder


def test_an_empty_prompt_alias_is_refused_before_anything_is_written(scene, tmp_path):
    # nerfstudio passes `--prompt` on only when it is not empty: "" would silently carve.
    result = _run(*sked_edit(scene, tmp_path / "out", scene["sketches"], "--prompt", ""))
    assert_refused(result, tmp_path / "out", "--prompt '' is empty")


def test_a_broken_sketch_set_is_one_line_before_anything_is_written(scene, tmp_path):
    sketches = broken_copy(scene["sketches"], tmp_path / "sketches", "nan pose")
    result = _run(*sked_edit(scene, tmp_path / "out", sketches, "pipeline.model.guidance:reference"))
    assert_refused(result, tmp_path / "out", str(sketches / "sketches.json"), "transform_matrix", "NaN")


def test_missing_diffusion_weights_are_refused_before_anything_is_written(scene, tmp_path):
    result = _run(*sked_edit(scene, tmp_path / "out", scene["sketches"], "--prompt", "a hat"),
                  env={"HF_HOME": str(tmp_path / "empty-cache"), "HF_HUB_OFFLINE": "1"})
    assert_refused(result, tmp_path / "out", "--pipeline.model.guidance.model CompVis/stable-diffusion-v1-4",
                   f"{hub_cli()} download CompVis/stable-diffusion-v1-4")


def _save_config(config) -> None:
    config.set_timestamp()
    config.save_config()


@pytest.mark.parametrize("breakage, message", [
    ("nan pose", r"views\[1\] 'transform_matrix': .*NaN"),
    ("singular pose", r"views\[1\] 'transform_matrix': the rotation part is not a proper rotation"),
    ("missing intrinsics", r"views\[1\]: missing field 'fl_x'"),
    ("mask of another size", r"view_01.png: mask is 64x64 but its camera says w=72"),
    ("empty mask", r"view_01.png: the mask is empty"),
    ("frame", r"sketches.json: \"frame\": \"model\", but .* read as \"data\""),
])
def test_every_sketch_set_problem_is_refused_before_anything_is_written(scene, tmp_path, breakage, message):
    from sked_ns.engine.edit_run import edit_config

    sketches = broken_copy(scene["sketches"], tmp_path / "sketches", breakage)
    config = edit_config(scene["base"], scene["data"], sketches, tmp_path / "out")
    with pytest.raises(SkedUserError, match=message):
        _save_config(config)
    assert not (tmp_path / "out").exists()


def test_an_incomplete_diffusion_checkpoint_is_refused_before_anything_is_written(scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config

    folder = tmp_path / "sd"
    for part, files in {"scheduler": ["scheduler_config.json"], "tokenizer": ["vocab.json", "merges.txt"],
                        "text_encoder": ["config.json", "model.safetensors"], "unet": ["config.json"],
                        "vae": ["config.json", "diffusion_pytorch_model.safetensors"]}.items():
        (folder / part).mkdir(parents=True)
        for name in files:
            (folder / part / name).write_text("{}")
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path / "out", prompt="a hat",
                         guidance="stable-diffusion")
    config.pipeline.model.guidance.model = str(folder)
    with pytest.raises(SkedUserError, match=rf"--pipeline.model.guidance.model {folder}: no unet/diffusion_pytorch"):
        _save_config(config)
    assert not (tmp_path / "out").exists()


def test_data_the_dataparser_cannot_read_is_refused_before_anything_is_written(scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config

    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    (data / "transforms.json").unlink()
    config = edit_config(scene["base"], data, scene["sketches"], tmp_path / "out")
    with pytest.raises(SkedUserError, match=rf"--data {data}: cannot read it \(FileNotFoundError"):
        _save_config(config)
    shutil.copy(scene["data"] / "transforms.json", data / "transforms.json")
    photo = sorted((data / "images").iterdir())[3]
    photo.unlink()
    with pytest.raises(SkedFileNotFoundError, match=rf"--data {data}: 1 of its \d+ training photos are missing: "
                                                    rf"{photo}"):
        _save_config(config)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, named", [
    (["sked-sketch", "check", "{sketches}"], ["sketches.json views[1] 'transform_matrix'", "NaN"]),
    (["sked-sketch", "check"], ["sked-sketch check: the following arguments are required: folder"]),
    (["sked-import-authors", "{tmp}", "{untouched}"], ["meta_data.pkl: missing"]),
    (["sked-demo", "--output", "{untouched}", "--beta", "-1"], ["--beta -1.0"]),
    (["sked-demo", "--output", "{untouched}", "--size", "big"], ["argument --size: invalid int value: 'big'"]),
    (["sked-demo", "--output", "{untouched}", "--prompt", " "], ["--prompt ' ' is empty"]),
])
def test_every_sked_command_says_a_user_error_in_one_line_before_writing(scene, tmp_path, argv, named):
    sketches = broken_copy(scene["sketches"], tmp_path / "sketches", "nan pose")
    values = {"sketches": sketches, "tmp": tmp_path, "untouched": tmp_path / "untouched"}
    result = _run(*[part.format(**values) for part in argv])
    assert_refused(result, tmp_path / "untouched", *named)


def test_a_message_of_several_lines_prints_as_one(monkeypatch, capsys):
    monkeypatch.delenv(errors.TRACEBACK_ENV, raising=False)
    errors.excepthook(SkedUserError, SkedUserError("Bad settings:\n  --a 1: no.\n  --b 2: no."), None)
    assert capsys.readouterr().err == "error: Bad settings: --a 1: no. --b 2: no.\n"


def test_a_library_failure_reading_a_users_file_is_a_user_error(tmp_path):
    with pytest.raises(SkedUserError, match=r"--data x: cannot read it \(KeyError: 'frames'\)\. Check it\."):
        with errors.reading("--data x", "Check it."):
            {}["frames"]
    with pytest.raises(ZeroDivisionError):  # not a reading failure: a bug keeps its traceback
        with errors.reading("--data x", "Check it."):
            1 / 0


SKED_COMMANDS = ["sked-eval", "sked-sketch", "sked-batch", "sked-demo", "sked-import-authors"]


@pytest.mark.parametrize("command", SKED_COMMANDS)
def test_sked_commands_print_help_without_warnings_and_with_every_flag_explained(command):
    program = shutil.which(command, path=str(Path(sys.executable).parent))
    result = subprocess.run([program, "--help"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.startswith("usage: "), result.stderr[-2000:]
    assert "Warning" not in result.stderr, result.stderr[-2000:]
    lines = result.stdout.splitlines()
    options = [i for i, line in enumerate(lines) if re.match(r"^  -", line)]
    unexplained = [lines[i].strip() for i in options
                   if not re.search(r"\S\s{2,}\S", lines[i].strip()) and not (i + 1 < len(lines) and
                                                                        lines[i + 1].startswith(" " * 8))]
    assert unexplained == []


def test_sked_sketch_usage_names_its_subcommands():
    program = shutil.which("sked-sketch", path=str(Path(sys.executable).parent))
    usage = subprocess.run([program, "--help"], capture_output=True, text=True, timeout=300).stdout.split("\n\n")[0]
    assert all(f"sked-sketch {sub}" in usage for sub in ("canvases", "import", "check"))


def test_each_option_s_help_names_its_default_once():
    from sked_ns.demo.cli import demo_parser
    from sked_ns.evaluation.eval_args import eval_parser

    for parser in (eval_parser(), demo_parser()):
        text = " ".join(parser.format_help().split())
        assert "(default: None)" not in text, parser.prog
        for option in text.split(" --")[1:]:
            assert option.count("default") <= 1, f"{parser.prog} --{option}"
