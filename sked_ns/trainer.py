"""`ns-train sked`: turns `--load-dir` into a base to edit (or an edit to resume).

nerfstudio's `--load-dir` means "resume this run": it restores the optimisers and the step.
An edit instead starts at step 0 with fresh optimisers from the base's weights, so the base
is resolved here, before the config is saved: its architecture is copied into the edit's
model config, its checkpoint recorded, and `load_dir` cleared. Pointing `--load-dir` at an
earlier SKED run resumes it; add `--progressive True` to edit that result again instead.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional, Type

import torch
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.models.instant_ngp import InstantNGPModelConfig
from nerfstudio.utils.rich_utils import CONSOLE

from sked_ns.base_scene import copy_base_architecture, resolve_base
from sked_ns.compat import train_loop_adds_start_step
from sked_ns.safe_step import GuardedGradScaler, GuardedOptimizers, StepGuard
from sked_ns.core import SkedOptions
from sked_ns.nerfacto_model import SkedNerfactoModelConfig
from sked_ns.ngp_model import SkedNGPModelConfig
from sked_ns.validation import check_options


@dataclass
class SkedTrainerConfig(TrainerConfig):
    _target: Type = field(default_factory=lambda: SkedTrainer)
    sketches: Optional[Path] = None
    """Alias for --pipeline.model.sketches: the sketch-set folder."""
    progressive: bool = False
    """With --load-dir on an earlier SKED run: edit its result again instead of resuming it."""

    def save_config(self) -> None:
        resolve_edit(self)  # before saving, so config.yml describes the edit's real model
        super().save_config()


def resolve_edit(config: SkedTrainerConfig) -> None:
    """Fill the model config from --load-dir and the aliases; safe to call twice."""
    check_options(config.pipeline.model, config.pipeline.datamanager)  # bad values refused before anything is written
    # Learning rates decay to 0.1x by the end of this edit (docs/method.md, Optimisation), however long --max-num-iterations makes it.
    for optimizer in config.optimizers.values():
        if hasattr(optimizer.get("scheduler"), "max_steps"):
            optimizer["scheduler"].max_steps = config.max_num_iterations
    model = config.pipeline.model
    if config.sketches is not None:
        model.sketches = config.sketches
    if config.load_dir is None:
        if model.base_checkpoint is None:
            raise ValueError("ns-train sked needs the scene to edit: --load-dir <base run>/nerfstudio_models.")
        return
    base = resolve_base(config.load_dir, config.load_step)
    if base.family == "sked" and not config.progressive:
        # Resume: same architecture, base and sketch set as the interrupted run.
        previous = base.model_config
        model = config.pipeline.model = edit_model_config(model, previous)
        model.base_checkpoint = previous.base_checkpoint
        model.sketches = model.sketches or previous.sketches
        model.prompt = model.prompt or previous.prompt
        config.load_dir = base.checkpoint.parent
        CONSOLE.print(f"Resuming the SKED edit {base.run_dir} from {base.checkpoint.name}")
        return
    model = config.pipeline.model = edit_model_config(model, base.model_config)
    model.base_checkpoint = base.checkpoint
    config.load_dir = None  # the base is not a run to resume: fresh optimisers, step 0
    config.load_step = None
    CONSOLE.print(f"Editing the {base.method} scene {base.run_dir} ({base.checkpoint.name})")


def edit_model_config(model, base_model_config):
    """The SKED model for the base's sampler (grid or proposals), shaped like the base, keeping SKED's options."""
    wanted = SkedNGPModelConfig if isinstance(base_model_config, InstantNGPModelConfig) else SkedNerfactoModelConfig
    if not isinstance(model, wanted):
        options = {option.name: getattr(model, option.name) for option in fields(SkedOptions)}
        model = wanted(**options, eval_num_rays_per_chunk=model.eval_num_rays_per_chunk)
    copy_base_architecture(model, base_model_config)
    return model


class SkedTrainer(Trainer):
    config: SkedTrainerConfig

    def __init__(self, config: SkedTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        super().__init__(config, local_rank=local_rank, world_size=world_size)
        self.step_guard = StepGuard(lambda: self.pipeline.model.parameters())
        # Before setup, so the pipeline gets it too: never backpropagates or applies a non-finite value.
        self.grad_scaler = GuardedGradScaler(self.step_guard, enabled=self.grad_scaler.is_enabled(),
                                             device=self.device.split(":")[0])

    def setup(self, test_mode="val") -> None:
        resolve_edit(self.config)
        self.skipped_steps = 0
        # fp16 on CUDA; tests set it on the CPU (where nerfstudio turns mixed precision off) to prove fp16 safety.
        self.autocast_dtype = torch.float16 if self.device.startswith("cuda") else torch.bfloat16
        super().setup(test_mode=test_mode)
        if getattr(self, "viewer_state", None) is not None:
            self._show_sketches_in_viewer()

    def _show_sketches_in_viewer(self) -> None:
        """The sketch views (frusta showing their masks) and the edit box, beside the training cameras.

        Through viser directly: nerfstudio's ViewerControl offers no scene objects (the model's controls,
        beta and the show-base / tint switches, are nerfstudio viewer elements, core.py)."""
        from sked_ns.sketch_viewer import show_sketch_views

        model = self.pipeline.model
        server = self.viewer_state.viser_server
        show_sketch_views(server, model.sketch_set.views, model.edit_box)
        lines = [f"- view {i}: {v.width}x{v.height}, mask {v.mask.mean():.0%} of the image"
                 for i, v in enumerate(model.sketch_set.views)]
        with server.gui.add_folder("SKED sketches"):
            server.gui.add_markdown("\n".join(lines))

    def _load_checkpoint(self) -> None:
        if self.config.load_dir is None and self.config.load_checkpoint is None:
            # Not "training from scratch": the model already holds the base's weights.
            CONSOLE.print(f"Edit starts at step 0 from the base {self.config.pipeline.model.base_checkpoint}")
            return
        super()._load_checkpoint()

    def train(self) -> None:
        # An edit's length is its total: nerfstudio 1.1.5 would run max_num_iterations more steps after a resume.
        if train_loop_adds_start_step():
            self.config.max_num_iterations = max(self.config.max_num_iterations - self._start_step, 1)
        super().train()

    def setup_optimizers(self) -> GuardedOptimizers:
        return GuardedOptimizers(super().setup_optimizers(), self.step_guard)

    def train_iteration(self, step: int):
        """nerfstudio's iteration under the step guard: a non-finite loss or gradient skips the update."""
        self.step_guard.start()
        device_type = "cpu" if self.device.split(":")[0] in ("cpu", "mps") else self.device.split(":")[0]
        with default_autocast_dtype(device_type, self.autocast_dtype):
            loss, loss_dict, metrics_dict = super().train_iteration(step)
        if self.step_guard.reason == "loss":
            self._skip(step, [name for name, value in loss_dict.items() if not torch.isfinite(value).all()] or ["loss"])
        elif self.step_guard.skipped:
            self._skip(step, [self.step_guard.reason])
        metrics_dict["skipped_steps"] = torch.tensor(float(self.skipped_steps))
        return loss, loss_dict, metrics_dict

    def _skip(self, step: int, names) -> None:
        self.skipped_steps += 1
        CONSOLE.print(f"[yellow]step {step}: non-finite {', '.join(names)}; update skipped[/yellow]")

    def save_checkpoint(self, step: int) -> None:
        """Never write a checkpoint holding NaN or inf weights."""
        bad = [name for name, p in self.pipeline.model.named_parameters() if not torch.isfinite(p).all()]
        if bad:
            CONSOLE.print(f"[red]step {step}: not saving a checkpoint with non-finite weights ({bad[:3]})[/red]")
            return
        super().save_checkpoint(step)


@contextlib.contextmanager
def default_autocast_dtype(device_type: str, dtype: torch.dtype):
    """nerfstudio's autocast takes the device's default dtype: make it SKED's for one iteration."""
    previous = torch.get_autocast_dtype(device_type)
    torch.set_autocast_dtype(device_type, dtype)
    try:
        yield
    finally:
        torch.set_autocast_dtype(device_type, previous)
