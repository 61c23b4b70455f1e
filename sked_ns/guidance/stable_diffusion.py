"""Score distillation (DreamFusion) through a diffusers Stable Diffusion checkpoint.

Loads any SD 1.x/2.x diffusers checkpoint by hub id or local folder: noise-predicting ones
(SD 1.x, 2.x base 512) and v-predicting ones (SD 2.x 768), whose output is turned into the
noise prediction SDS needs. The weights are read only from this machine (a folder, or the hub cache that
`hf download` fills), online too: an edit checks them before it writes anything and never downloads during a
run, and missing ones are one line with the command that fetches them. Only what the loop uses reaches the
device: the UNet and the VAE encoder; the text encoder is freed once the (directional) prompt
embeddings exist, and the VAE decoder is dropped before the VAE moves (loaded again only when
an image is decoded). The diffusion model may run on its own device (`device`).
"""

from __future__ import annotations

import gc
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Dict, List, Literal, Optional, Tuple, Type, get_args

import torch
import torch.nn.functional as F
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError, SkedUserError, UsualRange, is_number, refuse, warn_option
from sked_ns.guidance.base import VIEW_DIRECTIONS, Guidance, GuidanceConfig, RenderedView
from sked_ns.guidance.hub import download_command, hub_cli

SdsWeighting = Literal["authors", "dreamfusion"]
SDS_WEIGHTINGS = get_args(SdsWeighting)
PREDICTION_TYPES = ("epsilon", "v_prediction")
"""What the UNet may predict (its scheduler's `prediction_type`): the noise (SD 1.x, 2.x base) or v (SD 2.x 768)."""
FLAGS = "--pipeline.model.guidance."
MAX_GUIDANCE_SCALE = 200.0
"""Above this the SDS loss explodes quadratically (1e6 gives 2e11): DreamFusion and SKED use 100."""
DIFFUSERS_WEIGHTS = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin",
                     "diffusion_pytorch_model.safetensors.index.json", "diffusion_pytorch_model.bin.index.json")
TRANSFORMERS_WEIGHTS = ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json",
                        "pytorch_model.bin.index.json")
PARTS: Dict[str, Tuple[Tuple[str, ...], ...]] = {
    "scheduler": (("scheduler_config.json",),),
    "tokenizer": (("vocab.json",), ("merges.txt",)),
    "text_encoder": (("config.json",), TRANSFORMERS_WEIGHTS),
    "unet": (("config.json",), DIFFUSERS_WEIGHTS),
    "vae": (("config.json",), DIFFUSERS_WEIGHTS),
}
"""What score distillation reads of a diffusers checkpoint, per subfolder: each entry one of these file names."""


class DiffusionWeightsMissing(SkedFileNotFoundError):
    """The diffusion model's weights are not available where we may look."""


def noise_prediction(output: Tensor, noisy: Tensor, alpha_bar: Tensor, prediction_type: str) -> Tensor:
    """The UNet's output as the noise it implies: v = sqrt(a) eps - sqrt(1 - a) x_0 gives eps = sqrt(a) v + sqrt(1 - a) x_t."""
    if prediction_type == "epsilon":
        return output
    if prediction_type == "v_prediction":
        return alpha_bar.sqrt() * output + (1 - alpha_bar).sqrt() * noisy
    raise ValueError(f"the UNet predicts {prediction_type!r}; score distillation supports {PREDICTION_TYPES}.")


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
    usual_ranges: ClassVar[Dict[str, UsualRange]] = {
        "guidance_scale": UsualRange(1.0, MAX_GUIDANCE_SCALE, "", "the SDS gradient grows with the scale (its loss "
                                     "with the square), so it swamps every other loss; DreamFusion and SKED use 100"),
        # The default loss weights are tuned against L_SDS weighted 1.
        "weight": UsualRange(1e-6, 100.0, "score distillation barely pulls, so nearly nothing but L_sil shapes the "
                             "sketched region; 0 turns it off", "the SDS gradient drowns L_sil and L_pres, whose "
                             "default weights are tuned against weight 1"),
        "image_size": UsualRange(8, 1024, "SD's latent is an eighth of the image's side, so it holds less than one "
                                 "cell", "larger than SD 1.x and 2.x were trained at (512, 768): each step costs the "
                                 "square of the size in VAE and UNet work, for detail SD cannot give"),
    }
    model: str = "CompVis/stable-diffusion-v1-4"
    """Hub id (org/name) or local folder of a diffusers Stable Diffusion checkpoint: SD 1.x, 2.x base (512 px)
    or 2.x 768 px (v-prediction; then --pipeline.model.guidance.image-size 768)."""
    local_files_only: bool = False
    """Kept for saved configs: the weights are always read from local files (a folder, or the hub cache)."""
    guidance_scale: float = 100.0
    """Classifier-free guidance scale, >= 1 (1 = the text-conditioned prediction alone; DreamFusion uses 100)."""
    t_range: Tuple[float, float] = (0.02, 0.98)
    """Diffusion timesteps sampled, as fractions of the schedule in (0, 1], smallest first (t in [20, 980] of 1000)."""
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
    vae_checkpointing: bool = False
    """Recompute the VAE encoder's activations during the backward pass instead of keeping them from the forward:
    less memory for the encode's backward (the largest activations of the SD side at 512 px), more time."""
    weight: float = 1.0
    """Multiplier of L_SDS."""
    device: Optional[str] = None
    """Where the diffusion model runs, e.g. cuda:1 when one card cannot hold both it and the NeRF (default: the
    edit's device). Renders go there and the SDS gradient comes back."""

    def check(self) -> None:
        problems = []
        scale = self.guidance_scale
        if not (is_number(scale) and scale >= 1):
            problems.append(f"{FLAGS}guidance-scale {scale!r}: must be a finite number >= 1 (1 = the text-conditioned "
                            "prediction alone; below 1 the prompt counts less, 0 ignores it and a negative scale pushes "
                            "away from it). DreamFusion and SKED use 100.")
        t_range = tuple(self.t_range)
        if not (len(t_range) == 2 and all(map(is_number, t_range)) and 0 < t_range[0] <= t_range[1] <= 1):
            problems.append(f"{FLAGS}t-range {' '.join(map(str, self.t_range))}: must be two fractions of the diffusion "
                            "schedule in (0, 1], smallest first (default 0.02 0.98).")
        if not (is_number(self.weight) and self.weight >= 0):
            problems.append(f"{FLAGS}weight {self.weight!r}: a loss weight must be a finite number >= 0.")
        if not (isinstance(self.image_size, int) and self.image_size > 0):
            problems.append(f"{FLAGS}image-size {self.image_size!r}: must be a whole number of pixels > 0 (SD's 512).")
        problems += _model_problems(self.model) + _device_problems(self.device)
        refuse(problems)
        super().check()
        if self.weight == 0:
            warn_option(f"{FLAGS}weight 0: score distillation is off, so nothing but L_sil shapes the sketched region.")

    def check_available(self) -> None:
        """The checkpoint's files are on this machine (a local folder, or the hub cache), without loading them or
        contacting the hub, whether or not the hub is reachable: a download at the first step would come after the
        run folder, the config and the viewer."""
        check_checkpoint_folder(checkpoint_folder(self.model), self.model)


def looks_like_path(source: str) -> bool:
    """A folder, not a hub id: it starts with / . ~, has more than one '/', or its first part exists here."""
    parts = source.replace("\\", "/").split("/")
    return source.startswith(("/", ".", "~", "\\")) or len(parts) > 2 or Path(parts[0]).expanduser().exists()


def _model_problems(source: str) -> List[str]:
    local = Path(source).expanduser()
    if looks_like_path(source) and not local.is_dir():
        what = "is a file, not a folder" if local.exists() else "does not exist"
        return [f"{FLAGS}model {source}: the folder {local.resolve()} {what}. Pass the folder holding a diffusers "
                "Stable Diffusion checkpoint (unet/, vae/, text_encoder/, tokenizer/, scheduler/), or a hub id such "
                "as CompVis/stable-diffusion-v1-4."]
    return []


def _device_problems(device: Optional[str]) -> List[str]:
    if device is None:
        return []
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError):
        return [f"{FLAGS}device {device!r}: not a torch device; pass e.g. cuda:1, or leave it out for the edit's."]
    if parsed.type == "cuda" and (parsed.index or 0) >= torch.cuda.device_count():
        return [f"{FLAGS}device {device}: this machine has {torch.cuda.device_count()} CUDA device(s); pass one of "
                "them, or leave it out for the edit's."]
    return []


def view_prompt_tokens(tokenizer, prompt: str, suffixes: Dict[str, str]) -> Dict[str, List[int]]:
    """Token ids, padded, of the prompt plus each suffix; an over-long prompt is cut so that every suffix still fits."""
    room = tokenizer.model_max_length - 2  # start and end tokens
    words = tokenizer(prompt, add_special_tokens=False).input_ids
    endings = {key: tokenizer(suffix, add_special_tokens=False).input_ids for key, suffix in suffixes.items()}
    kept = room - max(map(len, endings.values()))
    if len(words) > kept:
        # Cut from the prompt, not the suffix: cut suffixes would make the view prompts identical.
        warn_option(f"--prompt is {len(words)} tokens, but the text encoder reads {tokenizer.model_max_length} with its start and "
             f"end tokens and the view suffix (up to {room - kept}): only its first {kept} are used "
             f"(\"{tokenizer.decode(words[:kept])}\"). Shorten it.")
        words = words[:kept]
    tokens = {}
    for key, ending in endings.items():
        ids = [tokenizer.bos_token_id] + words + ending + [tokenizer.eos_token_id]
        tokens[key] = ids + [tokenizer.pad_token_id] * (tokenizer.model_max_length - len(ids))
    return tokens


def how_to_get_weights(source: str) -> str:
    return (f"Download it once where the hub is reachable: `{download_command(source)}` fills the cache it is read "
            f"from (or `{download_command(source, '/path/to/sd')}`, then `pipeline.model.guidance:stable-diffusion "
            f"{FLAGS}model /path/to/sd`). Without weights, use `pipeline.model.guidance:reference`.")


def checkpoint_folder(source: str) -> Path:
    """The folder `from_pretrained` reads `source` from: itself, or the hub cache's snapshot of that id, found
    without contacting the hub; a hub id not cached is refused with the command that downloads it."""
    for problem in _model_problems(source):
        raise DiffusionWeightsMissing(problem)
    local = Path(source).expanduser()
    if local.is_dir():
        return local
    from huggingface_hub import constants, snapshot_download

    try:
        return Path(snapshot_download(source, local_files_only=True))
    except Exception:  # not cached, or not a hub id at all (huggingface_hub raises a dozen kinds)
        raise DiffusionWeightsMissing(f"{FLAGS}model {source}: not on this machine (no such folder, and not in the "
                                      f"Hugging Face cache {constants.HF_HUB_CACHE}); an edit reads its weights from "
                                      f"here and never downloads them. {how_to_get_weights(source)}") from None


def check_checkpoint_folder(folder: Path, source: str) -> None:
    """Refuse a diffusers checkpoint folder lacking a file score distillation reads, or one whose UNet predicts what
    SDS cannot use (read from its scheduler's config, not its weights)."""
    where = f"{FLAGS}model {source}" + ("" if Path(source).expanduser() == folder else f" (cached in {folder})")
    missing = [f"{part}/{' or '.join(names)}" for part, needs in PARTS.items() for names in needs
               if not any((folder / part / name).is_file() for name in names)]
    if missing:
        raise DiffusionWeightsMissing(
            f"{where}: no {', '.join(missing)}. A diffusers Stable Diffusion checkpoint holds unet/, vae/, "
            f"text_encoder/, tokenizer/ and scheduler/ (as `save_pretrained` or `{hub_cli()} download` write "
            f"them). {how_to_get_weights(source)}")
    config_path = folder / "scheduler" / "scheduler_config.json"
    try:
        prediction_type = json.loads(config_path.read_text()).get("prediction_type", "epsilon")
    except (OSError, ValueError, AttributeError) as error:
        raise SkedUserError(f"{where}: {config_path} is not a readable scheduler config ({error}).") from error
    if prediction_type not in PREDICTION_TYPES:
        raise SkedUserError(f"{where}: its UNet predicts {prediction_type!r} (scheduler/scheduler_config.json); score "
                            f"distillation supports {PREDICTION_TYPES}: SD 1.x, 2.x base and 2.x 768 checkpoints.")


class StableDiffusionGuidance(Guidance):
    config: StableDiffusionGuidanceConfig

    def _load(self, cls, subfolder: str, **kwargs):
        source = self.config.model
        local = Path(source).expanduser()
        for problem in _model_problems(source):  # a mistyped folder is not a hub id
            raise DiffusionWeightsMissing(problem)
        if local.exists() and not (local / subfolder).is_dir():
            # Checked here: some loaders quietly build a default object from a missing folder.
            raise DiffusionWeightsMissing(
                f"{local}: no '{subfolder}/' here. A diffusers Stable Diffusion folder holds unet/, vae/, "
                f"text_encoder/, tokenizer/ and scheduler/ (as `save_pretrained` or `{hub_cli()} download` "
                "write them)."
            )
        try:
            if local.exists():
                return cls.from_pretrained(str(local), subfolder=subfolder, **kwargs)
            # Checked in the cache before the edit wrote anything: read there, with no request to the hub.
            return cls.from_pretrained(source, subfolder=subfolder, local_files_only=True, **kwargs)
        except (OSError, ValueError) as error:
            where = f"the folder {local}" if local.exists() else f"the hub id '{source}'"
            detail = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise DiffusionWeightsMissing(
                f"{FLAGS}model {source}: cannot load the diffusion model's '{subfolder}' from {where} "
                f"({type(error).__name__}: {detail}). {how_to_get_weights(source)}"
            ) from error

    def weights_available(self) -> bool:
        """Whether every file of the checkpoint can be read here without downloading."""
        try:
            check_checkpoint_folder(checkpoint_folder(self.config.model), self.config.model)
            return True
        except SkedUserError:
            return False

    def prepare(self, prompt: Optional[str], device: str, context: Dict) -> None:
        if not prompt or not prompt.strip():
            raise SkedUserError("Score distillation needs a text prompt: pass --prompt \"...\" (to carve the sketched "
                             "region away instead, leave out --prompt).")
        sds_weight(torch.zeros(1), self.config.weighting)  # a bad weighting fails before any weights load
        from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        self.device = torch.device(self.config.device or device)
        self.dtype = torch.float16 if (self.device.type == "cuda" and self.config.half_precision) else torch.float32
        scheduler = self._load(DDPMScheduler, "scheduler")  # first: an unsupported checkpoint fails before the weights
        self.prediction_type = scheduler.config.prediction_type
        if self.prediction_type not in PREDICTION_TYPES:
            raise SkedUserError(f"{self.config.model}: its UNet predicts {self.prediction_type!r} (scheduler/"
                             f"scheduler_config.json); score distillation supports {PREDICTION_TYPES}: SD 1.x, 2.x base "
                             f"and 2.x 768 checkpoints ({FLAGS}model).")
        self.alphas_cumprod = scheduler.alphas_cumprod.to(self.device, torch.float32)
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.scheduler = scheduler
        self.embeddings = self._embed(prompt, self._load(CLIPTokenizer, "tokenizer"),
                                      self._load(CLIPTextModel, "text_encoder"))
        gc.collect()  # the text encoder is not needed again

        self.unet = self._load(UNet2DConditionModel, "unet", torch_dtype=self.dtype).to(self.device).eval()
        vae = self._load(AutoencoderKL, "vae", torch_dtype=self.dtype).eval()
        vae.decoder = None  # dropped before the move, so it never takes device memory (see `decode`)
        vae.post_quant_conv = None
        self.vae = vae.to(self.device)
        for module in (self.unet, self.vae):
            module.requires_grad_(False)
        if self.config.vae_checkpointing:
            self.vae.enable_gradient_checkpointing()  # same gradients (a test checks), activations recomputed
        self._unet_forward = self.unet.forward
        self._encode = self._posterior
        if self.config.compile and self.device.type == "cuda":
            self._unet_forward = torch.compile(self.unet.forward)
            self._encode = torch.compile(self._encode)

    def _embed(self, prompt: str, tokenizer, text_encoder) -> Dict[str, Tensor]:
        """Text embeddings of the prompt per view direction, and of "" (the unconditional one)."""
        directional = self.config.directional_prompts
        tokens = view_prompt_tokens(tokenizer, prompt, {d: f", {d} view" if directional else "" for d in VIEW_DIRECTIONS})
        tokens[""] = tokenizer("", padding="max_length", max_length=tokenizer.model_max_length).input_ids
        text_encoder = text_encoder.to(self.device)
        with torch.no_grad():
            embeddings = text_encoder(torch.tensor(list(tokens.values()), device=self.device))[0].to(self.dtype)
        return dict(zip(tokens.keys(), embeddings))

    def _posterior(self, image: Tensor) -> Tuple[Tensor, Tensor]:
        """Mean and standard deviation of the VAE's latent distribution (tensors only: compiles whole)."""
        posterior = self.vae.encode(image).latent_dist
        return posterior.mean, posterior.std

    def encode(self, image: Tensor) -> Tensor:
        """[0, 1] images -> scaled latents sampled from the VAE posterior; gradients flow through the encoder."""
        size = self.config.image_size
        image = F.interpolate(image.to(self.device), (size, size), mode="bilinear", align_corners=False)
        mean, std = self._encode((image * 2 - 1).to(self.dtype))
        # A sample, not the mean: the authors' code encodes with latent_dist.sample().
        latents = mean + std * torch.randn_like(mean)
        return latents.float() * float(self.vae.config.scaling_factor)

    def __call__(self, view: RenderedView, step: int) -> Dict[str, Tensor]:
        latents = self.encode(view.image)
        batch = latents.shape[0]
        low, high = (min(int(fraction * self.num_train_timesteps), self.num_train_timesteps - 1)
                     for fraction in self.config.t_range)
        t = torch.randint(low, high + 1, (batch,), device=self.device)
        with torch.no_grad():
            noise = torch.randn_like(latents)
            noisy = self.scheduler.add_noise(latents, noise, t.cpu()).to(self.dtype)
            conditional = self.embeddings[view.direction if self.config.directional_prompts else "front"]
            context = torch.stack([self.embeddings[""], conditional])[:, None].expand(2, batch, -1, -1).flatten(0, 1)
            predicted = self._unet_forward(torch.cat([noisy] * 2), torch.cat([t] * 2), encoder_hidden_states=context).sample
            unconditional, text = predicted.float().chunk(2)
            guided = unconditional + self.config.guidance_scale * (text - unconditional)
            alpha_bar = self.alphas_cumprod[t].view(-1, 1, 1, 1)
            # After guidance: the conversion is affine with the same x_t in both halves, so it commutes with it.
            guided = noise_prediction(guided, noisy.float(), alpha_bar, self.prediction_type)
            weight = sds_weight(alpha_bar, self.config.weighting)
            gradient = torch.nan_to_num(weight * (guided - noise), nan=0.0, posinf=0.0, neginf=0.0)
            target = latents - gradient
        # d loss / d latents = gradient, without back-propagating through the UNet.
        loss = 0.5 * F.mse_loss(latents, target.detach(), reduction="sum") / batch
        return {"sds_loss": (self.config.weight * loss).to(view.image.device)}  # autograd carries it across devices

    @torch.no_grad()
    def decode(self, latents: Tensor) -> Tensor:
        """Latents -> [0, 1] images; loads the decoder for this call only."""
        from diffusers import AutoencoderKL

        vae = self._load(AutoencoderKL, "vae", torch_dtype=self.dtype).to(self.device)
        images = vae.decode(latents.to(self.dtype) / float(vae.config.scaling_factor)).sample
        del vae
        return (images.float() / 2 + 0.5).clamp(0, 1)
