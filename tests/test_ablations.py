"""Each SKED loss does its job: switching it off must visibly break the edit (issue 12: tests that can fail).

The other end-to-end tests use reference guidance that alone fills the sketch and keeps the rest, so a
zeroed or sign-flipped L_sil or L_pres would pass them. Here guidance is made useless (weight 0) or
hostile (a target that changes everything), and the ablation must lose what the full loss keeps.
"""

from __future__ import annotations

import numpy as np
import torch

from sked_ns.edit_run import edit_config, run_edit
from sked_ns.demo.reference_guidance import ReferenceGuidance
from sked_ns.metrics import intersection_over_sketch, psnr_outside
from sked_ns.render import render_at, render_base_at, resized_mask

ITERATIONS = 40


def _edit(scene, tmp_path, ablation, **model_settings):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path / ablation, iterations=ITERATIONS,
                         guidance_resolution=24, silhouette_resolution=24, steps_per_save=10**6)
    config.pipeline.model.ablation = ablation
    for key, value in model_settings.items():
        target = config.pipeline.model
        *path, name = key.split("__")
        for part in path:
            target = getattr(target, part)
        setattr(target, name, value)
    model = run_edit(config).pipeline.model
    figures = []
    for view in model.sketch_set.views:
        mask = resized_mask(view, 32)
        edit, base = render_at(model, view, 32), render_base_at(model, view, 32)
        figures.append({"ios": intersection_over_sketch(edit["accumulation"], mask),
                        "ios_base": intersection_over_sketch(base["accumulation"], mask),
                        "psnr_outside": psnr_outside(edit["rgb"], base["rgb"], mask)})
    return {key: float(np.mean([f[key] for f in figures])) for key in figures[0]}


def _recoloured(self, view):
    """The base's render with its colour channels rotated (blue sphere -> red), changed everywhere: white
    background stays white, so geometry is untouched and only the colour of what must be kept is attacked
    (an inverted image, black where the background is, asks for opaque mass everywhere, which no weight
    of L_pres at the authors' setting resists at reference weight 30)."""
    return view.base_image[:, [2, 0, 1]], torch.ones_like(view.base_image[:, :1])


def test_without_guidance_the_silhouette_loss_alone_fills_the_sketch(scene, tmp_path):
    # Half the base's samples: the difference stays decisive at 40 steps, in half the time.
    full = _edit(scene, tmp_path, "none", guidance__weight=0.0, samples_per_ray_scale=0.5)
    ablated = _edit(scene, tmp_path, "no-silhouette", guidance__weight=0.0, samples_per_ray_scale=0.5)
    assert full["ios"] > full["ios_base"] + 0.3, full
    assert ablated["ios"] < ablated["ios_base"] + 0.1, ablated


def test_against_a_hostile_target_preservation_keeps_the_rest(scene, tmp_path, monkeypatch):
    """A target that recolours the whole scene, inside and outside the sketches: only preservation resists it.

    Preservation is L_pres plus the base-photo anchor; the no-preserve ablation drops both. Measured at 40 steps:
    PSNR outside 22.5 vs 20.5 dB (and 28.9 vs 27.2 at half the samples). Either alone is not asserted: L_pres alone
    measured 21.7 vs 21.8 dB (its colour term acts only where the base density exceeds the occupancy threshold) and
    the anchor alone 23.5 vs 20.7 in one run but 20.7 vs 20.5 in another (issue 9, open).
    """
    monkeypatch.setattr(ReferenceGuidance, "target_image", _recoloured)
    full = _edit(scene, tmp_path / "full", "none")
    ablated = _edit(scene, tmp_path / "ablated", "no-preserve")
    print("hostile target: full / no-preserve", full, ablated)
    assert full["psnr_outside"] > ablated["psnr_outside"] + 1.0, (full, ablated)
