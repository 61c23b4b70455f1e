"""sked-demo run again in its folder picks up where it stopped: the fitted base reused, the edit continued."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sked_ns.demo import rerun as rerun_module
from sked_ns.demo.rerun import forget_base, record_base, reusable_base


def fake_base(output, kind="nerfacto"):
    run = output / "base" / "demo-base" / kind / "base"
    (run / "nerfstudio_models").mkdir(parents=True)
    (run / "config.yml").write_text("fake")
    (run / "dataparser_transforms.json").write_text("{}")
    (run / "nerfstudio_models" / "step-000000040.ckpt").write_bytes(b"weights" * 100)
    return run


def test_a_base_is_reused_only_with_its_settings_and_intact(tmp_path):
    run = fake_base(tmp_path)
    settings = {"base": "nerfacto", "fit": {"steps": 40}, "data": "d1"}
    record_base(tmp_path, "nerfacto", settings, run)
    assert reusable_base(tmp_path, "nerfacto", settings) == run
    assert reusable_base(tmp_path, "nerfacto", {**settings, "fit": {"steps": 41}}) is None
    assert reusable_base(tmp_path, "nerfacto", {**settings, "data": "d2"}) is None
    assert reusable_base(tmp_path, "splatfacto", settings) is None

    checkpoint = run / "nerfstudio_models" / "step-000000040.ckpt"
    checkpoint.write_bytes(b"weights" * 50)  # cut short
    assert reusable_base(tmp_path, "nerfacto", settings) is None
    checkpoint.write_bytes(b"weights" * 100)
    assert reusable_base(tmp_path, "nerfacto", settings) == run
    (run / "nerfstudio_models" / "step-000000600.ckpt").write_bytes(b"other")  # nerfstudio would load this one
    assert reusable_base(tmp_path, "nerfacto", settings) is None


def test_a_fit_cut_short_is_never_reused(tmp_path):
    run = fake_base(tmp_path)
    settings = {"base": "nerfacto", "fit": {"steps": 40}, "data": "d1"}
    record_base(tmp_path, "nerfacto", settings, run)
    forget_base(tmp_path, "nerfacto")  # a refit starts: the record and the old fit go first
    assert not (tmp_path / "base" / "demo-base").exists()
    fake_base(tmp_path)  # the new fit's files, stopped before its record
    assert reusable_base(tmp_path, "nerfacto", settings) is None


def edit_runs(output):
    return sorted(path.parent for path in (output / "edits").rglob("config.yml"))


@pytest.mark.slow
def test_a_demo_stopped_in_its_edit_continues_when_run_again(tmp_path, monkeypatch, capsys):
    """Ctrl-C mid-edit names the demo's own command; the rerun fits nothing and continues that edit's run from its
    last checkpoint, leaving one run; a third run takes the finished edit as it is."""
    from sked_ns.demo import cli
    from sked_ns.demo import run as demo_run

    output = tmp_path / "demo out"
    argv = ["--output", str(output), "--size", "24", "--iterations", "8", "--base-steps", "30", "--device", "cpu"]
    train_iteration = demo_run.DemoEditTrainer.train_iteration

    def stopped_at_5(self, step):
        if step == 5:
            raise KeyboardInterrupt
        return train_iteration(self, step)

    with monkeypatch.context() as patch:
        patch.setattr(demo_run.DemoEditTrainer, "train_iteration", stopped_at_5)
        with pytest.raises(SystemExit) as stop:
            cli.entrypoint(argv)
    assert stop.value.code == 130
    said = capsys.readouterr().err
    line = next(line for line in said.splitlines() if line.startswith("interrupted"))
    assert "ns-train" not in line
    assert "while editing" in line and "reuses the fitted base" in line
    assert "continues the edit from its checkpoint at step 4" in line  # saved every step at 8 iterations
    assert "sked-demo --output '" + str(output) + "'" in line
    [stopped] = edit_runs(output)

    def no_refit(*args, **kwargs):
        raise AssertionError("the base was fitted again")

    monkeypatch.setattr(demo_run, "fit_base", no_refit)
    summary = demo_run.run(output, size=24, iterations=8, base_steps=30)
    assert summary["edit"] == "continued from step 4"
    [finished] = edit_runs(output)  # the stopped run was continued, not left behind
    assert finished != stopped and str(finished) == summary["edit_run"]
    assert finished.parent == stopped.parent  # continued beside it
    from nerfstudio.utils import writer

    # nerfstudio's writers outlive their run: none may log into the removed run when this process edits again.
    assert all(Path(w.tb_writer.log_dir).exists() for w in writer.EVENT_WRITERS if hasattr(w, "tb_writer"))
    record = json.loads((output / "edits" / rerun_module.EDIT_RECORD).read_text())
    assert [entry["runs"] for entry in record["edits"]] == [[str(finished.relative_to(output / "edits"))]]

    monkeypatch.setattr(demo_run, "DemoEditTrainer", None)  # no edit may run
    again = demo_run.run(output, size=24, iterations=8, base_steps=30)
    assert again["edit"] == "taken as done" and again["edit_run"] == str(finished)
    assert again["views"] == summary["views"]


@pytest.mark.parametrize("text", ["", "{", "[]", '{"edits": 3}', '{"edits": [3, {"settings": 1, "runs": 5}]}'])
def test_a_damaged_edit_record_starts_a_new_edit(tmp_path, text):
    from sked_ns.demo.rerun import plan_edit, record_runs

    edits = tmp_path / "edits"
    edits.mkdir()
    (edits / rerun_module.EDIT_RECORD).write_text(text)
    settings = {"beta": 0.025}
    plan = plan_edit(edits, settings, 10)
    assert plan.run is None and plan.chain == []
    record_runs(edits, settings, [edits / "edit" / "sked" / "run"])
    assert plan_edit(edits, settings, 10).chain == []  # recorded, but never written: nothing to continue
    assert json.loads((edits / rerun_module.EDIT_RECORD).read_text())["edits"][-1]["runs"] == ["edit/sked/run"]


def test_a_demo_stopped_in_its_base_fit_says_running_it_again_fits_the_base_again(tmp_path, monkeypatch, capsys):
    from sked_ns.demo import cli
    from sked_ns.demo import run as demo_run

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(demo_run, "fit_base", stopped)
    with pytest.raises(SystemExit) as stop:
        cli.entrypoint(["--output", str(tmp_path / "demo"), "--device", "cpu"])
    assert stop.value.code == 130
    [line] = [line for line in capsys.readouterr().err.splitlines() if line.startswith("interrupted")]
    assert line == (f"interrupted: sked-demo stopped by Ctrl-C while fitting the nerfacto base; running it again fits "
                    f"the base again. Run the same command (sked-demo --output {tmp_path / 'demo'} --device cpu) to "
                    "pick up where it stopped.")
    assert reusable_base(tmp_path / "demo", "nerfacto", {}) is None
