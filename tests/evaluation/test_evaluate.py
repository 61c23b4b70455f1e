"""sked-eval's command line: where it writes, what it refuses, named as sked-eval takes it (no model needed)."""

from __future__ import annotations

import argparse
import json
import re
import sys

import numpy as np
import pytest
import torch

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.evaluation.eval_args import positive_int
from sked_ns.evaluation.eval_inputs import edit_run_folder, orbit_count, output_paths


def test_results_go_next_to_the_edit_and_never_replace_an_earlier_one(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    assert output_paths(run, None, None, overwrite=False) == (run / "sked_eval.json", run / "sked_eval.png")
    (run / "sked_eval.png").write_bytes(b"earlier")
    with pytest.raises(SkedUserError, match=r"sked_eval.png already exist.*--output.*--overwrite"):
        output_paths(run, None, None, overwrite=False)
    assert output_paths(run, None, None, overwrite=True)[1] == run / "sked_eval.png"
    mine = tmp_path / "mine.json"
    assert output_paths(run, mine, None, overwrite=False) == (mine, tmp_path / "mine.png")


def test_a_missing_config_is_named_as_sked_eval_takes_it(tmp_path):
    with pytest.raises(SkedFileNotFoundError, match=r"sked-eval .*absent/config.yml: no .*config.yml") as error:
        edit_run_folder(tmp_path / "absent" / "config.yml")
    assert "--load-dir" not in str(error.value)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yml").write_text("")
    assert edit_run_folder(tmp_path / "run") == edit_run_folder(tmp_path / "run" / "config.yml") == tmp_path / "run"


@pytest.mark.parametrize("text", ["0", "-3", "x"])
def test_sizes_and_counts_must_be_positive_whole_numbers(text):
    with pytest.raises(argparse.ArgumentTypeError):
        positive_int(text)
    with pytest.raises(SkedUserError, match=f"--cameras orbit:{text}: "):
        orbit_count(f"orbit:{text}")
    assert positive_int("3") == 3 and orbit_count("orbit") == 12 and orbit_count("orbit:5") == 5


def test_the_command_refuses_before_loading_anything(tmp_path, monkeypatch, capsys):
    from sked_ns.errors import SkedUserError
    from sked_ns.evaluation.eval_cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["sked-eval", str(tmp_path / "nowhere"), "--resolution", "0"])
    with pytest.raises(SkedUserError, match="sked-eval: argument --resolution: 0: must be at least 1"):
        entrypoint()
    monkeypatch.setattr(sys, "argv", ["sked-eval", str(tmp_path / "nowhere")])
    with pytest.raises(SkedFileNotFoundError, match="sked-eval .*nowhere"):
        entrypoint()


def test_an_output_folder_that_cannot_be_written_is_refused_before_evaluating(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(SkedUserError, match="--output"):
        output_paths(run, blocker / "metrics.json", None, overwrite=False)
    with pytest.raises(SkedUserError, match="--sheet"):
        output_paths(run, None, blocker / "sheet.png", overwrite=False)


def fake_run(tmp_path):
    """A folder sked-eval takes as an edited run: every check below must refuse before it is loaded."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("")
    return run


def sked_eval(monkeypatch, *argv):
    from sked_ns.evaluation.eval_cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["sked-eval", *map(str, argv)])
    entrypoint()


def test_a_target_is_read_up_front_and_never_ignored(tmp_path, monkeypatch):
    from sked_ns.evaluation.evaluate import evaluate

    run, fresh = fake_run(tmp_path), tmp_path / "fresh" / "metrics.json"
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    ply = tmp_path / "model.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\n\x00\xff\xfe")
    no_images = tmp_path / "transforms.json"
    no_images.write_text(json.dumps({"fl_x": 20, "w": 32, "h": 32, "frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    cases = [(["--cameras", "none", "--target", broken], r"--cameras none and --target \S+broken.json: the target is "
                                                         r"scored at its own cameras, which --cameras none turns off"),
             (["--cameras", "orbit", "--target", broken], r"--cameras orbit and --target"),
             (["--target", broken], r"--target \S+broken.json: not readable as JSON"),
             (["--target", ply], r"--target \S+model.ply: not readable as JSON"),
             (["--target", no_images], r"--target \S+transforms.json: frame 0 has no 'file_path'; a target's frames")]
    for flags, message in cases:
        with pytest.raises(SkedUserError, match=message):
            sked_eval(monkeypatch, run, "--output", fresh, *flags)
    with pytest.raises(SkedUserError, match=r"--cameras none and --target"):
        evaluate(run, cameras="none", target=broken)
    assert not fresh.parent.exists() and sorted(p.name for p in run.iterdir()) == ["config.yml"], "nothing written"


def test_every_flag_is_checked_before_the_edit_loads(tmp_path, monkeypatch):
    from sked_ns.errors import SkedWarning

    run, fresh = fake_run(tmp_path), tmp_path / "fresh" / "metrics.json"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cases = [(["--sketches", tmp_path / "nowhere"], r"--sketches \S+nowhere: .*no sketch set here"),
             (["--base", tmp_path / "nowhere"], r"--base \S+nowhere: no such run folder"),
             (["--cameras", "orbits"], r"--cameras orbits: no such camera file or folder"),
             (["--prompt", "  "], r"--prompt '  ': empty; leave it out"),
             (["--clip-model", tmp_path / "no-clip"], r"--clip-model \S+no-clip: no such folder"),
             (["--device", "cuda"], r"--device cuda: no CUDA GPU is visible here; pass --device cpu"),
             (["--device", "gpu0"], r"--device gpu0: not a device torch knows")]
    for flags, message in cases:
        with pytest.raises(SkedUserError, match=message):
            sked_eval(monkeypatch, run, "--output", fresh, *flags)
    with pytest.warns(SkedWarning, match=r"--cameras orbit:40: only 12 of the 40 orbit views are scored"), \
            pytest.raises(SkedUserError, match=r"run/nerfstudio_models: missing"):  # then the fake run is refused
        sked_eval(monkeypatch, run, "--output", fresh, "--cameras", "orbit:40")
    with pytest.warns(SkedWarning, match=r"--clip-views 4000: that many renders"), pytest.raises(SkedUserError):
        sked_eval(monkeypatch, run, "--output", fresh, "--clip-views", "4000")
    assert not fresh.parent.exists() and sorted(p.name for p in run.iterdir()) == ["config.yml"], "nothing written"


def test_overwrite_replaces_only_an_earlier_result_and_the_two_outputs_differ(tmp_path):
    run = fake_run(tmp_path)
    with pytest.raises(SkedUserError, match=r"--output \S+m.png and --sheet \S+m.png: the same file"):
        output_paths(run, tmp_path / "m.png", None, overwrite=False)
    with pytest.raises(SkedUserError, match=r"--sheet \S+sheet.txt: OpenCV writes no image with that ending"):
        output_paths(run, None, tmp_path / "sheet.txt", overwrite=False)
    with pytest.raises(SkedUserError, match=r"--output \S+: a folder"):
        output_paths(run, tmp_path, None, overwrite=False)
    with pytest.raises(SkedUserError, match=r"--output \S+config.yml: not an earlier sked-eval result"):
        output_paths(run, run / "config.yml", run / "sheet.png", overwrite=True)
    (run / "sked_eval.json").write_text(json.dumps({"edit_run": str(run)}))
    assert output_paths(run, None, None, overwrite=True)[0] == run / "sked_eval.json"


@pytest.fixture(scope="module")
def tiny_edit(scene, tmp_path_factory):
    """A two-step reference-guided edit of the demo base at 16 px (what sked-eval loads and renders)."""
    from sked_ns.engine.edit_run import edit_config, run_edit

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path_factory.mktemp("edit"), iterations=2,
                         guidance_resolution=16, silhouette_resolution=16, steps_per_save=100)
    return run_edit(config).base_dir


def test_another_base_prints_no_nan_and_says_why_its_region_ios_is_missing(scene, tiny_edit, tmp_path, monkeypatch,
                                                                           capsys):
    output = tmp_path / "metrics.json"
    sked_eval(monkeypatch, tiny_edit / "config.yml", "--base", scene["base"], "--output", output, "--resolution", 16,
              "--cameras", "none", "--clip-views", 1, "--clip-resolution", 16)
    printed = capsys.readouterr().out
    assert "nan" not in printed.lower(), printed
    assert re.search(r"region IoS \d\.\d{3} \(base n/a: --base's renders carry no preservation weight", printed), printed
    metrics = json.loads(output.read_text())
    assert "ios_region_base" not in metrics["mean"] and metrics["ios_region_base"].startswith("n/a: --base's renders")
    assert 0 <= metrics["mean"]["ios_region"] <= 1


def test_only_a_sked_edit_is_evaluated_and_not_against_itself(scene, tiny_edit):
    from sked_ns.evaluation.evaluate import evaluate

    with pytest.raises(SkedUserError, match=r"sked-eval \S+: a 'nerfacto' run, not a SKED edit"):
        evaluate(scene["base"], cameras="none")
    with pytest.raises(SkedUserError, match=r"--base \S+: that is the edit itself"):
        evaluate(tiny_edit, base_run=tiny_edit, cameras="none")


def test_the_edit_is_named_once_as_a_path_or_as_nerfstudio_s_load_config(tmp_path):
    from sked_ns.errors import SkedUserError
    from sked_ns.evaluation.eval_cli import parse

    run = tmp_path / "run" / "config.yml"
    assert parse([str(run), "--device", "cpu"]).config == run
    assert parse(["--load-config", str(run), "--device", "cpu"]).config == run
    for argv in ([], [str(run), "--load-config", str(run)]):
        with pytest.raises(SkedUserError, match="give the edited run once"):
            parse(argv)


def test_an_edit_still_training_is_scored_only_from_outside_its_run_folder_and_its_step_recorded(
        tiny_edit, tmp_path, monkeypatch, capsys):
    from lock_helpers import holding, killed

    from sked_ns.engine.base_scene import checkpoint_step, resolve_base

    step = checkpoint_step(resolve_base(tiny_edit).checkpoint)
    trainer = holding(tiny_edit)  # the edit's trainer, as ns-train holds its run folder
    try:
        with pytest.raises(SkedUserError, match=rf"the edit is still training \(pid {trainer.pid} .*one writer.*"
                                                rf"--output and --sheet outside the run folder.*step {step}\)"):
            sked_eval(monkeypatch, tiny_edit / "config.yml", "--resolution", 16, "--cameras", "none",
                      "--clip-views", 1, "--clip-resolution", 16)
        assert not (tiny_edit / "sked_eval.json").exists() and not (tiny_edit / "sked_eval.png").exists()
        output = tmp_path / "live.json"
        with pytest.warns(UserWarning, match=rf"still training \(pid {trainer.pid}.*latest checkpoint so far, step {step}"):
            sked_eval(monkeypatch, tiny_edit / "config.yml", "--output", output, "--resolution", 16, "--cameras",
                      "none", "--clip-views", 1, "--clip-resolution", 16)
    finally:
        killed(trainer)
    metrics = json.loads(output.read_text())
    assert metrics["step"] == step and metrics["checkpoint"].endswith(f"step-{step:09d}.ckpt")
    assert f"(the edit at step {step})" in capsys.readouterr().out


def test_the_estimate_counts_every_render_and_offers_quicker_resolutions_when_long():
    from sked_ns.evaluation.eval_cost import EvalWork, estimate_line

    work = EvalWork([(256, 192)] * 2, [(256, 256)] * 12, clip_views=40, clip_resolution=128, clip_base=True)
    assert work.pixels() == 2 * (2 * 256 * 192 + 12 * 256 * 256) + 2 * 40 * 128 ** 2  # base and edit each
    line = estimate_line(work, 1e-3, "cpu", 256, 256)
    assert line.startswith("sked-eval: about 51 min on cpu for 2 sketch views at 256 px and 12 novel views at 256 px")
    assert "--resolution 128 --novel-resolution 128 takes about 29 min" in line
    assert "--resolution" not in estimate_line(work, 1e-6, "cuda", 256, 256)  # a few seconds: nothing to offer
    assert "--resolution" not in estimate_line(work.scaled(128, 128, 256, 256), 1e-3, "cpu", 128, 128)


def test_the_first_line_says_how_long_the_evaluation_will_take(tiny_edit, tmp_path, monkeypatch, capsys):
    sked_eval(monkeypatch, tiny_edit / "config.yml", "--output", tmp_path / "m.json", "--resolution", 16,
              "--cameras", "orbit:2", "--novel-resolution", 16, "--clip-views", 1, "--clip-resolution", 16)
    said = capsys.readouterr().err.splitlines()
    first = next(index for index, line in enumerate(said) if line.startswith("sked-eval: "))
    assert re.match(r"sked-eval: about [\d.,]+ (s|min) on cpu for 2 sketch views at 16 px and 2 novel views at 16 px, each "
                    r"with the base and the edit", said[first]), said
    assert any(line.startswith("sked-eval: sketch view 1/2") for line in said[first + 1:])
