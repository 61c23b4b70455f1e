"""Guidance: a tiny random Stable Diffusion saved to disk and loaded by path, offline."""

from __future__ import annotations

import gc
import json
import re
import shutil
import socket
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_sd import build_tiny_stable_diffusion

from sked_ns.errors import SkedOptionError, SkedOptionWarning
from sked_ns.guidance import RenderedView, StableDiffusionGuidanceConfig, check_guidance, guidance_config
from sked_ns.guidance.hub import hub_cli
from sked_ns.guidance.stable_diffusion import DiffusionWeightsMissing


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


@pytest.mark.parametrize("scale", [1.0, 100.0, 1e6])  # 1e6: refused by nothing, only warned about
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


def _installed_command(message: str) -> str:
    """The first backquoted command of a message, checked to be installed beside this Python."""
    command = re.search(r"`([^`]+)`", message).group(1)
    assert (Path(sys.executable).parent / command.split()[0]).exists(), f"{command}: not installed here"
    return command


def test_missing_weights_offline_say_how_to_get_them(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    guidance = StableDiffusionGuidanceConfig(model="CompVis/stable-diffusion-v1-4").setup()
    with pytest.raises(DiffusionWeightsMissing, match="download CompVis/stable-diffusion-v1-4") as error:
        guidance.prepare("a red hat", "cpu", {})
    assert _installed_command(str(error.value)).endswith("download CompVis/stable-diffusion-v1-4")


@pytest.fixture
def online(monkeypatch):
    """The hub allowed (HF_HUB_OFFLINE unset), with every network connection failing loudly and recorded."""
    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise AssertionError(f"a test reached for the network: {args}")

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_OFFLINE", False)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setattr(socket.socket, "connect", refuse)
    return attempts


def test_online_a_hub_id_not_on_the_machine_is_refused_without_a_download(online, monkeypatch, tmp_path):
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    config = StableDiffusionGuidanceConfig(model="CompVis/stable-diffusion-v1-4")
    with pytest.raises(DiffusionWeightsMissing, match=r"^--pipeline.model.guidance.model CompVis/stable-diffusion-v1-4: "
                                                      r"not on this machine") as error:
        config.check_available()
    assert "\n" not in str(error.value)
    assert _installed_command(str(error.value)) == f"{hub_cli()} download CompVis/stable-diffusion-v1-4"
    assert not config.setup().weights_available() and not online


def test_online_cached_weights_load_without_a_request_to_the_hub(online, tiny_sd, monkeypatch, tmp_path):
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "hub"))
    repo, commit = tmp_path / "hub" / "models--someone--tiny-sd", "0123abcd" * 5  # a cache as `hf download` fills it
    shutil.copytree(tiny_sd, repo / "snapshots" / commit)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    config = StableDiffusionGuidanceConfig(model="someone/tiny-sd", image_size=32)
    config.check_available()
    guidance = config.setup()
    guidance.prepare("a red hat", "cpu", {})
    assert torch.isfinite(guidance(_view(), step=0)["sds_loss"]) and not online


def test_online_missing_weights_are_refused_before_the_edit_writes_anything(online, scene, monkeypatch, tmp_path):
    from sked_ns.engine.edit_run import edit_config

    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path / "out", prompt="a red hat",
                         guidance="stable-diffusion", iterations=2)
    config.set_timestamp()
    with pytest.raises(DiffusionWeightsMissing, match="not on this machine"):
        config.print_to_terminal()  # nerfstudio's first hook, before the run folder, config.yml and the viewer
    with pytest.raises(DiffusionWeightsMissing, match="not on this machine"):
        config.save_config()
    assert not (tmp_path / "out").exists() and not online


def test_the_file_check_passes_a_saved_checkpoint_and_names_what_a_cached_one_lacks(tiny_sd, tmp_path, monkeypatch):
    import shutil

    from sked_ns.errors import SkedUserError

    StableDiffusionGuidanceConfig(model=str(tiny_sd)).check_available()  # what save_pretrained writes is enough
    # The same checkpoint as the hub cache holds a downloaded id, read offline.
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "hub"))  # read at import: patched
    repo = tmp_path / "hub" / "models--someone--tiny-sd"
    shutil.copytree(tiny_sd, repo / "snapshots" / "0123abcd")
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0123abcd")
    config = StableDiffusionGuidanceConfig(model="someone/tiny-sd")
    config.check_available()
    assert config.setup().weights_available()
    scheduler = repo / "snapshots" / "0123abcd" / "scheduler" / "scheduler_config.json"
    saved = scheduler.read_text()
    scheduler.write_text(saved.replace('"epsilon"', '"sample"'))
    with pytest.raises(SkedUserError, match="predicts 'sample'"):
        config.check_available()
    scheduler.write_text(saved)
    (repo / "snapshots" / "0123abcd" / "unet" / "diffusion_pytorch_model.safetensors").unlink()  # a broken download
    with pytest.raises(DiffusionWeightsMissing, match=r"--pipeline.model.guidance.model someone/tiny-sd \(cached in "
                                                      r".*\): no unet/diffusion_pytorch_model.safetensors or"):
        config.check_available()
    assert not config.setup().weights_available()


def test_incomplete_local_folder_names_the_part(tmp_path):
    (tmp_path / "sd").mkdir()
    guidance = StableDiffusionGuidanceConfig(model=str(tmp_path / "sd")).setup()
    with pytest.raises(DiffusionWeightsMissing, match="no 'scheduler/' here"):
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


# ---- SD 2.x: v-prediction ----------------------------------------------------------------------------
def _with_prediction_type(tiny_sd, folder, prediction_type):
    """The tiny checkpoint whose scheduler says its UNet predicts `prediction_type`."""
    shutil.copytree(tiny_sd, folder)
    config_file = folder / "scheduler" / "scheduler_config.json"
    config_file.write_text(json.dumps({**json.loads(config_file.read_text()), "prediction_type": prediction_type}))
    return folder


class StubVUNet(StubUNet):
    """The v-predicting twin of StubUNet: the same noise estimate, expressed as v (diffusers' get_velocity)."""

    def __call__(self, sample, timestep, encoder_hidden_states):
        eps = super().__call__(sample, timestep, encoder_hidden_states).sample
        alpha_bar = self.guidance.alphas_cumprod[timestep].view(-1, 1, 1, 1)
        x0 = (sample - (1 - alpha_bar).sqrt() * eps) / alpha_bar.sqrt()
        v = self.guidance.scheduler.get_velocity(x0, eps, timestep)
        return type("UNetOutput", (), {"sample": v})()


def test_v_prediction_gives_the_gradient_of_the_equivalent_noise_model(tiny_sd, tmp_path):
    gradients = {}
    for prediction_type, unet in (("epsilon", StubUNet), ("v_prediction", StubVUNet)):
        guidance = _guidance(_with_prediction_type(tiny_sd, tmp_path / prediction_type, prediction_type))
        guidance.prepare("a red hat", "cpu", {})
        assert guidance.prediction_type == prediction_type
        latents = torch.randn(1, 4, 4, 4, generator=torch.Generator().manual_seed(0), requires_grad=True)
        guidance.encode = lambda image: latents
        guidance._unet_forward = unet(guidance, latents)
        torch.manual_seed(0)  # the same t and noise for both
        guidance(_view(direction="side"), step=0)["sds_loss"].backward()
        gradients[prediction_type] = latents.grad
    assert gradients["epsilon"].abs().max() > 0.01
    torch.testing.assert_close(gradients["v_prediction"], gradients["epsilon"], rtol=1e-4, atol=1e-5)


def test_noise_from_v_by_hand():
    from sked_ns.guidance.stable_diffusion import noise_prediction

    alpha_bar, x0, eps = torch.tensor(0.36), torch.tensor(2.0), torch.tensor(-0.5)
    noisy = 0.6 * x0 + 0.8 * eps  # sqrt(0.36), sqrt(0.64)
    v = 0.6 * eps - 0.8 * x0
    torch.testing.assert_close(noise_prediction(v, noisy, alpha_bar, "v_prediction"), eps)
    assert noise_prediction(v, noisy, alpha_bar, "epsilon") is v


def test_an_unsupported_prediction_type_is_refused_before_the_weights_load(tiny_sd, tmp_path):
    guidance = _guidance(_with_prediction_type(tiny_sd, tmp_path / "sample", "sample"))
    with pytest.raises(ValueError, match=r"predicts 'sample'.*supports.*epsilon.*v_prediction"):
        guidance.prepare("a red hat", "cpu", {})
    assert not hasattr(guidance, "unet")


# ---- memory: what reaches the device ------------------------------------------------------------------
def test_the_vae_decoder_never_moves_and_the_text_encoder_is_freed(tiny_sd, monkeypatch):
    from diffusers import AutoencoderKL
    from transformers import CLIPTextModel

    moved_with_decoder, text_encoders = [], []
    module_to = torch.nn.Module.to

    def to(module, *args, **kwargs):
        if isinstance(module, AutoencoderKL):
            moved_with_decoder.append(module.decoder is not None)
        return module_to(module, *args, **kwargs)

    load_text_encoder = CLIPTextModel.from_pretrained

    def load_and_watch(*args, **kwargs):
        model = load_text_encoder(*args, **kwargs)
        text_encoders.append(weakref.ref(model))
        return model

    monkeypatch.setattr(torch.nn.Module, "to", to)
    monkeypatch.setattr(CLIPTextModel, "from_pretrained", load_and_watch)
    guidance = _guidance(tiny_sd)
    guidance.prepare("a red hat", "cpu", {})
    assert moved_with_decoder == [False]  # the VAE moved once, without its decoder
    assert guidance.vae.decoder is None and guidance.vae.post_quant_conv is None
    gc.collect()
    assert len(text_encoders) == 1 and text_encoders[0]() is None  # nothing holds the text encoder


# ---- the diffusion model on its own device ------------------------------------------------------------
def test_guidance_device_parses_from_the_command_line():
    import tyro

    from sked_ns.engine.presets import edit_preset

    config = edit_preset()
    parsed = tyro.cli(type(config), default=config, args=["pipeline.model.guidance:stable-diffusion",
                                                          "--pipeline.model.guidance.device", "cuda:1"])
    assert parsed.pipeline.model.guidance.device == "cuda:1"
    assert StableDiffusionGuidanceConfig().device is None  # default: the edit's device


def test_guidance_runs_on_its_own_device_and_the_gradient_comes_back(tiny_sd):
    # The edit's device here is "meta" (no storage): every module and the loss's graph must be on the guidance's.
    guidance = _guidance(tiny_sd, device="cpu")
    guidance.prepare("a red hat", "meta", {})
    devices = {p.device.type for module in (guidance.unet, guidance.vae) for p in module.parameters()}
    assert devices == {"cpu"} and guidance.alphas_cumprod.device.type == "cpu"
    view = _view()
    loss = guidance(view, step=0)["sds_loss"]
    assert loss.device == view.image.device
    loss.backward()
    assert view.image.grad.abs().sum() > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_guidance_on_cuda_returns_the_loss_to_a_cpu_render(tiny_sd):
    guidance = _guidance(tiny_sd, device="cuda:0", compile=False)
    guidance.prepare("a red hat", "cpu", {})
    assert next(guidance.unet.parameters()).device.type == "cuda"
    view = _view()
    loss = guidance(view, step=0)["sds_loss"]
    loss.backward()
    assert loss.device.type == "cpu" and torch.isfinite(view.image.grad).all() and view.image.grad.abs().sum() > 0


@pytest.mark.parametrize("device, message", [("gpu:0", "not a torch device"), ("cuda:64", "CUDA device")])
def test_a_bad_guidance_device_is_refused(device, message):
    with pytest.raises(SkedOptionError, match=rf"--pipeline.model.guidance.device.*{message}"):
        StableDiffusionGuidanceConfig(device=device).check()


# ---- bad input: prompt, guidance scale and the other numbers, the model folder ---------------------------
@pytest.mark.parametrize("prompt", ["", "   "])
def test_an_empty_prompt_is_refused_and_says_how_to_carve(prompt):
    with pytest.raises(SkedOptionError, match=r"--prompt .* is empty\. To carve .*leave out --prompt"):
        check_guidance(StableDiffusionGuidanceConfig(), prompt)
    check_guidance(StableDiffusionGuidanceConfig(), None)  # carving, as asked


def test_the_pipeline_refuses_an_empty_prompt_before_reading_any_data(tmp_path):
    from sked_ns.engine.pipeline import SkedPipelineConfig
    from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig

    # An unset shell variable ($PROMPT) must not carve the sketched region away; nothing here exists to be read.
    model = SkedNerfactoModelConfig(sketches=tmp_path / "no-sketches", prompt="")
    with pytest.raises(SkedOptionError, match="To carve the sketched region away, leave out --prompt"):
        SkedPipelineConfig(model=model).setup(device="cpu")


def test_a_prompt_given_to_guidance_without_prompts_is_warned_about():
    with pytest.warns(SkedOptionWarning, match=r"--prompt 'a hat' is ignored.*guidance:reference"):
        check_guidance(guidance_config("reference"), "a hat")


def test_a_long_prompt_is_cut_with_a_warning_and_keeps_its_view_suffixes(tiny_sd):
    from transformers import CLIPTokenizer

    from sked_ns.guidance.stable_diffusion import view_prompt_tokens

    tokenizer = CLIPTokenizer.from_pretrained(str(tiny_sd), subfolder="tokenizer")
    assert tokenizer.model_max_length == 77  # the tiny tokenizer has one token per character
    suffixes = {"front": ", front view", "overhead": ", overhead view"}
    short = view_prompt_tokens(tokenizer, "a red hat", suffixes)
    assert short["front"] == tokenizer("a red hat, front view", padding="max_length", max_length=77).input_ids
    # 82 tokens: cut at 77 as before, every view prompt would lose its whole suffix and all would be the same.
    prompt = "a tall red felt chef hat with golden stripes, a feather and tiny bells on its wide brim, shiny and new"
    with pytest.warns(SkedOptionWarning, match=r"--prompt is 82 tokens.*reads 77"):
        long = view_prompt_tokens(tokenizer, prompt, suffixes)
    for key, suffix in suffixes.items():
        assert len(long[key]) == 77 and tokenizer.decode(long[key], skip_special_tokens=True).endswith(suffix[2:])
    guidance = _guidance(tiny_sd)
    with pytest.warns(SkedOptionWarning, match="82 tokens"):
        guidance.prepare(prompt, "cpu", {})
    assert not torch.equal(guidance.embeddings["front"], guidance.embeddings["back"])


@pytest.mark.parametrize("scale", [0.0, -7.5, 0.5, float("nan"), float("inf")])
def test_an_impossible_guidance_scale_is_refused(scale):
    with pytest.raises(SkedOptionError, match=r"--pipeline.model.guidance.guidance-scale .*>= 1"):
        StableDiffusionGuidanceConfig(guidance_scale=scale).check()


def test_a_huge_guidance_scale_is_warned_about():
    with pytest.warns(SkedOptionWarning, match=r"guidance-scale 1e\+06.*100"):
        StableDiffusionGuidanceConfig(guidance_scale=1e6).check()  # its loss stays finite: see above
    StableDiffusionGuidanceConfig(guidance_scale=1.0).check()  # 1 is legal: the conditional prediction alone


@pytest.mark.parametrize("settings, flag", [
    ({"t_range": (0.0, 0.5)}, "t-range"), ({"t_range": (0.5, 0.2)}, "t-range"), ({"t_range": (0.02, 1.5)}, "t-range"),
    ({"t_range": (0.02, float("nan"))}, "t-range"), ({"weight": -1.0}, "weight"), ({"image_size": 0}, "image-size"),
])
def test_impossible_guidance_numbers_are_refused(settings, flag):
    with pytest.raises(SkedOptionError, match=rf"--pipeline.model.guidance.{flag} "):
        StableDiffusionGuidanceConfig(**settings).check()


def test_a_zero_sds_weight_is_warned_about():
    with pytest.warns(SkedOptionWarning, match=r"guidance.weight 0"):
        StableDiffusionGuidanceConfig(weight=0.0).check()


def test_the_last_timestep_fraction_1_stays_in_the_schedule(tiny_sd):
    guidance, _ = _stubbed(tiny_sd, t_range=(0.99, 1.0))
    for step in range(40):
        guidance(_view(size=8), step)
    assert max(int(call["t"].max()) for call in guidance._unet_forward.calls) == 999


@pytest.mark.parametrize("model", ["./missing-sd", "/no/such/sd", "~/no-such-sd-folder", "models/sd/v1", "models/sd"])
def test_a_missing_local_folder_is_not_taken_for_a_hub_id(tmp_path, monkeypatch, model):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "models").mkdir()  # "models/sd" exists in part: a path, not the hub id org/name
    config = StableDiffusionGuidanceConfig(model=model)
    with pytest.raises(SkedOptionError, match=r"--pipeline.model.guidance.model .*does not exist"):
        config.check()
    with pytest.raises(DiffusionWeightsMissing, match="does not exist"):
        config.setup().prepare("a red hat", "cpu", {})


def test_a_hub_id_is_still_a_hub_id(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    StableDiffusionGuidanceConfig(model="CompVis/stable-diffusion-v1-4").check()


def test_vae_checkpointing_gives_the_same_gradients_through_the_encoder(tiny_sd):
    """--pipeline.model.guidance.vae-checkpointing recomputes the encoder's activations in the backward pass: the
    render's gradient must not change (same noise draw)."""
    grads = []
    for checkpointing in (False, True):
        guidance = _guidance(tiny_sd, vae_checkpointing=checkpointing)
        guidance.prepare("a red hat", "cpu", {})
        assert guidance.vae.encoder.gradient_checkpointing is checkpointing
        image = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0)).requires_grad_()
        torch.manual_seed(1)
        guidance.encode(image).square().sum().backward()
        grads.append(image.grad)
    assert grads[0].abs().max() > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-5, atol=1e-7)
