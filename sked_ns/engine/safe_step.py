"""NaN-safe steps inside nerfstudio's own training iteration.

nerfstudio's `Trainer.train_iteration` zeroes gradients, computes the loss, calls
`grad_scaler.scale(loss).backward()`, steps each optimizer through `grad_scaler.step`, calls
`grad_scaler.update()` and then the schedulers, under autocast at the device's default dtype (made SKED's for the
iteration: `default_autocast_dtype`). SKED keeps that iteration as it is (gradient
accumulation and `--log-gradients` included) and guards two of the objects it calls: the grad
scaler never backpropagates a non-finite loss nor applies a non-finite gradient, and the
optimizers' schedulers wait while an update is skipped. A skip is all or nothing: every
optimizer's gradients are unscaled and checked before any optimizer steps (torch's scaler alone
skips only the optimizers whose own gradients overflowed, and the others still step).
"""

from __future__ import annotations

import contextlib
from typing import Callable, Iterable, Optional

import torch
from torch.nn import Parameter

INITIAL_LOSS_SCALE = 2.0**10
"""The fp16 loss scale's start (torch's default is 2**16). The SDS gradient per latent, w(t) (eps_hat - eps), reaches
tens at guidance scale 100 (w up to 0.38, eps_hat - eps up to ~100x the prompts' difference) and enters the fp16 VAE
encoder's backward times 0.18 (SD's latent scaling) times the loss scale: fp16's 65504 allows 5.5 per latent at
2**16, before the backward amplifies it further, 350 at 2**10. The scaler still doubles the scale after each 2000
clean steps. With the tiny test SD at scale 100, 2**16 overflows the first steps and 2**10 does not."""


class StepGuard:
    """Whether this iteration's update is skipped, and why ("loss" or "gradients")."""

    def __init__(self, parameters: Callable[[], Iterable[Parameter]]):
        self.parameters = parameters
        """The weights whose gradients are checked (the model's)."""
        self.start()

    def start(self) -> None:
        """Call before each iteration."""
        self.reason: Optional[str] = None
        self._gradients_checked = False

    @property
    def skipped(self) -> bool:
        return self.reason is not None

    def skip(self, reason: str) -> None:
        self.reason = self.reason or reason

    def check_gradients(self) -> None:
        """Once per iteration, before the first optimizer step: all gradients finite, with one sync."""
        if self._gradients_checked or self.skipped:
            return
        self._gradients_checked = True
        gradients = [p.grad for p in self.parameters() if p.grad is not None]
        if gradients and not bool(torch.stack([torch.isfinite(g).all() for g in gradients]).all()):
            for parameter in self.parameters():
                parameter.grad = None  # as optimizer.zero_grad(): nothing of this step is applied later
            self.skip("gradients")


class GuardedGradScaler(torch.amp.GradScaler):
    """nerfstudio's grad scaler, except that a skipped iteration backpropagates and applies nothing."""

    def __init__(self, guard: StepGuard, enabled: bool, device: str = "cuda", init_scale: float = INITIAL_LOSS_SCALE):
        super().__init__(device, init_scale=init_scale, enabled=enabled)
        self.guard = guard
        self._unscaled: set = set()
        """Optimizers unscaled since the last update (all are unscaled before any steps: unscale once)."""

    def scale(self, outputs):
        if not torch.isfinite(outputs).all():
            self.guard.skip("loss")
            # backward() of a fresh leaf reaches no weight
            return torch.zeros((), device=outputs.device, requires_grad=True)
        return super().scale(outputs)

    def unscale_(self, optimizer) -> None:
        if not self.guard.skipped and id(optimizer) not in self._unscaled:
            self._unscaled.add(id(optimizer))
            super().unscale_(optimizer)

    def unscale_all(self, optimizers) -> None:
        """Before any optimizer steps: every gradient unscaled, so an overflow in any one skips them all."""
        if self.is_enabled():
            for optimizer in optimizers:
                if any(p.grad is not None for group in optimizer.param_groups for p in group["params"]):
                    self.unscale_(optimizer)
        self.guard.check_gradients()

    def step(self, optimizer, *args, **kwargs):
        if not self.is_enabled():  # an enabled scaler skips non-finite gradients itself
            self.guard.check_gradients()
        if self.guard.skipped:
            return None
        return super().step(optimizer, *args, **kwargs)

    def update(self, new_scale=None) -> None:
        # After an overflow the scale backs off (its inf checks were recorded by unscale_); after a non-finite loss
        # nothing was unscaled and the scale stays.
        if self._unscaled or not self.guard.skipped:
            super().update(new_scale)
        self._unscaled.clear()


class GuardedOptimizers:
    """nerfstudio's Optimizers (every attribute passed through): all step or none, and the schedulers wait on a skip."""

    def __init__(self, optimizers, guard: StepGuard):
        self._optimizers = optimizers
        self._guard = guard

    def __getattr__(self, name: str):
        return getattr(self._optimizers, name)

    def optimizer_scaler_step_all(self, grad_scaler: GuardedGradScaler) -> None:
        grad_scaler.unscale_all(self._optimizers.optimizers.values())
        if not self._guard.skipped:
            self._optimizers.optimizer_scaler_step_all(grad_scaler)

    def optimizer_scaler_step_some(self, grad_scaler: GuardedGradScaler, param_groups) -> None:
        grad_scaler.unscale_all(self._optimizers.optimizers[group] for group in param_groups)
        if not self._guard.skipped:
            self._optimizers.optimizer_scaler_step_some(grad_scaler, param_groups)

    def scheduler_step_all(self, step: int) -> None:
        if not self._guard.skipped:
            self._optimizers.scheduler_step_all(step)


@contextlib.contextmanager
def default_autocast_dtype(device_type: str, dtype: torch.dtype):
    """nerfstudio's autocast takes the device's default dtype: make it SKED's for one iteration."""
    previous = torch.get_autocast_dtype(device_type)
    torch.set_autocast_dtype(device_type, dtype)
    try:
        yield
    finally:
        torch.set_autocast_dtype(device_type, previous)
