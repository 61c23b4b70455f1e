"""nerfstudio's training iteration under SKED's step guard, over many steps: a run of skipped updates stops the
edit with one error naming what is likely wrong, a run that skipped every step ends as an error without a checkpoint,
one that skipped some says their share, and the first step says it is running."""

from __future__ import annotations

import types

import pytest
import torch
from nerfstudio.engine.trainer import writer  # nerfstudio.utils.writer, imported after its configs
from test_nerfstudio_glue import toy_trainer

from sked_ns.engine.trainer import MAX_SKIPPED_IN_A_ROW, SkedTrainer
from sked_ns.errors import SkedUserError, excepthook


def test_a_run_of_skipped_updates_stops_the_edit_naming_the_likely_causes(tmp_path, capsys):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum() * float("nan"))
    for step in range(MAX_SKIPPED_IN_A_ROW - 1):
        trainer.train_iteration(step)  # a scale being found, or a rare bad view: the edit goes on
    with pytest.raises(SkedUserError) as stopped:
        trainer.train_iteration(MAX_SKIPPED_IN_A_ROW - 1)
    message = str(stopped.value)
    assert f"steps 0-{MAX_SKIPPED_IN_A_ROW - 1}: every update skipped for a non-finite toy_loss" in message
    assert all(cause in message for cause in ("--load-dir", "learning rate", "--pipeline.model.lambda-"))
    assert torch.equal(trainer.pipeline.model.weight.detach(), torch.tensor([1.0, 2.0]))
    capsys.readouterr()
    excepthook(type(stopped.value), stopped.value, None)  # as `ns-train sked` prints it: one line, no traceback
    assert capsys.readouterr().err.count("\n") == 1


def test_a_finite_step_between_skips_starts_the_count_again(tmp_path):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum() * float("nan"))
    for step in range(MAX_SKIPPED_IN_A_ROW - 1):
        trainer.train_iteration(step)
    trainer.pipeline.loss = lambda w: (w**2).sum()
    trainer.train_iteration(MAX_SKIPPED_IN_A_ROW - 1)
    trainer.pipeline.loss = lambda w: (w**2).sum() * float("nan")
    for step in range(MAX_SKIPPED_IN_A_ROW, 2 * MAX_SKIPPED_IN_A_ROW - 1):
        trainer.train_iteration(step)
    assert trainer.skipped_steps == 2 * MAX_SKIPPED_IN_A_ROW - 2 and trainer.skipped_in_a_row == MAX_SKIPPED_IN_A_ROW - 1


def test_the_first_step_says_it_is_running_and_the_next_ones_do_not(tmp_path, capsys):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum())
    trainer.train_iteration(0)
    said = capsys.readouterr().err
    assert "ns-train sked: running the edit's first step..." in said and "done running the edit's first step" in said
    trainer.train_iteration(1)
    assert "first step" not in capsys.readouterr().err
    resumed = toy_trainer(tmp_path, lambda w: (w**2).sum())
    resumed.train_iteration(500)
    assert "running step 500, the first since the resume" in capsys.readouterr().err


def _training(tmp_path, loss, iterations: int, start: int = 0):
    """A toy trainer that runs nerfstudio's own training loop (train, _after_train) for `iterations` steps."""
    trainer = toy_trainer(tmp_path, loss, max_num_iterations=iterations, vis="tensorboard")
    trainer.config.logging.local_writer.enable = False
    writer.setup_local_writer(trainer.config.logging, max_iter=iterations)  # the loop's timings go to its buffer
    trainer.pipeline.datamanager = types.SimpleNamespace(train_dataset=[None], eval_dataset=None,
                                                         get_train_rays_per_batch=lambda: 1)
    trainer.callbacks, trainer._start_step, trainer._stepped = [], start, True
    trainer.config.max_num_iterations = start + iterations  # an edit's length is its total (SkedTrainer.train)
    return trainer


def _nan_at(steps):
    return lambda w: (w**2).sum() * (float("nan") if _nan_at.step in steps else 1.0)


@pytest.fixture(autouse=True)
def _count_steps(monkeypatch):
    """_nan_at's step: the step nerfstudio's loop runs; nerfstudio's writer buffer as it was after each test."""
    monkeypatch.setattr(writer, "GLOBAL_BUFFER", {})
    original = SkedTrainer.train_iteration

    def counted(trainer, step):
        _nan_at.step = step
        return original(trainer, step)

    monkeypatch.setattr(SkedTrainer, "train_iteration", counted)


def test_a_run_that_skipped_every_step_ends_as_an_error_and_saves_nothing(tmp_path, capsys):
    trainer = _training(tmp_path, lambda w: (w**2).sum() * float("nan"), iterations=3)
    with pytest.raises(SkedUserError) as stopped:
        trainer.train()
    message = str(stopped.value)
    assert message.startswith("3 of 3 steps skipped for a non-finite toy_loss, so the edit is its base: nothing saved")
    assert all(cause in message for cause in ("--load-dir", "learning rate", "--pipeline.model.guidance.weight"))
    assert not list(tmp_path.rglob("*.ckpt")), "no checkpoint holding the base as if it were the edit"
    assert "Training Finished" not in capsys.readouterr().out
    excepthook(type(stopped.value), stopped.value, None)  # as `ns-train sked` prints it: one line, then status 1
    assert capsys.readouterr().err.count("\n") == 1


def test_a_resumed_run_that_skipped_every_step_says_the_edit_is_as_its_checkpoint(tmp_path):
    trainer = _training(tmp_path, lambda w: (w**2).sum() * float("nan"), iterations=2, start=500)
    with pytest.raises(SkedUserError, match="2 of 2 steps skipped for a non-finite toy_loss, so the edit is as its "
                                            "checkpoint of step 499: nothing saved"):
        trainer.train()
    assert not list(tmp_path.rglob("*.ckpt"))


def test_a_run_that_skipped_some_steps_says_their_share_once_at_its_end(tmp_path, capsys):
    trainer = _training(tmp_path, _nan_at({0, 2}), iterations=5)
    trainer.train()
    said = capsys.readouterr().out
    assert said.count("2 of 5 steps (40.0%) skipped for a non-finite toy_loss: their updates were not applied") == 1
    assert said.index("40.0%") < said.index("Training Finished")
    assert [path.name for path in tmp_path.rglob("*.ckpt")] == ["step-000000004.ckpt"]


def test_a_clean_run_says_nothing_of_skips(tmp_path, capsys):
    _training(tmp_path, lambda w: (w**2).sum(), iterations=2).train()
    said = capsys.readouterr().out
    assert "steps skipped" not in said and "update skipped" not in said and "Training Finished" in said


def test_no_checkpoint_is_saved_while_every_step_so_far_was_skipped(tmp_path):
    trainer = _training(tmp_path, _nan_at({0, 1}), iterations=4)
    trainer.config.steps_per_save, trainer.config.save_only_latest_checkpoint = 1, False  # a save after each step
    trainer.train()
    assert sorted(path.name for path in tmp_path.rglob("*.ckpt")) == ["step-000000002.ckpt", "step-000000003.ckpt"]
