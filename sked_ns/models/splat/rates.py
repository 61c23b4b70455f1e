"""Learning rates of a splat edit: splatfacto's are sized for 30,000 steps from scratch; an edit's seeds must form
within the edit's own length."""

from __future__ import annotations

import math
from typing import Dict, Optional

from sked_ns.method.options import SkedOptions
from sked_ns.models.splat.gaussians import SH_C0

SPLATFACTO_RATES = {"means": 1.6e-4, "scales": 0.005, "quats": 0.001, "features_dc": 0.0025,
                    "features_rest": 0.0025 / 20, "opacities": 0.05}
"""splatfacto's Adam learning rates of the six Gaussian groups, sized for 30,000-step runs."""
FORMATION_SHARE = 1.0 / 3.0
"""Under the edit's rates a seed can cross each of its ranges (seed_ranges) in this share of the edit's iterations."""
MIN_FORMATION_STEPS = 30
"""... but in no fewer steps than this: wider steps are noisier and jolt the editable base Gaussians of short edits
(docs/benchmarks.md)."""
OPAQUE = 0.99
"""The opacity a seed of the new part must be able to reach."""


def seed_ranges(seed_opacity: float) -> Dict[str, float]:
    """How far a seed's parameters must move to become part of the new content: its opacity logit from seed_opacity
    to opaque, its SH DC coefficient from grey to a saturated colour (0.5 / SH_C0), its log size by a factor of 4."""
    logit = lambda p: math.log(p / (1.0 - p))  # noqa: E731
    return {"opacities": max(logit(OPAQUE) - logit(seed_opacity), 0.0), "features_dc": 0.5 / SH_C0,
            "scales": math.log(4.0)}


def edit_rates(iterations: int, seed_opacity: float) -> Dict[str, float]:
    """The edit's Adam learning rates. Adam moves a parameter by about its rate a step, so splatfacto's rates, sized
    for 30,000 steps, leave a 500-step edit's seeds a faint grey haze (a seed's opacity logit moves 0.05 a step,
    its colour 0.0025 / 0.28 of grey a step). Each rate lets a seed cross its range in FORMATION_SHARE of the edit,
    never under splatfacto's (a long edit gets splatfacto's); the other groups keep splatfacto's."""
    steps = max(FORMATION_SHARE * max(int(iterations), 0), MIN_FORMATION_STEPS)
    ranges = seed_ranges(seed_opacity)
    return {name: max(rate, ranges.get(name, 0.0) / steps) for name, rate in SPLATFACTO_RATES.items()}


def splat_optimizers(iterations: int, options: Optional[SkedOptions] = None) -> Dict[str, Dict]:
    """The optimisers of the six Gaussian groups: Adam at the edit's rates (edit_rates), or at splatfacto's with
    `--pipeline.model.splat-learning-rates splatfacto` (or no options); the means' rate decays 100x over the edit,
    as over a splatfacto run."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    if options is None or options.splat_learning_rates == "splatfacto":
        rates = dict(SPLATFACTO_RATES)
    else:
        rates = edit_rates(iterations, options.seed_opacity)
    return {name: {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
                   "scheduler": (ExponentialDecaySchedulerConfig(lr_final=lr / 100, max_steps=iterations)
                                 if name == "means" else None)}
            for name, lr in rates.items()}
