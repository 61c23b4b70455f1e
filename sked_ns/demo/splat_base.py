"""A Gaussian-splat base fitted on the CPU and saved exactly as `ns-train splatfacto` saves a run.

`ns-train splatfacto` needs CUDA (gsplat's rasterizer), so the demo, the tests and the benchmarks fit
splatfacto's own model here with SKED's torch rasterizer (`sked_ns.models.splat.rasterize.rasterize`, gsplat's
`rasterization` in meaning) and write what nerfstudio's trainer writes: config.yml (splatfacto's
TrainerConfig with the data and the few settings a user would type), dataparser_transforms.json and
nerfstudio_models/step-*.ckpt with the pipeline's state dict, the optimizers', the schedulers' and the
grad scaler's. The fit is splatfacto's training step: one training image per step, its loss (L1 and SSIM),
its Adam learning rates and schedules, its densification strategy (gsplat's DefaultStrategy, fed by the
rasterizer's info), its resolution and SH-degree schedules; only the lengths are shrunk to a CPU fit.
Everything downstream (`ns-train sked --load-dir`, `ns-export gaussian-splat`) then reads a real run.
"""

from __future__ import annotations

import copy
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from sked_ns.progress import EVERY_SECONDS, Progress
from sked_ns.sketches.cameras import viewmat


@dataclass
class SplatFit:
    """How long and how big the CPU fit is; every other setting is splatfacto's."""

    steps: int = 200
    """training steps (one image each), as `--max-num-iterations`"""
    num_gaussians: int = 2000
    """seed Gaussians: points drawn from the seed cloud, or uniform ones without it"""
    refine_every: int = 40
    """densify and prune every this many steps (splatfacto: 100 of 30,000)"""
    warmup_length: int = 40
    """no densification before this step (splatfacto: 500)"""
    sh_degree_interval: int = 100
    """one more active SH degree every this many steps (splatfacto: 1000); features_rest is always degree 3"""
    num_downscales: int = 1
    """first steps at 1/2^d of the image size (splatfacto: 2, doubling every resolution_schedule steps)"""
    seed_opacity: float = 0.1
    """opacity of the seeds from a point cloud, splatfacto's"""
    random_scale: float = 1.0
    """side of the cube uniform seeds are drawn in, model units (splatfacto: 10, for unbounded scenes)"""
    background_color: str = "white"
    """the photos' background (splatfacto's default "random" asks Gaussians to paint a plain backdrop)"""


def splatfacto_config(data: Path, output_dir: Path, fit: SplatFit = SplatFit(), experiment: str = "splat-base",
                      timestamp: str = "base"):
    """`ns-train splatfacto --data DATA` with the fit's lengths, saved under output_dir/experiment/splatfacto/timestamp."""
    from nerfstudio.configs.method_configs import method_configs

    config = copy.deepcopy(method_configs["splatfacto"])
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment
    config.timestamp = timestamp
    config.machine.device_type = "cpu"
    config.vis = "tensorboard"
    config.max_num_iterations = fit.steps
    config.steps_per_save = fit.steps
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.dataparser.data = Path(data)
    model = config.pipeline.model
    model.background_color = fit.background_color
    model.num_random = fit.num_gaussians
    model.random_scale = fit.random_scale
    model.refine_every = fit.refine_every
    model.warmup_length = fit.warmup_length
    model.sh_degree_interval = fit.sh_degree_interval
    model.num_downscales = fit.num_downscales
    model.resolution_schedule = max(1, fit.steps // (2 * fit.num_downscales + 2))  # full size for the fit's second half
    model.stop_split_at = fit.steps * 3 // 4  # the last quarter settles what the last refinement made
    model.reset_alpha_every = 10 ** 6  # an opacity reset needs thousands of steps to recover from
    for schedule in (config.optimizers["means"]["scheduler"],):
        schedule.max_steps = fit.steps  # splatfacto decays the means' lr over its whole run
    return config


def render_for_training(model, camera, rasterize: Callable) -> Dict[str, Tensor]:
    """splatfacto's training `get_outputs`, rasterized by `rasterize` (gsplat's `rasterization` signature)."""
    camera_to_world = model.camera_optimizer.apply_to_camera(camera)
    factor = model._get_downscale_factor()
    camera.rescale_output_resolution(1 / factor)
    intrinsics = camera.get_intrinsics_matrices().to(model.device)
    width, height = int(camera.width.item()), int(camera.height.item())
    camera.rescale_output_resolution(factor)
    sh_degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    colours = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1)
    render, alpha, info = rasterize(
        model.means, model.quats, torch.exp(model.scales), torch.sigmoid(model.opacities).squeeze(-1), colours,
        viewmat(camera_to_world), intrinsics, width, height, sh_degree=sh_degree,
        absgrad=model.strategy.absgrad, rasterize_mode=model.config.rasterize_mode,
    )
    model.info = info
    model.strategy.step_pre_backward(model.gauss_params, model.optimizers, model.strategy_state, model.step, info)
    background = model._get_background_color()
    rgb = torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0)
    return {"rgb": rgb.squeeze(0), "accumulation": alpha.squeeze(0), "background": background}


def seed_gaussians(model, points: Optional[Tensor], colours: Optional[Tensor], count: int,
                   generator: torch.Generator, opacity: float = 0.1) -> None:
    """splatfacto's initialisation from a point cloud (model frame, colours in [0, 1]): `count` of its points,
    scale = mean distance to the 3 nearest, random rotation, `opacity` (splatfacto: 0.1), SH DC from the colour. Without a cloud
    the model keeps splatfacto's own uniform random seeds."""
    from nerfstudio.models.splatfacto import RGB2SH, num_sh_bases, random_quat_tensor

    if points is None:
        return
    if len(points) > count:
        chosen = torch.randperm(len(points), generator=generator)[:count]
        points, colours = points[chosen], colours[chosen]
    distances, _ = model.k_nearest_sklearn(points, 3)
    scales = torch.log(torch.from_numpy(distances).mean(dim=-1, keepdim=True).clamp_min(1e-4).repeat(1, 3))
    features = torch.zeros(len(points), num_sh_bases(model.config.sh_degree), 3)
    features[:, 0] = RGB2SH(colours.float())
    params = {"means": points.float(), "scales": scales, "quats": random_quat_tensor(len(points)),
              "features_dc": features[:, 0], "features_rest": features[:, 1:],
              "opacities": torch.logit(torch.full((len(points), 1), opacity))}
    for name, value in params.items():
        model.gauss_params[name] = torch.nn.Parameter(value.to(model.device))


def traced_point_cloud(trace_view: Callable[[np.ndarray], Dict[str, Tensor]], poses: Sequence[np.ndarray],
                       stride: int = 2) -> Tuple[Tensor, Tensor]:
    """A sparse cloud like structure-from-motion's: the surface points (and colours) the photos' cameras see.

    `trace_view(pose)` renders one data-frame camera of an analytic scene (hit, points, rgb); every `stride`-th
    pixel that hits a surface gives a point."""
    points, colours = [], []
    for pose in poses:
        view = trace_view(pose)
        hit = view["hit"][::stride, ::stride]
        points.append(view["points"][::stride, ::stride][hit])
        colours.append(view["rgb"][::stride, ::stride][hit])
    return torch.cat(points), torch.cat(colours)


def dataset_point_cloud(data: Path, trace_view: Callable[..., Dict[str, Tensor]], stride: int = 4) -> Tuple[Tensor, Tensor]:
    """`traced_point_cloud` at every camera of a nerfstudio dataset of an analytic scene;
    `trace_view(pose, focal, width, height)`, e.g. `BenchmarkScene.render_base`."""
    meta = json.loads((Path(data) / "transforms.json").read_text())
    poses = [np.asarray(frame["transform_matrix"], dtype=np.float64)[:3] for frame in meta["frames"]]
    return traced_point_cloud(lambda pose: trace_view(pose, meta["fl_x"], meta["w"], meta["h"]), poses, stride)


def fit_demo_splat_base(data: Path, output_dir: Path, fit: SplatFit = SplatFit(), sdf=None, seed: int = 0) -> Path:
    """The demo sphere's splat base (`sdf`: the demo's sphere unless given), seeded from its traced cloud."""
    from sked_ns.demo.scenes import sphere as demo_scene

    sdf = sdf or demo_scene.sphere_sdf
    cloud = dataset_point_cloud(data, lambda pose, focal, width, height: demo_scene.render(sdf, pose, focal, width, height))
    return fit_splat_base(data, output_dir, fit, seed_points=cloud, seed=seed, experiment="demo-base-splat")


def psnr(rendered: Tensor, truth: Tensor) -> float:
    return float(-10 * torch.log10(((rendered - truth) ** 2).mean().clamp_min(1e-10)))


def fit_splat_base(data: Path, output_dir: Path, fit: SplatFit = SplatFit(), seed_points: Optional[Tuple[Tensor, Tensor]] = None,
                   seed: int = 0, experiment: str = "splat-base", rasterize: Optional[Callable] = None) -> Path:
    """Fit splatfacto to `data`'s training images on the CPU and save the run; returns the run folder.

    `seed_points`: (points, colours) in the data frame (what a COLMAP cloud gives splatfacto), or None for
    splatfacto's uniform random seeds. The run folder holds only what ns-train writes; the fit's figures
    (Gaussian count, PSNR of the seeds, of the training and of the evaluation-split photos) go to `last_fit`."""
    from nerfstudio.engine.optimizers import Optimizers

    from sked_ns.method.options import without_lpips
    from sked_ns.sketches.sketch_set import DataparserTransform

    if rasterize is None:
        from sked_ns.models.splat.rasterize import rasterize
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    config = splatfacto_config(Path(data), Path(output_dir), fit, experiment)
    with without_lpips():
        pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    model = pipeline.model
    outputs = pipeline.datamanager.train_dataparser_outputs
    if seed_points is not None:
        transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64),
                                        float(outputs.dataparser_scale))
        seed_gaussians(model, transform.points_to_model(seed_points[0].float()), seed_points[1], fit.num_gaussians,
                       generator, fit.seed_opacity)
    optimizers = Optimizers(copy.deepcopy(config.optimizers), model.get_param_groups())
    datamanager = pipeline.datamanager
    model.eval()
    last_fit.clear()
    last_fit["seed_psnr"] = _mean_psnr(model, datamanager.cached_train, datamanager.train_dataset.cameras, rasterize)
    model.train()
    progress = Progress("demo base", "splatfacto fitting step", fit.steps, every_seconds=EVERY_SECONDS)
    for step in range(fit.steps):
        # nerfstudio's trainer: the step callback, forward, loss, backward, Adam, schedulers, then refinement.
        model.step_cb(optimizers, step)
        camera, batch = datamanager.next_train(step)
        loss_dict = model.get_loss_dict(render_for_training(model, camera, rasterize), batch)
        optimizers.zero_grad_all()
        sum(loss_dict.values()).backward()
        optimizers.optimizer_step_all()
        optimizers.scheduler_step_all(step)
        model.step_post_backward(step)
        progress.step()

    model.eval()
    last_fit.update(
        gaussians=int(model.num_points), steps=fit.steps,
        train_psnr=_mean_psnr(model, datamanager.cached_train, datamanager.train_dataset.cameras, rasterize),
        eval_psnr=_mean_psnr(model, datamanager.cached_eval, datamanager.eval_dataset.cameras, rasterize))
    return save_run(config, pipeline, optimizers, fit.steps - 1)


last_fit: Dict[str, float] = {}
"""The latest fit's Gaussian count and PSNR (train and evaluation split, full size)."""


@torch.no_grad()
def _mean_psnr(model, cached, cameras, rasterize: Callable, limit: int = 8) -> float:
    scores = []
    for index in range(min(limit, len(cached))):
        camera = cameras[index:index + 1]
        colours = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1)
        render, alpha, _ = rasterize(
            model.means, model.quats, torch.exp(model.scales), torch.sigmoid(model.opacities).squeeze(-1), colours,
            viewmat(camera.camera_to_worlds), camera.get_intrinsics_matrices(), int(camera.width.item()),
            int(camera.height.item()), sh_degree=model.config.sh_degree)
        rgb = (render[..., :3] + (1 - alpha) * model._get_background_color()).clamp(0, 1)[0]
        image = cached[index]["image"]
        truth = image.float() / 255.0 if image.dtype == torch.uint8 else image
        scores.append(psnr(rgb, truth[..., :3]))
    return float(np.mean(scores)) if scores else math.nan


def save_run(config, pipeline, optimizers, step: int) -> Path:
    """What nerfstudio's trainer writes: config.yml, dataparser_transforms.json and its checkpoint at `step`."""
    from torch.cuda.amp.grad_scaler import GradScaler

    run_dir = config.get_base_dir()
    models_dir = run_dir / "nerfstudio_models"
    models_dir.mkdir(parents=True, exist_ok=True)
    config.save_config()
    pipeline.datamanager.train_dataparser_outputs.save_dataparser_transform(run_dir / "dataparser_transforms.json")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch.cuda.amp.GradScaler is deprecated, and warns without CUDA
        scaler = GradScaler(enabled=config.mixed_precision or config.use_grad_scaler)
    torch.save(
        {"step": step, "pipeline": pipeline.state_dict(),
         "optimizers": {name: optimizer.state_dict() for name, optimizer in optimizers.optimizers.items()},
         "schedulers": {name: scheduler.state_dict() for name, scheduler in optimizers.schedulers.items()},
         "scalers": scaler.state_dict()},
        models_dir / f"step-{step:09d}.ckpt",
    )
    return run_dir

