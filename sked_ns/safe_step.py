"""NaN-safe steps inside nerfstudio's own training iteration.

nerfstudio's `Trainer.train_iteration` zeroes gradients, computes the loss, calls
`grad_scaler.scale(loss).backward()`, steps each optimizer through `grad_scaler.step`, calls
`grad_scaler.update()` and then the schedulers. SKED keeps that iteration as it is (gradient
accumulation and `--log-gradients` included) and guards two of the objects it calls: the grad
scaler never backpropagates a non-finite loss nor applies a non-finite gradient, and the
optimizers' schedulers wait while an update is skipped.
"""

from __future__ import annotations

from typing import Callable, Iterable, Optional

import torch
from torch.nn import Parameter


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

    def __init__(self, guard: StepGuard, enabled: bool):
        super().__init__("cuda", enabled=enabled)
        self.guard = guard

    def scale(self, outputs):
        if not torch.isfinite(outputs).all():
            self.guard.skip("loss")
            # backward() of a fresh leaf reaches no weight
            return torch.zeros((), device=outputs.device, requires_grad=True)
        return super().scale(outputs)

    def unscale_(self, optimizer) -> None:
        if not self.guard.skipped:
            super().unscale_(optimizer)

    def step(self, optimizer, *args, **kwargs):
        if not self.is_enabled():  # an enabled scaler skips non-finite gradients itself
            self.guard.check_gradients()
        if self.guard.skipped:
            return None
        return super().step(optimizer, *args, **kwargs)

    def update(self, new_scale=None) -> None:
        if not self.guard.skipped:  # nothing was stepped: the scale stays
            super().update(new_scale)


class GuardedOptimizers:
    """nerfstudio's Optimizers (every attribute passed through), whose schedulers wait on a skipped update."""

    def __init__(self, optimizers, guard: StepGuard):
        self._optimizers = optimizers
        self._guard = guard

    def __getattr__(self, name: str):
        return getattr(self._optimizers, name)

    def scheduler_step_all(self, step: int) -> None:
        if not self._guard.skipped:
            self._optimizers.scheduler_step_all(step)
