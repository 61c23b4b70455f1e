"""Guidance: a tiny random Stable Diffusion saved to disk and loaded by path, offline."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sked_ns.guidance import RenderedView, StableDiffusionGuidanceConfig
from sked_ns.guidance.stable_diffusion import DiffusionWeightsMissing
from tiny_sd import build_tiny_stable_diffusion


@pytest.fixture(scope="module")
def tiny_sd(tmp_path_factory):
    return build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny-sd"))


def _view(size=32, direction="side"):
    image = torch.rand(1, 3, size, size, requires_grad=True)
    return RenderedView(image=image, camera_to_world=np.eye(4)[:3], focal=30.0, direction=direction)


def _guidance(model, **kwargs):
    return StableDiffusionGuidanceConfig(model=str(model), image_size=32, **kwargs).setup()


def test_loads_from_a_local_folder_and_keeps_only_what_the_loop_uses(tiny_sd):
    guidance = _guidance(tiny_sd)
    guidance.prepare("a red hat", "cpu", {})
    assert guidance.dtype == torch.float32  # fp32 on the CPU
    assert set(guidance.embeddings) == {"", "front", "side", "back", "overhead", "bottom"}
    assert not hasattr(guidance, "text_encoder") and not hasattr(guidance, "tokenizer")  # freed
    assert guidance.vae.decoder is None  # loaded only to decode
    assert not any(p.requires_grad for p in guidance.unet.parameters())
    # Directional prompts give different embeddings.
    assert not torch.equal(guidance.embeddings["front"], guidance.embeddings["back"])


def test_sds_gradient_reaches_the_image_and_is_finite(tiny_sd):
    guidance = _guidance(tiny_sd)
    guidance.prepare("a red hat", "cpu", {})
    view = _view()
    losses = guidance(view, step=0)
    assert set(losses) == {"sds_loss"} and torch.isfinite(losses["sds_loss"])
    losses["sds_loss"].backward()
    assert view.image.grad is not None and torch.isfinite(view.image.grad).all() and view.image.grad.abs().sum() > 0


@pytest.mark.parametrize("scale", [1.0, 100.0, 1000.0])
def test_sds_finite_across_guidance_scales(tiny_sd, scale):
    guidance = _guidance(tiny_sd, guidance_scale=scale)
    guidance.prepare("a red hat", "cpu", {})
    for step in range(3):
        view = _view(direction="overhead")
        loss = guidance(view, step)["sds_loss"]
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(view.image.grad).all()


def test_decode_loads_the_decoder_on_demand(tiny_sd):
    guidance = _guidance(tiny_sd)
    guidance.prepare("a red hat", "cpu", {})
    latents = guidance.encode(torch.rand(1, 3, 32, 32))
    images = guidance.decode(latents)
    assert images.shape[1] == 3 and images.min() >= 0 and images.max() <= 1
    assert guidance.vae.decoder is None


def test_empty_prompt_is_refused(tiny_sd):
    with pytest.raises(ValueError, match="--prompt"):
        _guidance(tiny_sd).prepare("  ", "cpu", {})


def test_missing_weights_offline_say_how_to_get_them(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "empty-cache"))
    guidance = StableDiffusionGuidanceConfig(model="CompVis/stable-diffusion-v1-4").setup()
    with pytest.raises(DiffusionWeightsMissing, match="huggingface-cli download CompVis/stable-diffusion-v1-4"):
        guidance.prepare("a red hat", "cpu", {})


def test_incomplete_local_folder_names_the_part(tmp_path):
    (tmp_path / "sd").mkdir()
    guidance = StableDiffusionGuidanceConfig(model=str(tmp_path / "sd")).setup()
    with pytest.raises(DiffusionWeightsMissing, match="no 'tokenizer/' here"):
        guidance.prepare("a red hat", "cpu", {})
