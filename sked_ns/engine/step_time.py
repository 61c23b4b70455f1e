"""How long one edit step will take on its device kind: a rough estimate, printed with the memory plan.

A step's time is, to first order, its NeRF side, proportional to the field samples it renders with
gradients (the random view's and the sketch views' rays times the samples per ray), plus Stable
Diffusion's guidance step, which grows with its input's side squared. Each device kind's two rates come
from one measured step (STEP_SPEEDS): another machine of that kind, its load, its memory bandwidth and the
base's hash table size move them severalfold, so the estimate says how it was measured and is for telling
minutes from hours, no more. A step expected to take longer than SLOW_STEP_SECONDS is warned
(engine/memory_plan.check_memory); the trainer says while its first step runs how long it has been running.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional


@dataclass(frozen=True)
class StepSpeed:
    """Seconds of a step's parts on one kind of device, from one measured step."""

    per_field_sample: float
    """Per NeRF field sample of the step: its renders, the frozen base's L_pres, the backward pass, the optimiser."""
    sd_step_at_512: float
    """Stable Diffusion's guidance step at a 512 px input (VAE encode with its backward, the UNet at batch 2), at the
    precision it runs in there (fp32 on the CPU, fp16 on CUDA)."""
    measured_on: str
    """What the step was measured on, said with every estimate."""


STEP_SPEEDS: Dict[str, StepSpeed] = {
    # benchmarks/results/gpu_check_cpu_full.json: the step (ms_per_iteration) less the bare SD step (sd_floor_ms),
    # over its 64 px random view and two 64 px sketch views (rendered whole then) at nerfacto's 400 samples a ray.
    "cpu": StepSpeed(per_field_sample=(431.234 - 171.200) / (3 * 64**2 * 400), sd_step_at_512=171.200,
                     measured_on="a busy 2-core CPU"),
    # docs/benchmarks.md, GPU: run 1's seconds per iteration at 128 px (a random view and two whole sketch views, 400
    # samples a ray) less follow-up 3's eager fp16 SD step; torch hash grids (no tiny-cuda-nn).
    "cuda": StepSpeed(per_field_sample=(3.7 - 0.0656) / (3 * 128**2 * 400), sd_step_at_512=0.0656,
                      measured_on="an H200"),
}
"""Each device kind's rates (machine.device_type); a kind without a row gets no estimate."""

SLOW_STEP_SECONDS = 300.0
"""A step expected to take longer is warned: minutes of silence before the first step ends, and even sked-fast's
3,000 iterations would take over a week."""


@dataclass(frozen=True)
class StepTime:
    """A step's expected seconds on its device."""

    seconds: float
    whole: bool
    """False: a part of the step has no measured rate here (a splat edit's renders), so this is a lower bound."""
    measured_on: str

    def line(self, device: str, iterations: int) -> str:
        what = "about" if self.whole else "at least"
        return (f"Expected time per step on {device}: {what} {duration(self.seconds)}, {what} "
                f"{duration(self.seconds * iterations)} for {iterations:,} iterations (a rough estimate from a step "
                f"measured on {self.measured_on})")


def step_time(device_type: str, field_samples: Optional[float], sd_image_size: Optional[float] = None,
              sd_device_type: Optional[str] = None) -> Optional[StepTime]:
    """The expected step of an edit rendering FIELD_SAMPLES field samples with gradients on DEVICE_TYPE (None: a
    representation with no measured rate), guided by Stable Diffusion at SD_IMAGE_SIZE px on SD_DEVICE_TYPE
    (default: the same; None: another guidance, not counted). None where nothing of it was measured."""
    speed = STEP_SPEEDS.get(device_type)
    if speed is None:
        return None
    seconds, whole = 0.0, field_samples is not None
    if field_samples is not None:
        seconds += field_samples * speed.per_field_sample
    if sd_image_size:
        sd_speed = STEP_SPEEDS.get(sd_device_type or device_type)
        if sd_speed is None:
            whole = False
        else:
            seconds += sd_speed.sd_step_at_512 * (sd_image_size / 512) ** 2
    if not whole and seconds == 0:
        return None
    return StepTime(seconds, whole, speed.measured_on)


def slow_step_warning(time: StepTime, device_type: str) -> Optional[str]:
    """What to say of a step expected to take longer than SLOW_STEP_SECONDS on DEVICE_TYPE, or None."""
    if time.seconds <= SLOW_STEP_SECONDS:
        return None
    gpu = ", or train on a GPU (--machine.device-type cuda)" if device_type == "cpu" else ""
    return (f"one step of this edit is expected to take {'about' if time.whole else 'at least'} "
            f"{duration(time.seconds)} on {device_type} (a rough estimate). Lower --pipeline.model.guidance-resolution "
            "and --pipeline.model.silhouette-resolution (e.g. 64, as ns-train sked-fast), or "
            f"--pipeline.model.samples-per-ray-scale{gpu}.")


def duration(seconds: float) -> str:
    """Seconds as a person reads them: `0.25 s`, `42 s`, `2.5 min`, `20 h`, `1,234 days`."""
    seconds = max(seconds, 0.0)
    for unit, length in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 1.5 * length:
            return f"{seconds / length:,.0f} {unit}" if seconds >= 10 * length else f"{seconds / length:.1f} {unit}"
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.1f} s" if seconds >= 1 else f"{seconds:.2f} s"
