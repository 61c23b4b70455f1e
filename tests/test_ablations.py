"""Each SKED loss does its job: switching it off must visibly break the edit (issue 12: tests that can fail).

The other end-to-end tests use reference guidance that alone fills the sketch and keeps the rest, so a
zeroed or sign-flipped L_sil or L_pres would pass them. Here guidance is made useless (weight 0) or
hostile (a target that changes everything), and the ablation must lose what the full loss keeps.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.edit_run import edit_config, run_edit
from sked_ns.guidance.reference import ReferenceGuidance
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


def test_without_guidance_the_silhouette_loss_alone_fills_the_sketch(scene, tmp_path):
    full = _edit(scene, tmp_path, "none", reference__weight=0.0)
    ablated = _edit(scene, tmp_path, "no-silhouette", reference__weight=0.0)
    assert full["ios"] > full["ios_base"] + 0.3, full
    assert ablated["ios"] < ablated["ios_base"] + 0.1, ablated


def test_against_a_hostile_target_preservation_keeps_the_rest(scene, tmp_path, monkeypatch):
    # A target that inverts every colour, inside and outside the sketches: only preservation resists it.
    monkeypatch.setattr(ReferenceGuidance, "target_image",
                        lambda self, view: (1 - view.base_image, torch.ones_like(view.base_image[:, :1])))
    full = _edit(scene, tmp_path, "none")
    ablated = _edit(scene, tmp_path, "no-preserve")
    assert full["psnr_outside"] > ablated["psnr_outside"] + 3.0, (full, ablated)
    assert full["psnr_outside"] > 20.0, full


@pytest.mark.parametrize("lambda_photo", [0.0, 1.0])
def test_the_photo_anchor_alone_resists_a_hostile_target(scene, tmp_path, monkeypatch, lambda_photo):
    """With L_pres off, the base's photos are what keeps the scene (and nothing does without them)."""
    monkeypatch.setattr(ReferenceGuidance, "target_image",
                        lambda self, view: (1 - view.base_image, torch.ones_like(view.base_image[:, :1])))
    figures = _edit(scene, tmp_path, "none", lambda_pres=0.0, lambda_photo=lambda_photo)
    if lambda_photo:
        assert figures["psnr_outside"] > 20.0, figures
    else:
        assert figures["psnr_outside"] < 18.0, figures
