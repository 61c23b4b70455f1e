"""Render nerfstudio models at sketch-view cameras (evaluation, demo images)."""

from __future__ import annotations

import types
from pathlib import Path
from typing import Dict, Optional, Tuple

import torch

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.evaluation.exhaustion import exhaustion_as_error
from sked_ns.models.registry import is_sked_model, renders_cameras
from sked_ns.sketches.sketch_set import SketchView, sketch_view_at


def render_camera(model, camera, base: bool = False) -> Dict[str, torch.Tensor]:
    """rgb (h, w, 3) and accumulation (h, w) of one nerfstudio camera; `base`: a SKED model's frozen base."""
    camera = camera.to(model.device)
    was_training = model.training
    model.eval()
    with torch.no_grad():
        if not base and renders_cameras(model) and not is_sked_model(model) and model.device.type != "cuda":
            outputs = render_splatfacto(model, camera)
        elif not base:
            outputs = model.get_outputs_for_camera(camera)
        elif renders_cameras(model):
            outputs = model.render_base(camera)  # a splat edit rasterizes its frozen base per camera, not per ray
        else:
            rays = camera.generate_rays(camera_indices=0, keep_shape=True)
            shape = rays.shape
            rays = rays.flatten()
            chunk = model.config.eval_num_rays_per_chunk
            parts = [model.render_base(model._collide(rays[i : i + chunk])) for i in range(0, len(rays), chunk)]
            outputs = {key: torch.cat([part[key] for part in parts]).reshape(*shape, -1) for key in parts[0]
                       if key in ("rgb", "accumulation", "preservation_weight")}
    model.train(was_training)
    result = {"rgb": outputs["rgb"].cpu(), "accumulation": outputs["accumulation"][..., 0].cpu()}
    if "preservation_weight" in outputs:  # SKED models: 1 where the pixel shows only what must be kept
        result["preservation_weight"] = outputs["preservation_weight"][..., 0].cpu()
    return result


def render_splatfacto(model, camera) -> Dict[str, torch.Tensor]:
    """A plain splatfacto model's eval render off CUDA, with SKED's torch rasterizer: nerfstudio 1.1.5's
    get_outputs moves the intrinsics to CUDA and calls gsplat's CUDA-only kernels. Same Gaussians, SH degree
    (splatfacto's schedule at the model's step), background and clamping."""
    from sked_ns.models.splat.rasterize import rasterize
    from sked_ns.sketches.cameras import viewmat

    camera_to_world = camera.camera_to_worlds.reshape(-1, 3, 4)[:1].to(model.device, torch.float32)
    intrinsics = camera.get_intrinsics_matrices().reshape(-1, 3, 3)[:1].to(model.device, torch.float32)
    width, height = int(camera.width.reshape(-1)[0]), int(camera.height.reshape(-1)[0])
    if model.config.sh_degree > 0:
        colours = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1)
        sh_degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    else:
        colours, sh_degree = torch.sigmoid(model.features_dc), None
    render, alpha, _ = rasterize(model.means, model.quats, torch.exp(model.scales),
                                 torch.sigmoid(model.opacities).squeeze(-1), colours, viewmat(camera_to_world),
                                 intrinsics, width, height, sh_degree=sh_degree,
                                 rasterize_mode=model.config.rasterize_mode)
    background = model._get_background_color().to(render)
    rgb = torch.clamp(render[0, ..., :3] + (1 - alpha[0]) * background, 0.0, 1.0)
    return {"rgb": rgb, "accumulation": alpha[0]}


def render_at(model, view: SketchView, resolution: int) -> Dict[str, torch.Tensor]:
    """`model` at a sketch view (model frame), longer side `resolution`."""
    return render_camera(model, sketch_view_at(view, resolution)[0])


def render_base_at(model, view: SketchView, resolution: int) -> Dict[str, torch.Tensor]:
    """Like `render_at`, with a SKED model's frozen copy of its base (exactly the base's weights)."""
    return render_camera(model, sketch_view_at(view, resolution)[0], base=True)


def resized_mask(view: SketchView, resolution: int) -> torch.Tensor:
    """The mask at the resolution `render_at` renders (the same one L_sil uses)."""
    return sketch_view_at(view, resolution)[1]


CHECKPOINT_TRIES = 3
"""Reads of a run's latest checkpoint before giving up: a run still training replaces it at every save."""


def read_checkpoint(run, flag: str, pinned: bool = False) -> Tuple[Path, dict]:
    """(checkpoint, its state) of a resolved run (engine/base_scene.resolve_base). A run still training saves its
    next checkpoint and then removes the last (nerfstudio's save_only_latest_checkpoint): one gone between its pick
    and its read is picked again, the newest whole one. `pinned`: the user named that checkpoint; never another."""
    from sked_ns.engine.base_scene import resolve_base

    checkpoint = run.checkpoint
    for _ in range(CHECKPOINT_TRIES):
        try:
            return checkpoint, torch.load(checkpoint, map_location="cpu")
        except FileNotFoundError as error:
            if pinned:
                raise SkedFileNotFoundError(f"{flag} {checkpoint}: removed before it could be read (its run saved a "
                                            "newer one?); pass the run folder to load its latest.") from error
            gone = error
        checkpoint = resolve_base(run.run_dir, flag=flag).checkpoint
    raise SkedFileNotFoundError(f"{flag} {run.run_dir}: its latest checkpoint was replaced {CHECKPOINT_TRIES} times "
                                "while being read (the run is still training and saving that often); try again, or "
                                "wait for the run to end.") from gone


def _without_training_loaders(datamanager_config) -> None:
    """A run loaded to render needs its datasets (cameras, and photos read one at a time), not the loaders it trained
    from, which read every photo up front: nerfstudio's on a thread pool (VanillaDataManager) or in a process
    (ParallelDataManager). This config alone sets its datamanager up as a subclass that skips them."""
    target = datamanager_config._target
    name = f"{getattr(target, '__name__', 'DataManager')}ForRendering"
    skip = {"setup_train": _no_loaders, "setup_eval": _no_loaders, "__module__": __name__}
    datamanager_config._target = types.new_class(name, (target,), exec_body=lambda namespace: namespace.update(skip))


def _no_loaders(self) -> None:
    """In place of setup_train and setup_eval: nothing to read before a render."""


def load_pipeline(run_dir: Path, device: str = "cpu", flag: str = "--load-dir", data: Optional[Path] = None):
    """A trained run's pipeline (any method, SKED included) with its latest weights, for rendering; `flag`: how the
    user named the run, for the error if it is not one; `data`: its dataset, when not where its config.yml says.
    Running out of memory or threads while it loads is one error line, naming the run."""
    from sked_ns.engine.base_scene import resolve_base
    from sked_ns.method.options import without_lpips

    run = resolve_base(run_dir, flag=flag)
    needs_cuda = run.representation is not None and run.representation.stock_render_needs_cuda
    if needs_cuda and not device.startswith("cuda"):
        raise SkedUserError(
            f"{run.run_dir / 'config.yml'}: nerfstudio renders {run.family} runs with CUDA kernels only. "
            "Use a GPU, or compare with a SKED edit's own frozen copy of its base (sked-eval without --base)."
        )
    if needs_cuda:
        from sked_ns.models.nerf.nerfacc_backend import install_lazy_backend

        install_lazy_backend()  # a stock instant-ngp base rendered by a sked-* command gets kernels that build
    with exhaustion_as_error(f"{flag} {run_dir}: loading the run"):
        # Read as soon as picked: a run still training removes its older checkpoints.
        checkpoint, state = read_checkpoint(run, flag, pinned=Path(run_dir).suffix == ".ckpt")
        run.config.machine.device_type = device
        if data is not None:
            run.config.pipeline.datamanager.data = run.config.pipeline.datamanager.dataparser.data = Path(data)
        _without_training_loaders(run.config.pipeline.datamanager)
        with without_lpips():
            pipeline = run.config.pipeline.setup(device=device, test_mode="test")
        pipeline.load_pipeline(state["pipeline"], state["step"])
    # What was scored, recorded by sked-eval: a run still training gets newer checkpoints meanwhile.
    pipeline.sked_loaded_step, pipeline.sked_loaded_checkpoint = int(state["step"]), checkpoint
    return pipeline.eval()
