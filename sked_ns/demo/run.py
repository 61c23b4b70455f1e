"""`sked-demo`: a real SKED edit of the embedded demo scene, end to end (on the CPU, or a GPU where there is one).

1. writes the demo dataset (an analytic sphere) and fits a tiny nerfacto base to it, or with
   `--base splatfacto` a Gaussian-splat base, saved exactly as `ns-train nerfacto` (`splatfacto`)
   saves a run;
2. writes two sketches of a hat on top and renders their preservation-weight field;
3. runs `ns-train sked` on it: reference guidance (renders of the sphere with its hat) when
   no Stable Diffusion weights are available, text-prompt guidance when they are;
4. renders the sketch views before and after, and reports the paper's metrics.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from sked_ns.demo import BASES
from sked_ns.demo.base import build_demo_base
from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.errors import SkedFileExistsError, SkedUserError, check_writable_folder
from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_outside
from sked_ns.evaluation.novel_views import eval_split_views, evaluate_novel_views
from sked_ns.method.edit_box import compute_edit_box
from sked_ns.method.preservation import SketchDistanceField
from sked_ns.run_lock import hold
from sked_ns.sketches.sketch_set import DataparserTransform, SketchSet, load_sketch_set, save_sketch_set

MARKER = ".sked-demo"  # marks a folder the demo made, so a rerun may replace it


def overlay(rgb: np.ndarray, weight: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Tint the surface red where it may change (w near 0), leave it as is where it is kept."""
    editable = (1.0 - weight)[..., None] * hit[..., None]
    return rgb * (1 - 0.7 * editable) + np.array([1.0, 0.1, 0.1]) * 0.7 * editable


def weight_slice(field: SketchDistanceField, transform: DataparserTransform, beta: float, size: int) -> np.ndarray:
    """Heat map of w on the vertical plane through the object facing the first sketch view."""
    axis = np.linspace(-1.0, 1.0, size)
    x, z = np.meshgrid(axis, axis[::-1], indexing="xy")
    points = torch.tensor(np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3), dtype=torch.float32)
    weight = field.preservation_weight(transform.points_to_model(points), beta).reshape(size, size).numpy()
    heat = cv2.applyColorMap((weight * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1] / 255.0
    inside = (demo_scene.sphere_sdf(points) < 0).reshape(size, size).numpy()
    heat[inside] = heat[inside] * 0.6 + 0.4  # outline the base object
    return heat


def preservation_figure(sketches: SketchSet, transform: DataparserTransform, beta: float, size: int, path: Path) -> dict:
    """sketch view 1 with its mask | a new view, red = may change | w on a vertical slice."""
    model_sketches = sketches.in_model_frame(transform)
    field = SketchDistanceField(model_sketches.views)
    edit_box = compute_edit_box(model_sketches.views, scene_box=np.array([[-1.0] * 3, [1.0] * 3]))
    render = demo_scene.render(demo_scene.edited_sdf, demo_scene.orbit_pose(60.0, 25.0, 2.4), 1.2 * size, size, size)
    weight = field.preservation_weight(transform.points_to_model(render["points"]), beta)
    weight = torch.where(render["hit"], weight, torch.ones_like(weight)).numpy()
    hit = render["hit"].numpy()
    on_hat = (demo_scene.hat_sdf(render["points"]) < 2e-3).numpy() & hit
    first = sketches.views[0]
    first_render = demo_scene.render(demo_scene.edited_sdf, first.camera_to_world, first.fl_x, first.width, first.height)
    first_panel = overlay(first_render["rgb"].numpy(), 1.0 - first.mask.astype(float), np.ones_like(first.mask))
    panels = [
        cv2.resize(first_panel, (size, size), interpolation=cv2.INTER_NEAREST),
        overlay(render["rgb"].numpy(), weight, hit),
        weight_slice(field, transform, beta, size),
    ]
    _write_png(path, np.concatenate(panels, axis=1))
    return {
        "edit_box_model_frame": {"min": edit_box.min.tolist(), "max": edit_box.max.tolist()},
        "mean_weight_on_hat": float(weight[on_hat].mean()),
        "mean_weight_on_sphere": float(weight[hit & ~on_hat].mean()),
    }


def _write_png(path: Path, image: np.ndarray) -> None:
    cv2.imwrite(str(path), (image.clip(0, 1) * 255).round().astype(np.uint8)[..., ::-1])


def choose_guidance(prompt: Optional[str], model: str) -> str:
    """Stable Diffusion when a prompt is given and its weights load; else the reference target."""
    if not prompt:
        return "reference"
    from sked_ns.guidance.stable_diffusion import StableDiffusionGuidanceConfig

    if StableDiffusionGuidanceConfig(model=model).setup().weights_available():
        return "stable-diffusion"
    print(f"No Stable Diffusion weights for '{model}' here: using reference guidance (renders of the "
          "known target scene) instead of the prompt.")
    return "reference"




def fit_base(kind: str, data: Path, folder: Path, base_steps: Optional[int], splat_fit=None) -> Path:
    """The demo base: a tiny nerfacto fitted to the analytic scene (600 steps unless given), or splatfacto fitted
    to the photos (`splat_fit`, a SplatFit: its defaults unless given)."""
    if kind == "splatfacto":
        from sked_ns.demo.splat_base import SplatFit, fit_demo_splat_base, last_fit

        run_dir = fit_demo_splat_base(data, folder, splat_fit or SplatFit())
        print(f"splatfacto base: {last_fit['gaussians']} Gaussians, PSNR {last_fit['train_psnr']:.1f} dB on its "
              f"photos, {last_fit['eval_psnr']:.1f} dB on the held-out ones")
        return run_dir
    return build_demo_base(data, folder, steps=600 if base_steps is None else base_steps)


def check_demo_settings(output: Path, beta: float, size: int, iterations: int, base_steps: Optional[int],
                        prompt: Optional[str], diffusion_model: str, device: str, base: str) -> None:
    """Every setting, named by its flag, before anything is written; last, that --output can take the demo."""
    from sked_ns.guidance.stable_diffusion import _model_problems

    if not (isinstance(beta, (int, float)) and math.isfinite(beta) and beta > 0):
        raise SkedUserError(f"--beta {beta!r}: the preservation falloff, a finite number of image widths > 0 "
                            "(default 0.025).")
    for flag, value in (("--size", size), ("--iterations", iterations), ("base_steps", base_steps)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise SkedUserError(f"{flag} {value!r}: must be a whole number >= 1.")
    if base not in BASES:
        raise SkedUserError(f"--base {base}: no demo base {base!r}; choose one of {', '.join(BASES)}.")
    if prompt is not None and not prompt.strip():
        raise SkedUserError(f"--prompt {prompt!r} is empty: say what should be in the sketches, or leave --prompt out "
                            "for the reference guidance.")
    if prompt is not None:
        for problem in _model_problems(diffusion_model):
            raise SkedUserError(problem.replace("--pipeline.model.guidance.model", "--diffusion-model", 1))
    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise SkedUserError(f"--device {device!r}: not a torch device; pass cpu or cuda.") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise SkedUserError(f"--device {device}: torch sees no CUDA device here; pass --device cpu.")
    output = Path(output).resolve()
    if output.exists() and not output.is_dir():
        raise SkedFileExistsError(f"--output {output}: a file, not a folder; choose another --output.")
    if output.exists() and any(output.iterdir()) and not (output / MARKER).exists():
        raise SkedFileExistsError(f"--output {output}: exists and was not made by sked-demo; choose another "
                                  "--output.")
    check_writable_folder(output, "--output")


def run(output: Path, beta: float = 0.025, size: int = 128, iterations: int = 100, base_steps: Optional[int] = None,
        prompt: Optional[str] = None, diffusion_model: str = "CompVis/stable-diffusion-v1-4", device: str = "cpu",
        base: str = "nerfacto", splat_fit=None) -> dict:
    from sked_ns.engine.edit_run import edit_config, run_edit
    from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at, resized_mask

    check_demo_settings(output, beta, size, iterations, base_steps, prompt, diffusion_model, device, base)
    output = Path(output).resolve()  # absolute paths in config.yml: ns-* commands work from anywhere
    hold(output, "Wait for it to end, or choose another --output.")  # this process's alone until it ends
    (output / MARKER).touch()

    data = output / "data"
    demo_scene.write_demo_dataset(data)
    base_run = fit_base(base, data, output / "base", base_steps, splat_fit)
    save_sketch_set(demo_scene.demo_sketch_set(), output / "sketches", overwrite=True)
    sketches = load_sketch_set(output / "sketches")  # the user's path: from disk
    transform = DataparserTransform.from_json(base_run / "dataparser_transforms.json")
    summary = {"beta": beta, **preservation_figure(sketches, transform, beta, size, output / "preservation_weights.png")}

    guidance = choose_guidance(prompt, diffusion_model)
    config = edit_config(base_run / "nerfstudio_models", data, output / "sketches", output / "edits",
                         prompt=prompt, guidance=guidance, iterations=iterations, device=device)
    config.pipeline.model.beta = beta
    if guidance == "stable-diffusion":
        config.pipeline.model.guidance.model = diffusion_model
    trainer = run_edit(config)

    edit_model = trainer.pipeline.model
    if base == "splatfacto":
        # nerfstudio's splatfacto renders with gsplat's CUDA kernels only: the edit's frozen copy of the base
        # (exactly its Gaussians) renders it here.
        render_base = lambda view: render_base_at(edit_model, view, size)  # noqa: E731
    else:
        base_model = load_pipeline(base_run, device).model
        render_base = lambda view: render_at(base_model, view, size)  # noqa: E731
    rows, views = [], []
    for view in sketches.in_model_frame(transform).views:
        before, after, mask = render_base(view), render_at(edit_model, view, size), resized_mask(view, size)
        views.append({"ios_base": intersection_over_sketch(before["accumulation"], mask),
                      "ios_edit": intersection_over_sketch(after["accumulation"], mask),
                      "psnr_outside": psnr_outside(after["rgb"], before["rgb"], mask)})
        outline = cv2.dilate(mask.numpy().astype(np.uint8), np.ones((3, 3), np.uint8)) - mask.numpy().astype(np.uint8)
        sketched = after["rgb"].numpy().copy()
        sketched[outline > 0] = [1.0, 0.1, 0.1]
        rows.append(np.concatenate([before["rgb"].numpy(), after["rgb"].numpy(), sketched], axis=1))
    _write_png(output / "before_after.png", np.concatenate(rows, axis=0))
    # The edit from the base dataset's evaluation cameras, not only from the sketch views.
    novel = evaluate_novel_views(edit_model, eval_split_views(trainer.pipeline, size, (1.0, 1.0, 1.0)))
    _write_png(output / "novel_views.png", np.concatenate([row.numpy() for row in novel.pop("rows")], axis=0))
    summary["novel_views"] = novel
    summary.update(
        base=base, guidance=guidance, iterations=iterations, edit_run=str(trainer.base_dir), views=views,
        ios_mean=float(np.mean([v["ios_edit"] for v in views])),
        psnr_outside_mean=float(np.mean([v["psnr_outside"] for v in views])),
        images=[str(output / "preservation_weights.png"), str(output / "before_after.png"),
                str(output / "novel_views.png")],
    )
    (output / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def report(summary: dict) -> str:
    """What sked-demo prints when it ends."""
    from sked_ns.evaluation.evaluate import novel_summary

    return (
        f"\nmean preservation weight on the hat {summary['mean_weight_on_hat']:.3f} (free to change), "
        f"on the sphere {summary['mean_weight_on_sphere']:.3f} (kept)\n"
        f"edit ({summary['guidance']} guidance, {summary['iterations']} iterations): Intersection-over-Sketch "
        f"{summary['ios_mean']:.2f} (base: {np.mean([v['ios_base'] for v in summary['views']]):.2f}), "
        f"PSNR outside the sketches {summary['psnr_outside_mean']:.1f} dB\n"
        f"{novel_summary({**summary['novel_views'], 'cameras': 'the demo dataset eval split'})}\n"
        f"wrote {summary['images'][0]}, {summary['images'][1]} (before | after | after with the sketch outline) and "
        f"{summary['images'][2]} (base | edit | may-change region dimmed, new opacity in magenta)\n"
        f"edited run: {summary['edit_run']}"
    )
