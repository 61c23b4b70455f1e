"""Resuming continues the saved edit; checkpoints survive a kill; run settings are checked before anything runs.

Unit tests on configs and small files; the real resumed edit is in test_edit.py.
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig
from sked_ns.engine.base_scene import resolve_base
from sked_ns.engine.edit_run import resume_config
from sked_ns.engine.resume import preset_config, resumed_config
from sked_ns.engine.trainer import SkedTrainer, check_run_settings
from sked_ns.errors import SkedUserError, check_writable_folder


def saved_edit() -> object:
    """The config.yml of a short reference-guided CPU edit, as `ns-train sked` saved it."""
    config = preset_config("sked")
    config.pipeline.model.guidance = ReferenceGuidanceConfig()
    config.pipeline.model.prompt = "a hat"
    config.pipeline.model.beta = 0.05
    config.pipeline.model.guidance_resolution = 24
    config.pipeline.model.sketches = Path("/sketches/hat")
    config.data = config.pipeline.datamanager.data = Path("/data/scene")  # the --data alias, as ns-train sets it
    config.max_num_iterations, config.steps_per_save = 60, 20
    config.machine.device_type, config.vis, config.mixed_precision = "cpu", "tensorboard", False
    config.output_dir, config.experiment_name, config.timestamp = Path("/runs"), "scene", "2026-01-01_000000"
    return yaml.load(yaml.dump(config), Loader=yaml.Loader)  # as read back from the run's config.yml


def resume(config, saved, argv=()):
    resumed_config(config, saved, preset_config("sked"), Path("/runs/scene/sked/2026-01-01_000000"), argv=list(argv))
    return config


def test_resume_takes_the_saved_edit_not_the_defaults():
    config = resume_config(Path("/runs/scene/sked/2026-01-01_000000"), Path("/elsewhere"))
    config.timestamp = "now"
    saved = saved_edit()
    saved.method_name = "sked-fast"  # resumed with `ns-train sked`: still the sked-fast edit, in its folder
    resume(config, saved)
    model = config.pipeline.model
    assert isinstance(model.guidance, ReferenceGuidanceConfig) and model.prompt == "a hat"  # not carving
    assert (model.beta, model.guidance_resolution, model.sketches) == (0.05, 24, Path("/sketches/hat"))
    assert (config.max_num_iterations, config.steps_per_save, config.machine.device_type) == (60, 20, "cpu")
    assert config.pipeline.datamanager.data == Path("/data/scene")
    # This run's own: where it writes (typed) and its timestamp, beside the saved edit's experiment.
    assert (config.output_dir, config.experiment_name, config.timestamp) == (Path("/elsewhere"), "scene", "now")
    assert config.method_name == "sked-fast"
    resume(config, saved)  # the trainer resolves the config again: nothing changes, nothing is refused
    assert isinstance(config.pipeline.model.guidance, ReferenceGuidanceConfig) and config.max_num_iterations == 60
    assert config.load_dir == Path("/runs/scene/sked/2026-01-01_000000")


def test_resume_takes_the_settable_flags():
    config = resume_config(Path("/run"), iterations=100)
    config.viewer.quit_on_train_completion, config.vis = True, "viewer+tensorboard"
    config.pipeline.datamanager.dataparser.data = Path("/data/moved")
    config.pipeline.model.beta = 0.05  # typed, but the saved edit's value: no change
    resume(config, saved_edit())
    assert (config.max_num_iterations, config.vis, config.viewer.quit_on_train_completion) == (100, "viewer+tensorboard", True)
    # Typed data replace the saved ones whole: the saved --data alias would otherwise win over the typed dataparser.
    datamanager = config.pipeline.datamanager
    assert (config.data, datamanager.data, datamanager.dataparser.data) == (None, None, Path("/data/moved"))
    assert config.pipeline.model.prompt == "a hat"


def test_resume_refuses_what_would_change_the_edit():
    config = resume_config(Path("/run"))
    config.sketches = config.pipeline.model.sketches = Path("/sketches/other")  # the alias, as resolve_edit sets it
    config.pipeline.model.beta = 0.5
    config.pipeline.model.lambda_pres = 0.0
    with pytest.raises(SkedUserError) as refused:
        resume(config, saved_edit())
    message = str(refused.value)
    assert "--pipeline.model.sketches" not in message  # said once, as typed
    for typed in ("--sketches", "--pipeline.model.beta: 0.5 here, 0.05 in the saved edit", "--pipeline.model.lambda-pres",
                  "--progressive True"):
        assert typed in message, message
    # A new guidance is one change, named once (not with each of its settings).
    config = resume_config(Path("/run"))
    config.pipeline.model.guidance = copy.deepcopy(preset_config("sked").pipeline.model.guidance)
    config.pipeline.model.guidance.guidance_scale = 7.5
    saved = saved_edit()
    with pytest.raises(SkedUserError, match=r"pipeline\.model\.guidance \(a subcommand\): StableDiffusionGuidanceConfig here, "
                                            r"ReferenceGuidanceConfig") as refused:
        resume(config, saved)
    assert "guidance-scale" not in str(refused.value)


def test_an_edit_saved_before_a_setting_existed_continues_as_it_ran():
    text = yaml.dump(saved_edit())
    for line in ("edit_fill: 0.7", "sampling: as-rendered"):
        assert text.count(line) == 1, line
    older = yaml.load(text.replace("edit_fill: 0.7", "").replace("sampling: as-rendered", ""), Loader=yaml.Loader)
    # Read back without them, the class defaults (this version's) would show through.
    assert older.pipeline.datamanager.edit_fill == 0.7 and older.pipeline.model.guidance.sampling == "as-rendered"
    config = resume(resume_config(Path("/run")), older)
    assert config.pipeline.datamanager.edit_fill == 0.0  # the authors' 40-80 deg views it was trained with
    assert config.pipeline.model.guidance.sampling == "pixel-centre"
    # Typing the value it ran with is no change; an edit saved with the settings keeps its own.
    typed = resume_config(Path("/run"))
    typed.pipeline.datamanager.edit_fill = 0.0
    assert resume(typed, yaml.load(text.replace("edit_fill: 0.7", ""), Loader=yaml.Loader)).pipeline.datamanager.edit_fill == 0.0
    current = resume(resume_config(Path("/run")), saved_edit())
    assert (current.pipeline.datamanager.edit_fill, current.pipeline.model.guidance.sampling) == (0.7, "as-rendered")


def test_a_flag_typed_at_its_default_value_counts_on_the_ns_train_command_line():
    config = resume_config(Path("/run"))  # beta is the preset's 0.025 whether typed or not
    resume(copy.deepcopy(config), saved_edit(), argv=["pytest"])  # not ns-train: the saved 0.05 is kept
    with pytest.raises(SkedUserError, match=r"--pipeline\.model\.beta: 0\.025 here, 0\.05"):
        resume(config, saved_edit(), argv=["/venv/bin/ns-train", "sked", "--load-dir", "/run",
                                           "--pipeline.model.beta", "0.025"])


@pytest.mark.parametrize("iterations", [0, -5])
def test_iterations_below_one_are_refused(iterations):
    config = preset_config("sked")
    config.max_num_iterations = iterations
    with pytest.raises(SkedUserError, match=f"--max-num-iterations {iterations}: an edit needs at least 1"):
        check_run_settings(config)


def test_save_and_eval_intervals_are_checked():
    config = preset_config("sked")
    config.steps_per_save, config.logging.steps_per_log = -1, -2
    with pytest.raises(SkedUserError, match=r"--steps-per-save -1, --logging.steps-per-log -2: .*whole number >= 0"):
        check_run_settings(config)
    config.steps_per_save, config.logging.steps_per_log = 0, 10
    with pytest.warns(UserWarning, match="--steps-per-save 0: the edit is saved only when it ends"):
        check_run_settings(config)


# ---- checkpoints ----------------------------------------------------------------------------


def fake_run(folder: Path, steps) -> Path:
    """A run folder (config.yml of a SKED edit) with a tiny intact checkpoint per step."""
    (folder / "nerfstudio_models").mkdir(parents=True)
    (folder / "config.yml").write_text(yaml.dump(preset_config("sked")))
    for step in steps:
        torch.save({"step": step, "pipeline": {"_model.field.w": torch.full((256,), float(step))}},
                   folder / "nerfstudio_models" / f"step-{step:09d}.ckpt")
    return folder


def test_a_checkpoint_cut_short_by_a_kill_is_named_and_skipped(tmp_path):
    run = fake_run(tmp_path / "run", [10, 20])
    models = run / "nerfstudio_models"
    intact = (models / "step-000000020.ckpt").read_bytes()
    (models / "step-000000030.ckpt").write_bytes(intact[: len(intact) // 2])  # killed mid-write
    (models / "step-000000040.ckpt").write_bytes(b"")  # killed before the first byte
    with pytest.warns(UserWarning) as caught:
        assert resolve_base(run).checkpoint == models / "step-000000020.ckpt"
    skipped = [str(w.message) for w in caught]
    assert any("step-000000040.ckpt: skipped, it is empty (0 bytes)" in m for m in skipped), skipped
    assert any("step-000000030.ckpt: skipped, it is truncated" in m for m in skipped), skipped
    with pytest.raises(SkedUserError, match=r"step-000000030.ckpt: cannot use this checkpoint: it is truncated"):
        resolve_base(run, step=30)  # a step the user chose is not swapped for another
    for path in models.glob("*.ckpt"):
        path.write_bytes(b"")
    with pytest.raises(SkedUserError, match="every checkpoint here is broken"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        resolve_base(run)


def checkpointing_trainer(run: Path, save_only_latest: bool = False) -> SkedTrainer:
    """Just what SkedTrainer.save_checkpoint reads, around a tiny model."""
    trainer = SkedTrainer.__new__(SkedTrainer)
    pipeline = torch.nn.Module()
    pipeline.model = torch.nn.Linear(4, 4)
    trainer.pipeline = pipeline
    trainer.optimizers = SimpleNamespace(optimizers={}, schedulers={})
    trainer.grad_scaler = torch.amp.GradScaler("cpu", enabled=False)
    trainer.checkpoint_dir = run / "nerfstudio_models"
    trainer.config = SimpleNamespace(save_only_latest_checkpoint=save_only_latest)
    return trainer


def test_a_kill_while_saving_leaves_the_last_checkpoint_intact(tmp_path, monkeypatch):
    run = fake_run(tmp_path / "run", [])
    trainer = checkpointing_trainer(run)
    trainer.save_checkpoint(10)
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000010.ckpt"]
    assert not (run / ".nerfstudio_models.partial").exists()

    def killed_half_way(state, path, *args, **kwargs):
        Path(path).write_bytes(b"PK\x03\x04 half a checkpoint")
        raise KeyboardInterrupt  # the process dies here

    monkeypatch.setattr(torch, "save", killed_half_way)
    with pytest.raises(KeyboardInterrupt):
        trainer.save_checkpoint(20)
    # The checkpoint folder holds only whole checkpoints: nerfstudio's own loaders list it too.
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000010.ckpt"]
    assert resolve_base(run).checkpoint.name == "step-000000010.ckpt"
    monkeypatch.undo()
    trainer.config.save_only_latest_checkpoint = True
    trainer.save_checkpoint(30)  # the next save replaces the stale partial file
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000030.ckpt"]
    assert torch.load(run / "nerfstudio_models" / "step-000000030.ckpt")["step"] == 30


def test_an_unwritable_checkpoint_folder_names_the_path(tmp_path):
    (tmp_path / "file").write_text("")
    trainer = checkpointing_trainer(tmp_path / "file" / "run")
    with pytest.raises(SkedUserError, match=r"file/run/nerfstudio_models/step-000000005.ckpt: cannot write"):
        trainer.save_checkpoint(5)


def test_output_folder_under_a_file_is_refused_with_its_flag(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    with pytest.raises(SkedUserError, match=r"--output-dir .*file/sub: cannot write there \(the run folder "):
        check_writable_folder(tmp_path / "file" / "sub" / "exp" / "sked", "--output-dir", tmp_path / "file" / "sub")
    # Permission bits do not stop root: a refused write is what counts.
    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / "ro" / "probe"))

    monkeypatch.setattr(Path, "write_bytes", refuse)
    with pytest.raises(SkedUserError, match=r"--output-dir .*ro: cannot write there: Permission denied"):
        check_writable_folder(tmp_path / "ro", "--output-dir")


# ---- the resumed run's config.yml ------------------------------------------------------------


@pytest.fixture
def inputs_pass(monkeypatch):
    """A fake_run has no data nor sketches: the inputs' checks (tests/foundation/test_cli_errors.py) pass, the writing is tested."""
    import sked_ns.engine.trainer

    monkeypatch.setattr(sked_ns.engine.trainer, "check_edit_inputs", lambda config: None)


def resumed_into(run: Path, output_dir: Path, timestamp: str = "{timestamp}"):
    """`ns-train sked --load-dir RUN --output-dir OUT --data ... --max-num-iterations 100` on a fake_run."""
    config = resume_config(run, output_dir, iterations=100)
    config.data = run  # the fake edit saved none
    config.timestamp = timestamp
    config.set_timestamp()
    return config


def test_a_resumed_runs_config_yml_names_none_of_the_interrupted_runs_checkpoints(tmp_path, inputs_pass):
    """nerfstudio's eval_setup (ns-render, ns-export, ns-viewer) loads config.yml's load_step from the run's own
    folder: the step this start resumes from is the interrupted run's."""
    run = fake_run(tmp_path / "run", [10])
    config = resumed_into(run, tmp_path / "out")
    config.save_config()
    written = yaml.load((config.get_base_dir() / "config.yml").read_text(), Loader=yaml.Loader)
    assert (written.load_dir, written.load_step, written.load_checkpoint) == (None, None, None)
    assert written.max_num_iterations == 100 and type(written) is type(config)
    assert (config.load_dir, config.load_step) == (run / "nerfstudio_models", 10)  # this start still resumes


def full_disk(monkeypatch) -> None:
    """Files open (and truncate) as on a full disk, and no byte can be written to them."""
    import errno
    import io

    real_open = io.open

    class Full:
        def __init__(self, file):
            self._file = file

        def write(self, data):
            if len(data):
                raise OSError(errno.ENOSPC, "No space left on device")
            return 0

        def __getattr__(self, name):
            return getattr(self._file, name)

        def __enter__(self):
            return self

        def __exit__(self, *exception):
            self._file.close()

    def opened(file, mode="r", *args, **kwargs):
        handle = real_open(file, mode, *args, **kwargs)
        return handle if mode.startswith("r") and "+" not in mode else Full(handle)

    monkeypatch.setattr(io, "open", opened)  # pathlib's writes and os.fdopen open through it


def test_a_full_disk_at_resume_keeps_config_yml_and_says_so_in_one_line(tmp_path, monkeypatch, inputs_pass):
    # sked-batch resumes a job into its own folder: a failed write must not leave its config.yml empty.
    run = fake_run(tmp_path / "job" / "edit" / "sked" / "run", [10])
    before = (run / "config.yml").read_text()
    config = resumed_into(run, tmp_path / "job", timestamp="run")
    config.experiment_name = "edit"
    assert config.get_base_dir() == run
    full_disk(monkeypatch)
    with pytest.raises(SkedUserError, match=r"^\S*job/edit/sked/run/config.yml: cannot write the run's config \(No "
                                            r"space left on device\)\. Free space there, or pass another --output-dir"):
        config.save_config()
    monkeypatch.undo()
    assert (run / "config.yml").read_text() == before
    left = sorted(p.name for p in run.iterdir() if p.name != ".sked-writer.lock")  # the lock is the run's writer's
    assert left == ["config.yml", "nerfstudio_models"]  # no partial file left


def saved_splat_edit() -> object:
    """saved_edit() of a splatfacto base: the model and optimisers start_edit gives a splat edit."""
    from nerfstudio.models.splatfacto import SplatfactoModelConfig

    from sked_ns.engine.trainer import edit_model_config
    from sked_ns.models.splat.rates import splat_optimizers

    config = saved_edit()
    config.pipeline.model = edit_model_config(config.pipeline.model, SplatfactoModelConfig())
    config.optimizers = splat_optimizers(config.max_num_iterations, config.pipeline.model)
    return yaml.load(yaml.dump(config), Loader=yaml.Loader)


def test_a_splat_edit_compares_each_typed_flag_as_a_nerf_edit_does():
    """The command line parses the preset's NeRF model config; a splat edit's own is no subcommand the user typed."""
    config = resume_config(Path("/run"))
    config.pipeline.model.beta = 0.05  # typed, the saved edit's value: no change
    resumed = resume(config, saved_splat_edit())
    assert type(resumed.pipeline.model).__name__ == "SkedSplatModelConfig" and resumed.pipeline.model.beta == 0.05
    resume(resumed, saved_splat_edit())  # the trainer resolves it again
    config = resume_config(Path("/run"))
    config.pipeline.model.beta, config.pipeline.model.num_nerf_samples_per_ray = 0.5, 7
    with pytest.raises(SkedUserError) as refused:
        resume(config, saved_splat_edit())
    message = str(refused.value)
    assert "--pipeline.model.beta: 0.5 here, 0.05 in the saved edit" in message, message
    assert ("--pipeline.model.num-nerf-samples-per-ray: 7 here; the saved edit's SkedSplatModelConfig has no such "
            "setting") in message, message
    assert "subcommand" not in message, message
    with pytest.raises(SkedUserError, match=r"--pipeline\.model\.beta: 0\.025 here, 0\.05"):
        resume(resume_config(Path("/run")), saved_splat_edit(), argv=["ns-train", "sked", "--pipeline.model.beta", "0.025"])


def test_an_edit_resumed_by_an_older_version_opens_and_says_how_nerfstudio_can_open_it(tmp_path, inputs_pass):
    run = fake_run(tmp_path / "run", [30])
    older = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    older.load_dir, older.load_step = tmp_path / "interrupted" / "nerfstudio_models", 20  # as it resumed
    (run / "config.yml").write_text(yaml.dump(older))
    with pytest.warns(UserWarning, match=r"config.yml: load_step 20 is the step its resume started from, so "
                                         r"ns-render, ns-export and ns-viewer .* `load_step: null`"):
        assert resolve_base(run).checkpoint.name == "step-000000030.ckpt"  # sked-eval and a resume take the latest
    config = resumed_into(run, tmp_path / "out")
    with pytest.warns(UserWarning, match="load_step 20"):
        config.save_config()
    assert (config.load_dir, config.load_step) == (run / "nerfstudio_models", 30)


FIELD_KEYS = ["local_field.density_mlp.layers.0.weight", "local_field.encoding.hash_table"]


@pytest.mark.parametrize("saved_keys, resumed_as, options", [
    (["local_field.head.0.weight", "local_field.encoding.hash_table"], "local-residual", (32, True)),  # 0.8's
    (FIELD_KEYS, "local", (0, False)),  # 0.9's local field: no hull proposal, no colour residual
    (FIELD_KEYS + ["hull_proposal.log_scale", "colour_residual.linear.weight"], "local", (32, True)),
])
def test_a_local_edit_resumes_as_the_representation_its_checkpoint_holds(tmp_path, saved_keys, resumed_as, options):
    from sked_ns.engine.resume import keep_saved_representation

    checkpoint = tmp_path / "step-000000019.ckpt"
    torch.save({"pipeline": {f"_model.{key}": torch.zeros(2) for key in saved_keys}, "step": 19}, checkpoint)
    model = SimpleNamespace(nerf_edit_field="local", hull_proposal_grid=32, colour_residual=True)
    keep_saved_representation(model, checkpoint)
    assert model.nerf_edit_field == resumed_as
    assert (model.hull_proposal_grid, model.colour_residual) == options  # what it trained, as it ran
    # A whole-field copy is left to its own setting (config.yml says it, or its age: SETTINGS_SINCE).
    model = SimpleNamespace(nerf_edit_field="full-copy")
    keep_saved_representation(model, checkpoint)
    assert model.nerf_edit_field == "full-copy"
