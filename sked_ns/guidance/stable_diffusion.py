"""Score distillation (DreamFusion) through a diffusers Stable Diffusion checkpoint.

Loads any SD 1.x/2.x diffusers checkpoint by hub id or local folder; offline
(`HF_HUB_OFFLINE=1`, or `local_files_only`) it reads only local files and says how to
provide missing weights. Only what the loop uses stays in memory: the UNet and the VAE
encoder; the text encoder is freed once the (directional) prompt embeddings exist, and
the VAE decoder is loaded only when an image is decoded.
"""

from __future__ import annotations

import gc
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Dict, Literal, Optional, Tuple, Type, get_args

import torch
import torch.nn.functional as F
from torch import Tensor

from sked_ns.guidance.base import Guidance, GuidanceConfig, RenderedView
from sked_ns.random_views import DIRECTIONS


SdsWeighting = Literal["authors", "dreamfusion"]
SDS_WEIGHTINGS = get_args(SdsWeighting)


class DiffusionWeightsMissing(FileNotFoundError):
    """The diffusion model's weights are not available where we may look."""


def sds_weight(alphas_cumprod: Tensor, weighting: str) -> Tensor:
    """w(t) of the SDS gradient w(t) (eps_hat - eps), from alpha_bar_t (see the config's `weighting`)."""
    if weighting == "authors":
        return alphas_cumprod.sqrt() * (1 - alphas_cumprod)
    if weighting == "dreamfusion":
        return 1 - alphas_cumprod
    raise ValueError(
        f"StableDiffusionGuidanceConfig.weighting: unknown SDS weighting {weighting!r}; use one of {SDS_WEIGHTINGS} "
        "(--pipeline.model.guidance.weighting)."
    )


@dataclass
class StableDiffusionGuidanceConfig(GuidanceConfig):
    _target: Type = field(default_factory=lambda: StableDiffusionGuidance)
    uses_prompt: ClassVar[bool] = True
    model: str = "CompVis/stable-diffusion-v1-4"
    """Hub id or local folder of a diffusers Stable Diffusion checkpoint."""
    local_files_only: bool = False
    """Never contact the hub (also implied by HF_HUB_OFFLINE=1)."""
    guidance_scale: float = 100.0
    """Classifier-free guidance scale (DreamFusion uses 100)."""
    t_range: Tuple[float, float] = (0.02, 0.98)
    """Diffusion timesteps sampled, as fractions of the schedule (t in [20, 980] of 1000)."""
    weighting: SdsWeighting = "authors"
    """w(t) in the SDS gradient w(t) (eps_hat - eps): "authors" = sqrt(alpha_bar_t) (1 - alpha_bar_t), the SKED
    code's, with which the default lambdas were tuned; "dreamfusion" = 1 - alpha_bar_t (with SD's schedule 2.6x the
    mean weight over t in [20, 980], 13x at t = 980)."""
    image_size: int = 512
    """Renders are resized to this before the VAE (SD's native 512)."""
    directional_prompts: bool = True
    """Append ', front view' etc. from the camera."""
    half_precision: bool = True
    """fp16 weights on CUDA (always fp32 on the CPU)."""
    compile: bool = True
    """torch.compile the UNet and VAE encoder on CUDA."""
    weight: float = 1.0
    """Multiplier of L_SDS."""


def _offline(config: StableDiffusionGuidanceConfig) -> bool:
    return config.local_files_only or os.environ.get("HF_HUB_OFFLINE", "0") not in ("", "0", "false", "False")


class StableDiffusionGuidance(Guidance):
    config: StableDiffusionGuidanceConfig

    def _load(self, cls, subfolder: str, **kwargs):
        source = self.config.model
        local = Path(source).expanduser()
        if local.exists() and not (local / subfolder).is_dir():
            # Checked here: some loaders quietly build a default object from a missing folder.
            raise DiffusionWeightsMissing(
                f"{local}: no '{subfolder}/' here. A diffusers Stable Diffusion folder holds unet/, vae/, "
                "text_encoder/, tokenizer/ and scheduler/ (as `save_pretrained` or `huggingface-cli download` "
                "write them)."
            )
        try:
            if local.exists():
                return cls.from_pretrained(str(local), subfolder=subfolder, **kwargs)
            return cls.from_pretrained(source, subfolder=subfolder, local_files_only=_offline(self.config), **kwargs)
        except (OSError, ValueError) as error:
            where = f"the folder {local}" if local.exists() else f"the hub id '{source}'"
            raise DiffusionWeightsMissing(
                f"Cannot load the diffusion model's '{subfolder}' from {where} ({type(error).__name__}: {error}). "
                "Provide the weights: download a diffusers Stable Diffusion checkpoint once where the hub is "
                f"reachable (`huggingface-cli download {source}` fills the cache read offline), or pass a local "
                "folder with `pipeline.model.guidance:stable-diffusion --pipeline.model.guidance.model "
                "/path/to/stable-diffusion`. Without weights, use `pipeline.model.guidance:reference`."
            ) from error

    def weights_available(self) -> bool:
        """Whether the checkpoint can be read here without downloading (its scheduler, as a probe)."""
        from diffusers import DDPMScheduler

        offline = self.config.local_files_only
        self.config.local_files_only = True
        try:
            self._load(DDPMScheduler, "scheduler")
            return True
        except DiffusionWeightsMissing:
            return False
        finally:
            self.config.local_files_only = offline

    def prepare(self, prompt: Optional[str], device: str, context: Dict) -> None:
        if not prompt or not prompt.strip():
            raise ValueError("Score distillation needs a text prompt: pass --prompt \"...\" (or carve with no guidance).")
        sds_weight(torch.zeros(1), self.config.weighting)  # a bad weighting fails before any weights load
        from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        self.device = torch.device(device)
        self.dtype = torch.float16 if (self.device.type == "cuda" and self.config.half_precision) else torch.float32
        tokenizer = self._load(CLIPTokenizer, "tokenizer")
        text_encoder = self._load(CLIPTextModel, "text_encoder").to(self.device)
        prompts = {"": ""}
        for direction in set(DIRECTIONS):
            prompts[direction] = f"{prompt}, {direction} view" if self.config.directional_prompts else prompt
        with torch.no_grad():
            tokens = tokenizer(
                list(prompts.values()), padding="max_length", max_length=tokenizer.model_max_length,
                truncation=True, return_tensors="pt",
            ).input_ids.to(self.device)
            embeddings = text_encoder(tokens)[0].to(self.dtype)
        self.embeddings = dict(zip(prompts.keys(), embeddings))  # "" is the unconditional one
        del text_encoder, tokenizer  # computed once: the text encoder is not needed again
        gc.collect()

        self.unet = self._load(UNet2DConditionModel, "unet", torch_dtype=self.dtype).to(self.device).eval()
        vae = self._load(AutoencoderKL, "vae", torch_dtype=self.dtype).to(self.device).eval()
        vae.decoder = None  # loaded again only to decode (see `decode`)
        vae.post_quant_conv = None
        self.vae = vae
        for module in (self.unet, self.vae):
            module.requires_grad_(False)
        scheduler = self._load(DDPMScheduler, "scheduler")
        self.alphas_cumprod = scheduler.alphas_cumprod.to(self.device, torch.float32)
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.scheduler = scheduler
        self._unet_forward = self.unet.forward
        self._encode = self._posterior
        if self.config.compile and self.device.type == "cuda":
            self._unet_forward = torch.compile(self.unet.forward)
            self._encode = torch.compile(self._encode)

    def _posterior(self, image: Tensor) -> Tuple[Tensor, Tensor]:
        """Mean and standard deviation of the VAE's latent distribution (tensors only: compiles whole)."""
        posterior = self.vae.encode(image).latent_dist
        return posterior.mean, posterior.std

    def encode(self, image: Tensor) -> Tensor:
        """[0, 1] images -> scaled latents sampled from the VAE posterior; gradients flow through the encoder."""
        size = self.config.image_size
        image = F.interpolate(image, (size, size), mode="bilinear", align_corners=False)
        mean, std = self._encode((image * 2 - 1).to(self.dtype))
        # A sample, not the mean: the authors' code encodes with latent_dist.sample().
        latents = mean + std * torch.randn_like(mean)
        return latents.float() * float(self.vae.config.scaling_factor)

    def __call__(self, view: RenderedView, step: int) -> Dict[str, Tensor]:
        latents = self.encode(view.image)
        batch = latents.shape[0]
        low, high = (int(fraction * self.num_train_timesteps) for fraction in self.config.t_range)
        t = torch.randint(low, high + 1, (batch,), device=self.device)
        with torch.no_grad():
            noise = torch.randn_like(latents)
            noisy = self.scheduler.add_noise(latents, noise, t.cpu()).to(self.dtype)
            conditional = self.embeddings[view.direction if self.config.directional_prompts else "front"]
            context = torch.stack([self.embeddings[""], conditional])[:, None].expand(2, batch, -1, -1).flatten(0, 1)
            predicted = self._unet_forward(torch.cat([noisy] * 2), torch.cat([t] * 2), encoder_hidden_states=context).sample
            unconditional, text = predicted.float().chunk(2)
            guided = unconditional + self.config.guidance_scale * (text - unconditional)
            weight = sds_weight(self.alphas_cumprod[t], self.config.weighting).view(-1, 1, 1, 1)
            gradient = torch.nan_to_num(weight * (guided - noise), nan=0.0, posinf=0.0, neginf=0.0)
            target = latents - gradient
        # d loss / d latents = gradient, without back-propagating through the UNet.
        loss = 0.5 * F.mse_loss(latents, target.detach(), reduction="sum") / batch
        return {"sds_loss": self.config.weight * loss}

    @torch.no_grad()
    def decode(self, latents: Tensor) -> Tensor:
        """Latents -> [0, 1] images; loads the decoder for this call only."""
        from diffusers import AutoencoderKL

        vae = self._load(AutoencoderKL, "vae", torch_dtype=self.dtype).to(self.device)
        images = vae.decode(latents.to(self.dtype) / float(vae.config.scaling_factor)).sample
        del vae
        return (images.float() / 2 + 0.5).clamp(0, 1)
