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


# ---- score distillation against a stub UNet whose answer is known --------------------------------
EPS_PER_PROMPT = {"": 0.30, "side": 0.31}
"""Noise the stub predicts for each prompt's embedding; any other prompt gets OTHER_EPS."""
OTHER_EPS = 5.0


class StubUNet:
    """Predicts a constant per prompt embedding, and recovers the true noise from what it is given."""

    def __init__(self, guidance, latents):
        self.guidance, self.latents, self.calls = guidance, latents, []

    def __call__(self, sample, timestep, encoder_hidden_states):
        alpha_bar = self.guidance.alphas_cumprod[timestep].view(-1, 1, 1, 1)
        # noisy = sqrt(alpha_bar) x + sqrt(1 - alpha_bar) eps, so eps is known to the test.
        noise = (sample - alpha_bar.sqrt() * self.latents.detach()) / (1 - alpha_bar).sqrt()
        self.calls.append({"t": timestep.clone(), "noise": noise})
        eps = [self._eps_of(row) for row in encoder_hidden_states]
        predicted = torch.stack([torch.full_like(sample[0], value) for value in eps])
        return type("UNetOutput", (), {"sample": predicted})()

    def _eps_of(self, row):
        for key, value in EPS_PER_PROMPT.items():
            if torch.equal(row, self.guidance.embeddings[key]):
                return value
        return OTHER_EPS


def _stubbed(tiny_sd, **kwargs):
    guidance = _guidance(tiny_sd, **kwargs)
    guidance.prepare("a red hat", "cpu", {})
    latents = torch.randn(1, 4, 4, 4, requires_grad=True)
    guidance.encode = lambda image: latents  # the gradient is checked w.r.t. the latents themselves
    guidance._unet_forward = StubUNet(guidance, latents)
    return guidance, latents


@pytest.mark.parametrize("weighting", ["authors", "dreamfusion"])
def test_sds_gradient_is_w_times_guided_noise_minus_noise(tiny_sd, weighting):
    scale = 100.0
    guidance, latents = _stubbed(tiny_sd, guidance_scale=scale, weighting=weighting)
    guidance(_view(direction="side"), step=0)["sds_loss"].backward()
    call = guidance._unet_forward.calls[0]
    t = call["t"][:1]
    alpha_bar = guidance.scheduler.alphas_cumprod[t].view(-1, 1, 1, 1)
    w = alpha_bar.sqrt() * (1 - alpha_bar) if weighting == "authors" else 1 - alpha_bar
    # Unconditional first: eps_hat = eps_uncond + s (eps_text - eps_uncond) = 1.3 here (swapped: -0.69).
    guided = EPS_PER_PROMPT[""] + scale * (EPS_PER_PROMPT["side"] - EPS_PER_PROMPT[""])
    expected = w * (guided - call["noise"][:1])  # both halves of the UNet batch hold the same noisy latents
    torch.testing.assert_close(latents.grad, expected, rtol=1e-4, atol=1e-5)


def test_sds_weightings_differ_by_sqrt_alpha_bar_and_bad_ones_are_refused(tiny_sd):
    from sked_ns.guidance.stable_diffusion import sds_weight

    alpha_bar = torch.tensor([0.9, 0.5, 0.0058])
    torch.testing.assert_close(sds_weight(alpha_bar, "authors"), alpha_bar.sqrt() * sds_weight(alpha_bar, "dreamfusion"))
    assert StableDiffusionGuidanceConfig().weighting == "authors"
    with pytest.raises(ValueError, match=r"weighting.*'sds'.*--pipeline.model.guidance.weighting"):
        _guidance(tiny_sd, weighting="sds").prepare("a red hat", "cpu", {})


@pytest.mark.parametrize("t_range, bounds", [((0.02, 0.98), (20, 980)), ((0.5, 0.6), (500, 600))])
def test_sds_timesteps_stay_in_t_range(tiny_sd, t_range, bounds):
    guidance, _ = _stubbed(tiny_sd, t_range=t_range)
    torch.manual_seed(0)
    for step in range(1500):
        guidance(_view(size=8), step)
    t = torch.cat([call["t"] for call in guidance._unet_forward.calls])
    low, high = bounds
    assert t.min() >= low and t.max() <= high
    span = high - low
    assert t.min() < low + span / 50 and t.max() > high - span / 50  # the whole range is used


def test_latents_are_sampled_from_the_vae_posterior(tiny_sd):
    guidance = _guidance(tiny_sd)
    guidance.prepare("a red hat", "cpu", {})
    image = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        samples = guidance.encode(image.expand(400, -1, -1, -1))  # 400 draws, one encoder pass
    with torch.no_grad():
        posterior = guidance.vae.encode(image * 2 - 1).latent_dist
    scale = guidance.vae.config.scaling_factor
    assert not torch.equal(samples[0], samples[1])  # the authors sample; the mean would repeat
    torch.testing.assert_close(samples.mean(0, keepdim=True), posterior.mean * scale, atol=4 * posterior.std.max() * scale / 20, rtol=0)
    torch.testing.assert_close(samples.std(0, keepdim=True), posterior.std * scale, rtol=0.15, atol=1e-6)
