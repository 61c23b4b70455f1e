"""An edit stopped from outside: Ctrl-C at any stage is one line and status 130, with a resumable state; a full disk
is found before training, and a save cut short leaves no partial checkpoint behind."""

from __future__ import annotations

import errno
import os
import shlex
from pathlib import Path

import pytest
import torch

from sked_ns.engine import edit_inputs
from sked_ns.engine.base_scene import checkpoint_step, resolve_base
from sked_ns.engine.edit_run import edit_config
from sked_ns.engine.trainer import INTERRUPTED_STATUS, SkedTrainer, resolve_edit
from sked_ns.errors import SkedUserError
from sked_ns.run_lock import release


def _config(scene, output: Path, **settings):
    settings = {"iterations": 30, "steps_per_save": 10, "guidance_resolution": 16, "silhouette_resolution": 16,
                **settings}
    config = edit_config(scene["base"], scene["data"], scene["sketches"], output, **settings)
    config.set_timestamp()
    return config


def _ns_train(config) -> None:
    """What ns-train does after parsing: save the config, then nerfstudio's launch of its train loop."""
    from nerfstudio.scripts.train import launch, train_loop

    try:
        config.save_config()
        launch(main_func=train_loop, num_devices_per_machine=1, device_type="cpu", config=config)
    finally:
        release(config.get_base_dir())


def _interrupt_at(monkeypatch, at: int) -> None:
    iteration = SkedTrainer.train_iteration

    def interrupted(self, step):
        if step == at:
            raise KeyboardInterrupt
        return iteration(self, step)

    monkeypatch.setattr(SkedTrainer, "train_iteration", interrupted)


def test_ctrl_c_while_training_is_one_line_status_130_and_resumes_from_the_last_checkpoint(scene, tmp_path,
                                                                                          monkeypatch, capsys):
    config = _config(scene, tmp_path / "out")
    _interrupt_at(monkeypatch, 14)
    with pytest.raises(SystemExit) as stopped:
        _ns_train(config)
    assert stopped.value.code == INTERRUPTED_STATUS
    captured = capsys.readouterr()
    run = config.get_base_dir()
    assert "Traceback" not in captured.out + captured.err and "KeyboardInterrupt" not in captured.out + captured.err
    assert captured.err.splitlines()[-1] == (f"interrupted at step 14; its last checkpoint is step 10: resume with "
                                             f"ns-train sked --load-dir {shlex.quote(str(run))}")
    assert checkpoint_step(resolve_base(run).checkpoint) == 10  # what that command resumes from


def test_ctrl_c_before_the_first_checkpoint_names_the_command_that_starts_the_edit_again(scene, tmp_path,
                                                                                         monkeypatch, capsys):
    config = _config(scene, tmp_path / "out", prompt="a red hat; rm -rf ~")
    _interrupt_at(monkeypatch, 3)
    with pytest.raises(SystemExit) as stopped:
        _ns_train(config)
    assert stopped.value.code == INTERRUPTED_STATUS
    printed = capsys.readouterr().err.splitlines()[-1]
    run = config.get_base_dir()
    assert "interrupted at step 3, before the edit's first checkpoint: nothing to resume" in printed
    # Resuming it says the same, naming its saved sketch set; the command is quoted, so a shell runs it as one.
    with pytest.raises(SkedUserError, match=r"stopped before its first checkpoint.*sketch set is saved in") as refused:
        resolve_base(run)
    restart = lambda text: text.split("Start it again with ", 1)[1].rsplit(" (its other settings", 1)[0]  # noqa: E731
    words = shlex.split(restart(str(refused.value)))
    assert words[:4] == ["ns-train", "sked", "--load-dir", str(scene["base"])]
    assert words[words.index("--sketches") + 1] == str(run / "sketches")  # the run's own copy of the sketch set
    assert words[words.index("--prompt") + 1] == "a red hat; rm -rf ~"
    assert words[-3:] == ["nerfstudio-data", "--data", str(scene["data"])]
    assert shlex.split(restart(printed)) == words


@pytest.mark.parametrize("failure", [KeyboardInterrupt, OSError(errno.ENOSPC, "No space left on device")])
def test_a_save_cut_short_leaves_no_partial_checkpoint(scene, tmp_path, monkeypatch, failure):
    import nerfstudio.engine.trainer as nerfstudio_trainer

    config = _config(scene, tmp_path / "out", iterations=12)
    save = torch.save

    def cut_short(state, path, *args, **kwargs):
        if isinstance(path, (str, os.PathLike)) and Path(path).name == "step-000000010.ckpt":
            Path(path).write_bytes(b"PK\x03\x04 half a checkpoint")
            raise failure
        return save(state, path, *args, **kwargs)

    monkeypatch.setattr(nerfstudio_trainer.torch, "save", cut_short)
    with pytest.raises(SystemExit if failure is KeyboardInterrupt else SkedUserError) as stopped:
        _ns_train(config)
    if failure is KeyboardInterrupt:
        assert stopped.value.code == INTERRUPTED_STATUS
    else:
        assert "cannot write the checkpoint" in str(stopped.value) and "free space" in str(stopped.value)
    run = config.get_base_dir()
    assert not (run / ".nerfstudio_models.partial").exists()
    assert not list(run.rglob("step-000000010.ckpt"))


def test_too_little_disk_for_a_checkpoint_is_refused_before_anything_is_written(scene, tmp_path, monkeypatch):
    import collections
    import shutil

    size = resolve_base(scene["base"]).checkpoint.stat().st_size
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 * size, 9 * size, size))
    config = _config(scene, tmp_path / "out")
    with pytest.raises(SkedUserError, match=r"--output-dir .*GB free where the checkpoints go .*the edit needs about"):
        resolve_edit(config)
    assert not (tmp_path / "out").exists()
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(100 * size, 90 * size, 4 * size))
    config = _config(scene, tmp_path / "out")
    config.save_only_latest_checkpoint = False  # 4 checkpoints kept: more than the disk holds
    with pytest.warns(UserWarning, match=r"the edit's 4 checkpoints need about .* the later saves will fail"):
        resolve_edit(config)
    assert edit_inputs.CHECKPOINT_MARGIN >= 1
