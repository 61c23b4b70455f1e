"""Evaluation metrics on synthetic cases with known answers."""

from __future__ import annotations

import math

import pytest
import torch

from sked_ns.evaluation.metrics import IOS_THRESHOLDS, intersection_over_sketch, psnr_outside, ssim_outside


def test_ios_thresholds_are_the_papers():
    assert len(IOS_THRESHOLDS) == 9
    assert IOS_THRESHOLDS[0] == pytest.approx(25 / 255) and IOS_THRESHOLDS[-1] == pytest.approx(225 / 255)


def test_ios_known_answers():
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[:2] = True  # 8 sketch pixels
    full = torch.ones(4, 4)
    assert intersection_over_sketch(full, mask) == 1.0
    assert intersection_over_sketch(torch.zeros(4, 4), mask) == 0.0
    half = torch.zeros(4, 4)
    half[0] = 1.0  # 4 of 8 sketch pixels covered at every threshold
    assert intersection_over_sketch(half, mask) == 0.5
    # alpha 0.5 (127.5 / 255) passes the thresholds 25, 50, 75, 100 and 125 / 255: 5 of 9.
    assert intersection_over_sketch(torch.full((4, 4), 0.5), mask) == pytest.approx(5 / 9)
    with pytest.raises(ValueError, match="empty mask"):
        intersection_over_sketch(full, torch.zeros(4, 4, dtype=torch.bool))


def test_psnr_outside_ignores_the_sketch():
    base = torch.zeros(8, 8, 3)
    edited = base.clone()
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:4] = True
    edited[mask] = 1.0  # changes inside the sketch do not count
    assert psnr_outside(edited, base, mask) == math.inf
    edited[~mask] = 0.1  # MSE 0.01 outside -> 20 dB
    assert psnr_outside(edited, base, mask) == pytest.approx(20.0, rel=1e-5)
    with pytest.raises(ValueError, match="whole image"):
        psnr_outside(edited, base, torch.ones(8, 8, dtype=torch.bool))


def test_ssim_outside_known_answers():
    torch.manual_seed(0)
    base = torch.rand(32, 32, 3)
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[:, :8] = True
    assert ssim_outside(base, base, mask) == pytest.approx(1.0, abs=1e-6)
    noisy = (base + 0.3 * torch.randn_like(base)).clamp(0, 1)
    assert ssim_outside(noisy, base, mask) < 0.9


def test_psnr_inside_looks_only_at_the_sketch():
    from sked_ns.evaluation.metrics import psnr_inside

    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[2:4, 2:6] = True
    target = torch.full((8, 8, 3), 0.5)
    edited = target.clone()
    edited[~mask] = 0.0  # wrong everywhere outside: ignored
    assert psnr_inside(edited, target, mask) == math.inf
    edited[mask] = 0.6  # MSE 0.01 inside -> 20 dB
    assert psnr_inside(edited, target, mask) == pytest.approx(20.0, rel=1e-5)
    with pytest.raises(ValueError, match="empty"):
        psnr_inside(edited, target, torch.zeros(8, 8, dtype=torch.bool))
