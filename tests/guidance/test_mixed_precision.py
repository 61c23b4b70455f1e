"""Mixed precision with score distillation: an fp16 overflow skips the whole update, and is counted.

nerfstudio's own iteration (`Trainer.train_iteration`, under SKED's step guard) runs on the CPU with
an enabled grad scaler and the tiny Stable Diffusion in fp16, as on CUDA: one optimizer's parameters
get the SDS gradient through the fp16 VAE, the other's a plain fp32 loss.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from nerfstudio.engine.optimizers import AdamOptimizerConfig, Optimizers
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from tiny_sd import build_tiny_stable_diffusion
from torch.nn import Parameter

from sked_ns.engine.safe_step import INITIAL_LOSS_SCALE, GuardedGradScaler, GuardedOptimizers, StepGuard
from sked_ns.engine.trainer import SkedTrainer
from sked_ns.guidance import RenderedView, StableDiffusionGuidanceConfig

GUIDANCE_SCALE = 100.0


@pytest.fixture(scope="module")
def fp16_guidance(tmp_path_factory):
    folder = build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny-sd"))
    guidance = StableDiffusionGuidanceConfig(model=str(folder), image_size=16, guidance_scale=GUIDANCE_SCALE).setup()
    guidance.prepare("a red hat", "cpu", {})
    # What half_precision gives on CUDA, forced here (the CPU runs fp16 convolutions, slowly).
    guidance.dtype = torch.float16
    guidance.unet.half(), guidance.vae.half()
    guidance.embeddings = {key: value.half() for key, value in guidance.embeddings.items()}
    return guidance


class SdsPipeline:
    """Losses of one iteration: SDS on the 'field' image, a plain fp32 loss on the 'camera' vector."""

    def __init__(self, guidance, field, camera):
        self.guidance, self.field, self.camera = guidance, field, camera

    def get_train_loss_dict(self, step):
        torch.manual_seed(step + 1)
        view = RenderedView(image=torch.sigmoid(self.field), camera_to_world=np.eye(4)[:3], focal=20.0, direction="side")
        losses = {"sds_loss": self.guidance(view, step)["sds_loss"], "camera_loss": (self.camera - 1).pow(2).sum()}
        return {}, losses, {}


def _trainer(guidance, init_scale):
    """SkedTrainer's iteration (and nerfstudio's inside it) on two parameter groups, without a scene."""
    # A textured render: a uniform one makes the CPU's fp16 GroupNorm backward NaN at any scale.
    field = Parameter(torch.randn(1, 3, 16, 16, generator=torch.Generator().manual_seed(100)))
    camera = Parameter(torch.zeros(4))
    groups = {"field": [field], "camera": [camera]}
    optimizers = Optimizers(
        {name: {"optimizer": AdamOptimizerConfig(lr=1e-2), "scheduler": ExponentialDecaySchedulerConfig(max_steps=100)}
         for name in groups}, groups)
    trainer = SkedTrainer.__new__(SkedTrainer)
    trainer.step_guard = StepGuard(lambda: [field, camera])
    trainer.grad_scaler = GuardedGradScaler(trainer.step_guard, enabled=True, device="cpu", init_scale=init_scale)
    trainer.optimizers = GuardedOptimizers(optimizers, trainer.step_guard)
    trainer.pipeline = SdsPipeline(guidance, field, camera)
    trainer.config = SimpleNamespace(log_gradients=False)
    trainer.device, trainer.mixed_precision, trainer.autocast_dtype = "cpu", False, torch.float16
    trainer.gradient_accumulation_steps = {name: 1 for name in groups}
    trainer.skipped_steps, trainer.skipped_in_a_row, trainer._stepped = 0, 0, True  # as __init__ and a first step leave them
    return trainer, field, camera


def _learning_rates(trainer):
    return [optimizer.param_groups[0]["lr"] for optimizer in trainer.optimizers.optimizers.values()]


def test_an_fp16_overflow_skips_every_optimizer_and_scheduler_and_is_counted(fp16_guidance):
    trainer, field, camera = _trainer(fp16_guidance, init_scale=2.0**20)  # the SDS gradient overflows fp16 at once
    start, rates = field.detach().clone(), _learning_rates(trainer)
    _, _, metrics = trainer.train_iteration(0)
    assert torch.equal(camera.detach(), torch.zeros(4)), "the optimizer whose gradient was finite stepped alone"
    assert trainer.step_guard.reason == "gradients"
    assert torch.equal(field.detach(), start)
    assert trainer.skipped_steps == 1 and float(metrics["skipped_steps"]) == 1
    assert _learning_rates(trainer) == rates  # the schedulers waited
    assert trainer.grad_scaler.get_scale() == 2.0**19  # and the scale backed off, for the next step


def test_the_initial_loss_scale_keeps_the_first_sds_steps(fp16_guidance):
    def skipped(init_scale):
        trainer, field, camera = _trainer(fp16_guidance, init_scale=init_scale)
        for step in range(2):
            trainer.train_iteration(step)
        assert torch.isfinite(field).all() and camera.detach().abs().sum() > 0
        return trainer.skipped_steps

    assert skipped(2.0**16) > 0  # torch's default throws first steps away at the paper's guidance scale
    assert INITIAL_LOSS_SCALE <= 2.0**10 and skipped(INITIAL_LOSS_SCALE) == 0


def test_unscale_before_clipping_is_not_repeated(fp16_guidance):
    """nerfstudio unscales an optimizer with max_norm itself: after the all-or-nothing check that is a no-op."""
    trainer, field, camera = _trainer(fp16_guidance, init_scale=INITIAL_LOSS_SCALE)
    for name in ("field", "camera"):
        trainer.optimizers.config[name]["optimizer"].max_norm = 1.0
    trainer.train_iteration(0)
    assert trainer.skipped_steps == 0 and camera.detach().abs().sum() > 0
