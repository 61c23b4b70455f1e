"""`sked-demo`: a real SKED edit of the embedded demo scene, end to end (on the CPU, or a GPU where there is one).

1. writes the demo dataset (an analytic sphere) and fits a tiny nerfacto base to it, or with
   `--base splatfacto` a Gaussian-splat base, saved exactly as `ns-train nerfacto` (`splatfacto`)
   saves a run;
2. writes two sketches of a hat on top and renders their preservation-weight field;
3. runs `ns-train sked` on it: reference guidance (renders of the sphere with its hat) when
   no Stable Diffusion weights are available, text-prompt guidance when they are;
4. renders the sketch views before and after, and reports the paper's metrics.

Run again in the same `--output`, it picks up where the last run stopped (rerun.py): the fitted base is reused and
an interrupted edit continued from its last checkpoint.
"""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from sked_ns.demo import BASES
from sked_ns.demo.base import build_demo_base
from sked_ns.demo.rerun import (
    DemoInterrupted,
    base_digest,
    data_digest,
    drop_replaced,
    forget_base,
    plan_edit,
    record_base,
    record_runs,
    reusable_base,
)
from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.engine.trainer import SkedTrainer
from sked_ns.errors import SkedFileExistsError, SkedUserError, check_writable_folder
from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_outside
from sked_ns.evaluation.novel_views import eval_split_views, evaluate_novel_views
from sked_ns.method.edit_box import compute_edit_box
from sked_ns.method.preservation import SketchDistanceField
from sked_ns.progress import Progress
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


class DemoEditTrainer(SkedTrainer):
    """The demo's edit, run as ns-train sked runs it; Ctrl-C is the demo's to report (running the demo again
    continues the edit), not the ns-train line that would resume it by hand."""

    @contextlib.contextmanager
    def _interruptible(self, training: bool):
        yield


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
    to the photos (`splat_fit`, a SplatFit: its defaults, or `base_steps` long, unless given)."""
    if kind == "splatfacto":
        from sked_ns.demo.splat_base import fit_demo_splat_base, last_fit

        run_dir = fit_demo_splat_base(data, folder, splat_fit_of(base_steps, splat_fit))
        print(f"splatfacto base: {last_fit['gaussians']} Gaussians, PSNR {last_fit['train_psnr']:.1f} dB on its "
              f"photos, {last_fit['eval_psnr']:.1f} dB on the held-out ones")
        return run_dir
    return build_demo_base(data, folder, steps=base_steps_of(kind, base_steps))


def base_steps_of(kind: str, base_steps: Optional[int]) -> int:
    if base_steps is not None:
        return base_steps
    if kind == "splatfacto":
        from sked_ns.demo.splat_base import SplatFit

        return SplatFit().steps
    return 600


def splat_fit_of(base_steps: Optional[int], splat_fit=None):
    from sked_ns.demo.splat_base import SplatFit

    if splat_fit is not None:
        return splat_fit
    return SplatFit() if base_steps is None else SplatFit(steps=base_steps)


def base_settings(kind: str, base_steps: Optional[int], splat_fit, data: Path) -> dict:
    """What the fitted base depends on: a rerun with the same reuses it."""
    fit = vars(splat_fit_of(base_steps, splat_fit)) if kind == "splatfacto" else {"steps": base_steps_of(kind, base_steps)}
    return {"base": kind, "fit": fit, "data": data_digest(data)}


def check_demo_settings(output: Path, beta: float, size: int, iterations: int, base_steps: Optional[int],
                        prompt: Optional[str], diffusion_model: str, device: str, base: str) -> None:
    """Every setting, named by its flag, before anything is written; last, that --output can take the demo."""
    from sked_ns.guidance.stable_diffusion import _model_problems

    if not (isinstance(beta, (int, float)) and math.isfinite(beta) and beta > 0):
        raise SkedUserError(f"--beta {beta!r}: the preservation falloff, a finite number of image widths > 0 "
                            "(default 0.025).")
    for flag, value in (("--size", size), ("--iterations", iterations), ("--base-steps", base_steps)):
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


class Rerun:
    """What the demo has settled so far, so that Ctrl-C can say what running it again will reuse."""

    def __init__(self, output: Path, base: str, iterations: int):
        self.output, self.base, self.iterations = output, base, iterations
        self.phase, self.base_settings, self.edit_settings = "starting", None, None

    def interrupted(self) -> DemoInterrupted:
        try:
            again = self._again()
        except Exception:  # a damaged folder: the next run says what it finds
            again = []
        return DemoInterrupted(f"while {self.phase}" + (f"; running it again {', '.join(again)}" if again else ""))

    def _again(self) -> list:
        again = []
        if self.base_settings is not None:
            reused = reusable_base(self.output, self.base, self.base_settings) is not None
            again.append("reuses the fitted base" if reused else "fits the base again")
        if self.edit_settings is not None:
            plan = plan_edit(self.output / "edits", self.edit_settings, self.iterations)
            again.append("starts the edit again (it had saved no checkpoint)" if plan.run is None else
                         "takes the finished edit" if plan.done else
                         f"continues the edit from its checkpoint at step {plan.step}")
        return again


def run(output: Path, beta: float = 0.025, size: int = 128, iterations: int = 100, base_steps: Optional[int] = None,
        prompt: Optional[str] = None, diffusion_model: str = "CompVis/stable-diffusion-v1-4", device: str = "cpu",
        base: str = "nerfacto", splat_fit=None) -> dict:
    """The demo in `output`, picking up what an earlier run there left (rerun.py); Ctrl-C raises DemoInterrupted."""
    check_demo_settings(output, beta, size, iterations, base_steps, prompt, diffusion_model, device, base)
    output = Path(output).resolve()  # absolute paths in config.yml: ns-* commands work from anywhere
    hold(output, "Wait for it to end, or choose another --output.")  # this process's alone until it ends
    (output / MARKER).touch()
    rerun = Rerun(output, base, iterations)
    try:
        return _run(output, rerun, beta, size, iterations, base_steps, prompt, diffusion_model, device, base, splat_fit)
    except DemoInterrupted:
        raise
    except KeyboardInterrupt:
        raise rerun.interrupted() from None


def _settled_base(output: Path, rerun: Rerun, base: str, base_steps: Optional[int], splat_fit) -> Path:
    """The fitted base: reused when a run here fitted it with the same settings and it is intact, else fitted."""
    data = output / "data"
    rerun.phase = "writing the demo data"
    demo_scene.write_demo_dataset(data)
    rerun.base_settings = settings = base_settings(base, base_steps, splat_fit, data)
    run_dir = reusable_base(output, base, settings)
    if run_dir is not None:
        print(f"sked-demo: reusing the {base} base fitted here before with these settings ({run_dir})")
        return run_dir
    rerun.phase = f"fitting the {base} base"
    forget_base(output, base)
    run_dir = fit_base(base, data, output / "base", base_steps, splat_fit)
    record_base(output, base, settings, run_dir)
    return run_dir


def _settled_edit(output: Path, rerun: Rerun, base_run: Path, iterations: int, prompt, guidance: str,
                  diffusion_model: str, beta: float, device: str) -> tuple:
    """The edit's finished run: taken as it is, continued, or run; and how it came to be."""
    from sked_ns.engine.edit_run import edit_config, resume_config, run_edit

    edits = output / "edits"
    rerun.edit_settings = settings = {
        "base": base_digest(output, rerun.base), "beta": beta, "guidance": guidance, "prompt": prompt,
        "diffusion_model": diffusion_model if guidance == "stable-diffusion" else None}
    plan = plan_edit(edits, settings, iterations)
    print(f"sked-demo: {plan.describe(iterations)}")
    rerun.phase = "editing"
    if plan.done:
        drop_replaced(edits, settings, plan.run, plan.chain)
        return plan.run, "taken as done"
    if plan.run is not None:
        config = resume_config(plan.run, edits, iterations=iterations)
        config.experiment_name = plan.run.parent.parent.name  # beside the run it continues
        config.machine.device_type, config.vis = device, "tensorboard"
    else:
        config = edit_config(base_run / "nerfstudio_models", output / "data", output / "sketches", edits,
                             prompt=prompt, guidance=guidance, iterations=iterations, device=device,
                             steps_per_save=max(1, min(50, iterations // 10)))  # a rerun continues from near the stop
        config.pipeline.model.beta = beta
        if guidance == "stable-diffusion":
            config.pipeline.model.guidance.model = diffusion_model
    config.set_timestamp()
    record_runs(edits, settings, [*plan.chain, config.get_base_dir()])  # before it writes: Ctrl-C finds it
    run_dir = run_edit(config, DemoEditTrainer).base_dir
    drop_replaced(edits, settings, run_dir, plan.chain)
    return run_dir, "new" if plan.run is None else f"continued from step {plan.step}"


def _run(output: Path, rerun: Rerun, beta, size, iterations, base_steps, prompt, diffusion_model, device, base,
         splat_fit) -> dict:
    from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at, resized_mask

    print(f"sked-demo: the demo data, a {base} base ({base_steps_of(base, base_steps)} fitting steps), two sketches, "
          f"the edit ({iterations} iterations), then renders and metrics; each phase prints its progress and time "
          "left. Stopped, the same command picks up where it stopped: the fitted base and the edit's last "
          "checkpoint are kept.")
    base_run = _settled_base(output, rerun, base, base_steps, splat_fit)
    rerun.phase = "writing the sketches"
    save_sketch_set(demo_scene.demo_sketch_set(), output / "sketches", overwrite=True)
    sketches = load_sketch_set(output / "sketches")  # the user's path: from disk
    transform = DataparserTransform.from_json(base_run / "dataparser_transforms.json")
    summary = {"beta": beta, **preservation_figure(sketches, transform, beta, size, output / "preservation_weights.png")}

    guidance = choose_guidance(prompt, diffusion_model)
    edit_run, how = _settled_edit(output, rerun, base_run, iterations, prompt, guidance, diffusion_model, beta, device)
    rerun.phase = "rendering the results"
    edit_pipeline = load_pipeline(edit_run, device)
    edit_model = edit_pipeline.model
    if base == "splatfacto":
        # nerfstudio's splatfacto renders with gsplat's CUDA kernels only: the edit's frozen copy of the base
        # (exactly its Gaussians) renders it here.
        render_base = lambda view: render_base_at(edit_model, view, size)  # noqa: E731
    else:
        base_model = load_pipeline(base_run, device).model
        render_base = lambda view: render_at(base_model, view, size)  # noqa: E731
    rows, views = [], []
    sketch_views = sketches.in_model_frame(transform).views
    progress = Progress("sked-demo", "sketch view rendered", len(sketch_views))
    for view in sketch_views:
        before, after, mask = render_base(view), render_at(edit_model, view, size), resized_mask(view, size)
        views.append({"ios_base": intersection_over_sketch(before["accumulation"], mask),
                      "ios_edit": intersection_over_sketch(after["accumulation"], mask),
                      "psnr_outside": psnr_outside(after["rgb"], before["rgb"], mask)})
        outline = cv2.dilate(mask.numpy().astype(np.uint8), np.ones((3, 3), np.uint8)) - mask.numpy().astype(np.uint8)
        sketched = after["rgb"].numpy().copy()
        sketched[outline > 0] = [1.0, 0.1, 0.1]
        rows.append(np.concatenate([before["rgb"].numpy(), after["rgb"].numpy(), sketched], axis=1))
        progress.step()
    _write_png(output / "before_after.png", np.concatenate(rows, axis=0))
    # The edit from the base dataset's evaluation cameras, not only from the sketch views.
    novel_views = eval_split_views(edit_pipeline, size, (1.0, 1.0, 1.0))
    novel = evaluate_novel_views(edit_model, novel_views,
                                 progress=Progress("sked-demo", "evaluation view rendered", len(novel_views)))
    _write_png(output / "novel_views.png", np.concatenate([row.numpy() for row in novel.pop("rows")], axis=0))
    summary["novel_views"] = novel
    summary.update(
        base=base, guidance=guidance, iterations=iterations, edit_run=str(edit_run), edit=how, views=views,
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
