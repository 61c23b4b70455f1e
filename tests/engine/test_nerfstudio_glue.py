"""The nerfstudio glue without a scene: nerfstudio's own training iteration under SKED's step guard,
the version layer (compat), refused settings, and how a base's model config becomes the edit's."""

from __future__ import annotations

import copy
import types

import pytest
import torch
import yaml
from nerfstudio.configs.method_configs import method_configs
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import Trainer
from nerfstudio.models.nerfacto import NerfactoModelConfig

from sked_ns import compat  # noqa: F401  (the version layer applies on import)
from sked_ns.engine.base_scene import resolve_base
from sked_ns.engine.pipeline import SkedPipeline, SkedPipelineConfig
from sked_ns.engine.trainer import SkedTrainer, SkedTrainerConfig
from sked_ns.method.options import copy_base_architecture
from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig
from sked_ns.models.nerf.ngp import SkedNGPModelConfig
from sked_ns.models.registry import family as base_family


class ToyPipeline(torch.nn.Module):
    """One weight vector and a loss chosen by the test: enough for nerfstudio's train_iteration."""

    def __init__(self, loss):
        super().__init__()
        self.model = torch.nn.Module()
        self.model.weight = torch.nn.Parameter(torch.tensor([1.0, 2.0]))
        self.loss = loss

    def get_param_groups(self):
        return {"fields": [self.model.weight]}

    def get_train_loss_dict(self, step):
        return {}, {"toy_loss": self.loss(self.model.weight)}, {}


def toy_trainer(tmp_path, loss, **settings) -> SkedTrainer:
    config = SkedTrainerConfig(method_name="sked", experiment_name="toy", output_dir=tmp_path, **settings)
    config.machine.device_type = "cpu"
    config.optimizers = {"fields": {"optimizer": AdamOptimizerConfig(lr=0.1),
                                    "scheduler": ExponentialDecaySchedulerConfig(lr_final=0.01, max_steps=10)}}
    trainer = SkedTrainer(config)
    trainer.pipeline = ToyPipeline(loss)
    trainer.optimizers = trainer.setup_optimizers()
    trainer.skipped_steps, trainer.autocast_dtype = 0, torch.bfloat16
    return trainer


def scheduler_steps(trainer) -> int:
    return trainer.optimizers.schedulers["fields"].last_epoch


def test_finite_step_updates_and_steps_the_scheduler(tmp_path):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum())
    _, _, metrics = trainer.train_iteration(0)
    assert not torch.equal(trainer.pipeline.model.weight.detach(), torch.tensor([1.0, 2.0]))
    assert scheduler_steps(trainer) == 1 and trainer.skipped_steps == 0 and metrics["skipped_steps"] == 0


@pytest.mark.parametrize("loss, reason", [
    (lambda w: (w**2).sum() * float("nan"), "loss"),
    (lambda w: torch.sqrt(w - w.detach()).sum(), "gradients"),  # value 0, gradient inf
])
def test_non_finite_loss_or_gradient_skips_update_and_scheduler(tmp_path, loss, reason, capsys):
    trainer = toy_trainer(tmp_path, loss)
    _, _, metrics = trainer.train_iteration(0)
    assert torch.equal(trainer.pipeline.model.weight.detach(), torch.tensor([1.0, 2.0]))
    assert trainer.step_guard.reason == reason and trainer.skipped_steps == 1 and metrics["skipped_steps"] == 1
    assert scheduler_steps(trainer) == 0, "no scheduler step without an update"
    assert trainer.pipeline.model.weight.grad is None, "nothing of the skipped step is applied later"
    assert "update skipped" in capsys.readouterr().out
    trainer.pipeline.loss = lambda w: (w**2).sum()  # the next step is a normal one
    trainer.train_iteration(1)
    assert trainer.step_guard.reason is None and scheduler_steps(trainer) == 1


def test_gradient_accumulation_steps_work(tmp_path):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum(), gradient_accumulation_steps={"fields": 2})
    trainer.train_iteration(0)
    assert torch.equal(trainer.pipeline.model.weight.detach(), torch.tensor([1.0, 2.0])), "accumulating"
    assert torch.equal(trainer.pipeline.model.weight.grad, torch.tensor([2.0, 4.0]))
    trainer.train_iteration(1)
    assert not torch.equal(trainer.pipeline.model.weight.detach(), torch.tensor([1.0, 2.0])), "stepped"


def test_log_gradients_works(tmp_path):
    trainer = toy_trainer(tmp_path, lambda w: (w**2).sum(), log_gradients=True)
    _, _, metrics = trainer.train_iteration(0)
    assert float(metrics["Gradients/Total"]) == pytest.approx(float(torch.tensor([2.0, 4.0]).norm()))


def test_autocast_dtype_is_skeds(tmp_path):
    seen = []
    trainer = toy_trainer(tmp_path, lambda w: seen.append(torch.get_autocast_dtype("cpu")) or (w**2).sum())
    trainer.mixed_precision, trainer.autocast_dtype = True, torch.float16
    trainer.train_iteration(0)
    assert seen == [torch.float16] and torch.get_autocast_dtype("cpu") == torch.bfloat16


def test_multi_device_is_refused_naming_the_flag_and_the_ways_that_scale():
    with pytest.raises(ValueError, match="--machine.num-devices") as refused:
        SkedPipeline(SkedPipelineConfig(), device="cpu", world_size=2)
    assert "--pipeline.model.guidance.device cuda:1" in str(refused.value) and "sked-batch" in str(refused.value)


# ---- nerfstudio 1.1.5's loop ------------------------------------------------------------------

def test_resumed_edit_runs_exactly_to_its_total(monkeypatch):
    """nerfstudio 1.1.5 runs max_num_iterations more steps after a resume; an edit's length is its total."""
    trainer = SkedTrainer.__new__(SkedTrainer)
    trainer.config, trainer._start_step = types.SimpleNamespace(max_num_iterations=25), 21
    seen = []
    monkeypatch.setattr(Trainer, "train", lambda self: seen.extend(
        range(self._start_step, self._start_step + self.config.max_num_iterations)))  # 1.1.5's loop
    trainer.train()
    assert seen == [21, 22, 23, 24]


def test_nerfstudio_1_1_5_loop_is_the_one_the_trainer_counts_on():
    """The pinned nerfstudio adds the start step to the loop's range: if an upgrade changes that, this fails."""
    import inspect

    assert "self._start_step + num_iterations" in inspect.getsource(Trainer.train).replace("\n", " ")


# ---- the base's model config ----------------------------------------------------------------

def test_every_architecture_field_of_the_base_is_copied_but_skeds_own():
    base = NerfactoModelConfig(use_gradient_scaling=True, hidden_dim=32, collider_params={"near_plane": 0.5,
                               "far_plane": 3.0}, prompt="the base's", interlevel_loss_mult=9.0)
    edit = SkedNerfactoModelConfig(prompt="a hat")
    copy_base_architecture(edit, base)
    assert edit.use_gradient_scaling and edit.hidden_dim == 32 and edit.collider_params["near_plane"] == 0.5
    assert edit.prompt == "a hat" and edit.interlevel_loss_mult == 1.0 and edit._target is SkedNerfactoModelConfig()._target
    ngp = method_configs["instant-ngp-bounded"].pipeline.model
    edit = SkedNGPModelConfig()
    copy_base_architecture(edit, ngp)
    assert edit.enable_collider == ngp.enable_collider and edit.grid_resolution == ngp.grid_resolution


@pytest.mark.parametrize("method", ["nerfacto-big", "nerfacto-huge", "depth-nerfacto"])
def test_nerfacto_style_bases_are_recognised_by_config_type(tmp_path, method):
    config = method_configs[method]
    assert base_family(config.pipeline.model) == "nerfacto"
    (tmp_path / "nerfstudio_models").mkdir()
    torch.save({"step": 1, "pipeline": {}}, tmp_path / "nerfstudio_models" / "step-000000001.ckpt")  # intact, if empty
    (tmp_path / "config.yml").write_text(yaml.dump(config))
    assert resolve_base(tmp_path).family == "nerfacto"


def test_other_models_are_refused():
    assert base_family(method_configs["vanilla-nerf"].pipeline.model) is None
    assert base_family(method_configs["splatfacto"].pipeline.model) == "splatfacto"
    assert base_family(method_configs["splatfacto-big"].pipeline.model) == "splatfacto"
    assert base_family(method_configs["instant-ngp"].pipeline.model) == "instant-ngp"
    assert base_family(SkedNGPModelConfig()) == "sked"


def test_run_edit_seeds_as_ns_train_does(tmp_path):
    """ns-train seeds torch, numpy and random from machine.seed before building the trainer; the demo, the
    tests and the benchmarks' Python edits go through run_edit, so it must too, or an edit depends on
    whatever drew random numbers before it (a test that passed alone failed in the full suite)."""
    import random

    import numpy as np

    from sked_ns.engine.edit_run import run_edit

    class Trainer:
        def setup(self):
            self.draws = (torch.rand(3), np.random.rand(3), random.random())

        def train(self):
            pass

    config = types.SimpleNamespace(machine=types.SimpleNamespace(seed=42), set_timestamp=lambda: None,
                                   save_config=lambda: None, setup=lambda **_: Trainer(),
                                   get_base_dir=lambda: tmp_path / "run")
    first = run_edit(config).draws
    torch.rand(7), np.random.rand(7), random.random()  # whatever ran in between
    second = run_edit(config).draws
    assert torch.equal(first[0], second[0]) and np.array_equal(first[1], second[1]) and first[2] == second[2]
    config.machine.seed = 43
    assert not torch.equal(run_edit(config).draws[0], first[0])


@pytest.mark.parametrize("layout, tinycudann, expected", [("torch", True, "torch"), ("torch", False, "torch"),
                                                         ("tcnn", True, "tcnn"), ("tcnn", False, "refused")])
def test_the_edit_takes_the_field_implementation_from_the_base_checkpoint(tmp_path, monkeypatch, layout, tinycudann,
                                                                          expected):
    """A base trained where tinycudann was missing says implementation "tcnn" in its config but holds torch weights:
    the layout decides, and only a tcnn layout without tinycudann is refused (before anything is written)."""
    import importlib.util

    from sked_ns.engine.base_scene import BaseScene
    from sked_ns.engine.resume import preset_config
    from sked_ns.engine.trainer import start_edit
    from sked_ns.errors import SkedUserError

    weights = ({"_model.field.mlp_base.params": torch.zeros(8)} if layout == "tcnn"
               else {"_model.field.mlp_base.layers.0.weight": torch.zeros(2, 2)})
    checkpoint = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": weights}, checkpoint)
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: (
        (types.SimpleNamespace() if tinycudann else None) if name == "tinycudann" else real_find_spec(name, *args)))
    base_config = copy.deepcopy(method_configs["nerfacto"])
    assert base_config.pipeline.model.implementation == "tcnn"  # nerfstudio's default, whatever was installed
    config = preset_config("sked")
    base = BaseScene(run_dir=tmp_path, checkpoint=checkpoint, config=base_config)
    if expected == "refused":
        with pytest.raises(SkedUserError, match="Install tinycudann here"):
            start_edit(config, base)
    else:
        start_edit(config, base)
        assert config.pipeline.model.implementation == expected


def test_printed_commands_are_shell_quoted_and_run_as_printed(tmp_path):
    """What a message offers to type (the dataparser of a frame mismatch, the command that starts an edit again)
    splits back into the same words in a shell, whatever the paths and the prompt hold."""
    import shlex
    import subprocess
    from pathlib import Path

    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from sked_ns.engine.base_scene import dataparser_command, restart_command

    data = tmp_path / "my data; echo INJECTED"
    config = copy.deepcopy(method_configs["nerfacto"])
    config.pipeline.datamanager.dataparser = NerfstudioDataParserConfig(data=data)
    config.pipeline.datamanager.data = data
    shown = dataparser_command(types.SimpleNamespace(config=config)).strip("`")
    assert shlex.split(shown) == ["nerfstudio-data", "--data", str(data)]
    edit = copy.deepcopy(SkedTrainerConfig(method_name="sked"))
    edit.pipeline.datamanager.dataparser = NerfstudioDataParserConfig(data=data)
    edit.pipeline.datamanager.data = data
    edit.pipeline.model.base_checkpoint = Path("/runs/it's mine/nerfstudio_models/step-000000001.ckpt")
    edit.pipeline.model.sketches = tmp_path / "sketches $(touch PWNED)"
    edit.pipeline.model.prompt = 'a "red" hat; rm -rf ~'
    line = restart_command(edit)
    words = subprocess.run(["bash", "-c", f"set -- {line}; printf '%s\\0' \"$@\""], capture_output=True,
                           text=True, cwd=tmp_path, check=True).stdout.split("\0")[:-1]
    assert words == ["ns-train", "sked", "--load-dir", "/runs/it's mine", "--sketches", str(edit.pipeline.model.sketches),
                     "--prompt", 'a "red" hat; rm -rf ~', "nerfstudio-data", "--data", str(data)]
    assert not (tmp_path / "PWNED").exists()

    # Another guidance is part of the edit: its subcommand and its own settings, where tyro reads them.
    import tyro

    from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig

    edit.pipeline.model.guidance = ReferenceGuidanceConfig(target="vase")
    words = shlex.split(restart_command(edit))
    assert words[words.index("--prompt") + 2:words.index("nerfstudio-data")] == [
        "pipeline.model.guidance:reference", "--pipeline.model.guidance.target", "vase"]
    from sked_ns.engine.presets import edit_preset

    preset = edit_preset()
    parsed = tyro.cli(type(preset), default=preset, args=words[2:])
    assert parsed.pipeline.model.guidance == edit.pipeline.model.guidance
