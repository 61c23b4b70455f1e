"""Where an SDS iteration's time goes: render, VAE encode, UNet, losses, backward; and peak memory.

    python benchmarks/sds_iteration.py                     # full-size SD v1.x architecture (needs a GPU)
    python benchmarks/sds_iteration.py --size tiny --iterations 3   # a smoke run anywhere

Runs a real `ns-train sked` edit with Stable Diffusion guidance at the default settings (random
view at 128 px, sketch views at 128 px) on the demo scene's tiny nerfacto base. The diffusion
model has SD v1.x's full architecture (UNet 860M, VAE, CLIP ViT-L text encoder) with RANDOM
weights, built here and saved like a real checkpoint: honest timings, meaningless images.
On CUDA the UNet and VAE encoder are compiled (the default) and fp16.

Reports the first iteration (compilation included), then the mean of the rest split by stage
(each stage timed between CUDA synchronisations, which costs a little), the unsynchronised
iteration time, the bare compiled SD cost (VAE encode + UNet on a fixed input, measured in the
same process under the edit's autocast) and their ratio, and peak memory. Writes benchmarks/results/sds_iteration.json.
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
from pathlib import Path

import harness
import numpy as np
import torch
from harness import StageTimer, sync


def build_random_stable_diffusion(folder: Path, size: str) -> Path:
    """SD v1.x's architecture (or a tiny one) with random weights, in diffusers' folder layout."""
    from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(0)
    full = size == "full"
    # A byte-level vocabulary: the prompt's tokens do not matter for timing.
    printable = [chr(c) for c in range(33, 127)]
    vocab = {t: i for i, t in enumerate(printable + [c + "</w>" for c in printable])}
    vocab["<|startoftext|>"], vocab["<|endoftext|>"] = len(vocab), len(vocab) + 1
    (folder / "tokenizer").mkdir(parents=True, exist_ok=True)
    (folder / "tokenizer" / "vocab.json").write_text(json.dumps(vocab))
    (folder / "tokenizer" / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(folder / "tokenizer" / "vocab.json"), str(folder / "tokenizer" / "merges.txt"),
                  model_max_length=77).save_pretrained(str(folder / "tokenizer"))
    hidden = 768 if full else 32
    CLIPTextModel(CLIPTextConfig(
        vocab_size=49408 if full else len(vocab), hidden_size=hidden, intermediate_size=3072 if full else 37,
        num_attention_heads=12 if full else 4, num_hidden_layers=12 if full else 2, max_position_embeddings=77,
        bos_token_id=vocab["<|startoftext|>"], eos_token_id=vocab["<|endoftext|>"], pad_token_id=vocab["<|endoftext|>"],
    )).save_pretrained(str(folder / "text_encoder"))
    if full:
        unet = UNet2DConditionModel(
            sample_size=64, in_channels=4, out_channels=4, layers_per_block=2, block_out_channels=(320, 640, 1280, 1280),
            down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3, cross_attention_dim=768, attention_head_dim=8,
        )
        vae = AutoencoderKL(
            in_channels=3, out_channels=3, down_block_types=("DownEncoderBlock2D",) * 4,
            up_block_types=("UpDecoderBlock2D",) * 4, block_out_channels=(128, 256, 512, 512), layers_per_block=2,
            latent_channels=4, sample_size=512,
        )
    else:
        unet = UNet2DConditionModel(
            sample_size=8, in_channels=4, out_channels=4, layers_per_block=1, block_out_channels=(32, 64),
            down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
            cross_attention_dim=hidden, attention_head_dim=8, norm_num_groups=32,
        )
        vae = AutoencoderKL(
            in_channels=3, out_channels=3, down_block_types=("DownEncoderBlock2D",) * 2,
            up_block_types=("UpDecoderBlock2D",) * 2, block_out_channels=(32, 64), latent_channels=4, norm_num_groups=32,
        )
    unet.save_pretrained(str(folder / "unet"))
    vae.save_pretrained(str(folder / "vae"))
    DDPMScheduler(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012,
                  beta_schedule="scaled_linear").save_pretrained(str(folder / "scheduler"))
    return folder


@contextmanager
def edit_autocast(trainer):
    """The autocast SkedTrainer.train_iteration runs the model under: nerfstudio's switch, at SKED's dtype."""
    from sked_ns.engine.trainer import default_autocast_dtype

    device_type = "cpu" if trainer.device.split(":")[0] in ("cpu", "mps") else trainer.device.split(":")[0]
    with default_autocast_dtype(device_type, trainer.autocast_dtype):
        with torch.autocast(device_type=device_type, enabled=trainer.mixed_precision):
            yield


def bare_sd_step(trainer, image: torch.Tensor) -> None:
    """The SD work every SDS iteration pays, on a fixed image: VAE encode forward + backward and the batch-2
    UNet, under the edit's autocast (another dtype would be another compiled graph: unlike things compared)."""
    guidance = trainer.pipeline.model.guidance
    context = torch.stack([guidance.embeddings[""], guidance.embeddings["front"]])
    with edit_autocast(trainer):
        latents = guidance.encode(image)
        t = torch.full((2,), 500, device=image.device)
        with torch.no_grad():
            guidance._unet_forward(torch.cat([latents.detach().to(guidance.dtype)] * 2), t, encoder_hidden_states=context)
    latents.sum().backward()  # outside autocast, as the edit's backward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=("full", "tiny"), default="full")
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--resolution", type=int, default=128, help="random-view and sketch-view render size")
    parser.add_argument("--image-size", type=int, default=512, help="SD input size (SD's native 512)")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "sds_iteration.json")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    harness.claim("sds_iteration.py", args.output, args.workdir)

    from sked_ns.demo.base import TinyNerfacto
    from sked_ns.engine.edit_run import edit_config

    device = "cuda" if torch.cuda.is_available() else "cpu"
    with harness.work_folder(args.workdir) as work:
        harness.demo_scene(work)
        base = harness.demo_base(work, "nerfacto", 300, TinyNerfacto())
        sd = build_random_stable_diffusion(work / f"sd-{args.size}", args.size)

        config = edit_config(base, work / "data", work / "sketches", work / "edits", prompt=harness.PROMPT,
                             guidance="stable-diffusion", iterations=args.iterations + 1,
                             guidance_resolution=args.resolution, silhouette_resolution=args.resolution,
                             device=device, steps_per_save=10**9)
        config.pipeline.model.guidance.model = str(sd)
        config.pipeline.model.guidance.image_size = args.image_size
        config.set_timestamp()
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        trainer.pipeline.prepare_guidance()
        model, guidance = trainer.pipeline.model, trainer.pipeline.model.guidance

        timer = StageTimer(device)
        timer.wrap(model, "_render", "render")
        timer.wrap(guidance, "_encode", "vae_encode")
        timer.wrap(guidance, "_unet_forward", "unet")
        if device == "cuda":
            torch.cuda.reset_peak_memory_stats()
        (first,) = harness.timed_steps(trainer, [0], device)

        # Split, with synchronisations.
        timer.totals.clear()
        iteration_totals = harness.timed_steps(trainer, range(1, args.iterations + 1), device)
        split = {name: 1000 * value / args.iterations for name, value in timer.totals.items()}
        split["losses_and_backward_and_step"] = 1000 * float(np.mean(iteration_totals)) - sum(split.values())

        # Without synchronisations: the real iteration time.
        timer.enabled = False
        start = time.perf_counter()
        for step in range(args.iterations + 1, 2 * args.iterations + 1):
            trainer.train_iteration(step)
        sync(device)
        iteration_ms = 1000 * (time.perf_counter() - start) / args.iterations

        # The bare (compiled) SD cost on a fixed input, same process and autocast: VAE encode fwd+bwd + UNet batch 2.
        image = torch.rand(1, 3, args.resolution, args.resolution, device=device, requires_grad=True)
        bare = harness.timed_calls(lambda: bare_sd_step(trainer, image), args.iterations, device)
        bare_ms = 1000 * float(np.mean(bare))
        peak = torch.cuda.max_memory_allocated() / 2**30 if device == "cuda" else harness.peak_rss_gb()

    environment = harness.environment(device)
    result = {
        "environment": environment, "device": device,
        "diffusion_model": f"SD v1.x architecture ({args.size}), random weights",
        "precision": "fp16, compiled UNet and VAE encoder" if device == "cuda" else "fp32, eager",
        "resolution": args.resolution, "iterations": args.iterations,
        "first_iteration_s (compilation included)": first,
        "split_ms (synchronised)": split,
        "iteration_ms": iteration_ms,
        "bare_sd_ms (VAE encode fwd+bwd + UNet batch 2)": bare_ms,
        "iteration_over_bare_sd": iteration_ms / bare_ms,
        "peak_memory_gb": peak,
        "projected_10k_iterations_min": (first + 10_000 * iteration_ms / 1000) / 60,
    }
    harness.write_results(args.output, result)
    print(f"{environment['device']}, {environment['torch_threads']} threads; {result['diffusion_model']}; "
          f"{result['precision']}")
    harness.report(harness.markdown_table(["stage", "ms"], [[name, f"{value:.1f}"] for name, value in split.items()])
                   + f"\niteration {iteration_ms:.1f} ms, bare SD {bare_ms:.1f} ms (x{iteration_ms / bare_ms:.2f}), "
                   f"first {first:.1f} s, peak {peak:.2f} GB, 10k iterations "
                   f"~{result['projected_10k_iterations_min']:.1f} min", args.output)


if __name__ == "__main__":
    main()
