"""A tiny nerfacto (or instant-ngp) base of the demo scene, built in seconds on a CPU.

Photometric training of even a tiny nerfacto takes many minutes on a CPU, so the demo and
the tests fit the field directly to the analytic scene (density from its SDF, colour from
its shading) and save the result exactly as `ns-train nerfacto` would: config.yml,
dataparser_transforms.json and nerfstudio_models/step-*.ckpt. Everything downstream then
takes the user's path.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.configs.method_configs import method_configs
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.field_components.field_heads import FieldHeadNames

from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.method.options import without_lpips
from sked_ns.progress import EVERY_SECONDS, Progress
from sked_ns.sketches.sketch_set import DataparserTransform

PEAK_DENSITY = 100.0
"""Density inside the object (alpha 0.98 over the 0.07 step used by L_pres)."""


@dataclass
class TinyNerfacto:
    """Architecture small enough for CPU tests, still a real NerfactoField."""

    num_levels: int = 8
    log2_hashmap_size: int = 15
    max_res: int = 1024
    hidden_dim: int = 32
    hidden_dim_color: int = 32
    num_nerf_samples_per_ray: int = 32
    proposal_samples: tuple = (64, 32)


def _run_config(method: str, data: Path, output_dir: Path, experiment: str, device: str = "cpu"):
    """`ns-train METHOD` for the demo data, saved under output_dir/experiment/METHOD/base."""
    config = copy.deepcopy(method_configs[method])
    config.output_dir = output_dir
    config.experiment_name = experiment
    config.timestamp = "base"
    config.machine.device_type = device.split(":")[0]
    config.vis = "tensorboard"
    # The method's own dataparser (instant-ngp-bounded: instant-ngp-data) and the plain
    # datamanager: nerfacto's parallel one spawns worker processes, pointless here.
    dataparser = copy.deepcopy(config.pipeline.datamanager.dataparser)
    dataparser.data = data
    config.pipeline.datamanager = VanillaDataManagerConfig(data=data, dataparser=dataparser, train_num_rays_per_batch=1024)
    return config


def tcnn_available() -> bool:
    try:
        import tinycudann  # noqa: F401
    except (ImportError, OSError, EnvironmentError):
        return False
    return True


def nerfacto_config(data: Path, output_dir: Path, tiny: Optional[TinyNerfacto] = TinyNerfacto(), device: str = "cpu"):
    """`ns-train nerfacto` config for the demo data, shrunk to `tiny` (None: nerfacto's own size)."""
    config = _run_config("nerfacto", data, output_dir, "demo-base", device)
    model = config.pipeline.model
    # tiny-cuda-nn where it is installed and usable (CUDA), as `ns-train nerfacto` would choose.
    model.implementation = "tcnn" if device.startswith("cuda") and tcnn_available() else "torch"
    model.camera_optimizer = CameraOptimizerConfig(mode="off")
    model.background_color = "white"
    model.far_plane = 4.0  # an object scene: nothing lies beyond the cameras' far side
    if tiny is None:
        return config
    model.num_levels = tiny.num_levels
    model.log2_hashmap_size = tiny.log2_hashmap_size
    model.max_res = tiny.max_res
    model.hidden_dim = tiny.hidden_dim
    model.hidden_dim_color = tiny.hidden_dim_color
    model.num_nerf_samples_per_ray = tiny.num_nerf_samples_per_ray
    model.num_proposal_samples_per_ray = tiny.proposal_samples
    model.proposal_net_args_list = [
        {"hidden_dim": 16, "log2_hashmap_size": 12, "num_levels": 5, "max_res": 64, "use_linear": False},
        {"hidden_dim": 16, "log2_hashmap_size": 12, "num_levels": 5, "max_res": 128, "use_linear": False},
    ]
    return config


def ngp_config(data: Path, output_dir: Path, tiny: Optional[TinyNerfacto] = TinyNerfacto(), method: str = "instant-ngp",
               device: str = "cpu"):
    """`ns-train instant-ngp(-bounded)` config for the demo data: a coarse grid and long steps for the CPU
    (`tiny` None: the method's own grid, step size and hash grid)."""
    config = _run_config(method, data, output_dir, "demo-base-ngp", device)
    model = config.pipeline.model
    model.background_color = "white"
    if tiny is None:
        return config
    model.log2_hashmap_size = tiny.log2_hashmap_size
    model.max_res = tiny.max_res
    model.grid_resolution = 32
    model.grid_levels = 1 if method == "instant-ngp-bounded" else 2
    model.render_step_size = 0.01
    model.cone_angle = 0.0  # a bounded object, as instant-ngp-bounded
    return config


def soft_density(sdf_values: torch.Tensor, width: float) -> torch.Tensor:
    return PEAK_DENSITY * torch.sigmoid(-sdf_values / width)


def build_demo_base(
    data: Path, output_dir: Path, steps: int = 300, points_per_step: int = 8192, seed: int = 0,
    sdf=demo_scene.sphere_sdf, tiny: Optional[TinyNerfacto] = TinyNerfacto(), method: str = "nerfacto",
    device: str = "cpu",
) -> Path:
    """Fit a nerfacto or instant-ngp (tiny, or None: the method's own size) to the analytic scene on
    `device`; returns the run folder (with config.yml)."""
    torch.manual_seed(seed)
    if method == "nerfacto":
        config = nerfacto_config(Path(data), Path(output_dir), tiny, device)
    else:
        config = ngp_config(Path(data), Path(output_dir), tiny, method, device)
    with without_lpips():
        pipeline = config.pipeline.setup(device=device, test_mode="val")
    outputs = pipeline.datamanager.train_dataparser_outputs
    transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64), float(outputs.dataparser_scale))
    centre = transform.points_to_model(torch.zeros(3, device=device))  # the object's centre (data origin) in the model frame

    model = pipeline.model
    proposals = list(getattr(model, "proposal_networks", []))
    parameters = list(model.field.parameters()) + [p for network in proposals for p in network.parameters()]
    if method != "nerfacto":
        model.field.eval()  # fit the appearance NGP renders with (no per-image embedding)
    optimizer = torch.optim.Adam(parameters, lr=1e-2)
    radius = demo_scene.SPHERE_RADIUS * transform.scale * 1.6
    progress = Progress("demo base", f"{method} fitting step", steps, every_seconds=EVERY_SECONDS)
    for _ in range(steps):
        # Points near the object, in the scene box, and out to infinity (nerfacto's contracted space).
        near = centre + (torch.rand(points_per_step // 2, 3, device=device) * 2 - 1) * radius
        anywhere = torch.rand(points_per_step // 4, 3, device=device) * 2 - 1
        positions = torch.cat([near, anywhere, _uncontract(torch.rand(points_per_step // 4, 3, device=device) * 4 - 2)])
        data_positions = transform.points_to_data(positions).cpu()  # the analytic scene is evaluated on the CPU
        with torch.no_grad():
            # SDF in model units; a 0.003-wide soft surface: about one cell of the finest grid.
            target_density = soft_density(sdf(data_positions) * transform.scale, 0.003).to(device)
            target_rgb = demo_scene.surface_colour(data_positions, sdf).to(device)
        field_outputs = model.field(_point_samples(positions))
        # Fit alpha over a 0.05 step: bounded, so the huge inside densities do not dominate.
        target_alpha = 1 - torch.exp(-target_density * 0.05)
        alpha = 1 - torch.exp(-field_outputs[FieldHeadNames.DENSITY].reshape(-1) * 0.05)
        # Colour wherever there is any density (the soft shell too), from the nearest surface.
        occupied = (target_density > 1e-2).float()[:, None]
        loss = ((alpha - target_alpha) ** 2).mean() * 10
        # Empty space must be really empty: rays integrate it over long distances.
        loss = loss + 0.01 * (field_outputs[FieldHeadNames.DENSITY].reshape(-1) * (target_density < 1e-2)).mean()
        loss = loss + (occupied * (field_outputs[FieldHeadNames.RGB].reshape(-1, 3) - target_rgb) ** 2).mean()
        for network in proposals:
            proposal = network.density_fn(positions[:, None]).reshape(-1)
            loss = loss + ((1 - torch.exp(-proposal * 0.05)) - target_alpha).pow(2).mean() * 10
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        progress.step()

    if method != "nerfacto":
        with torch.no_grad():
            # Every cell, as in instant-ngp's warm-up: occupancy = max over random points of density x step.
            for _ in range(16):
                model.occupancy_grid._update(
                    step=0, occ_eval_fn=lambda x: model.field.density_fn(x) * model.config.render_step_size,
                    ema_decay=1.0,
                )
    run_dir = config.get_base_dir()
    models_dir = run_dir / "nerfstudio_models"
    models_dir.mkdir(parents=True, exist_ok=True)
    config.save_config()
    outputs.save_dataparser_transform(run_dir / "dataparser_transforms.json")
    torch.save(
        {"step": steps, "pipeline": pipeline.state_dict(), "optimizers": {}, "schedulers": {}, "scalers": {}},
        models_dir / f"step-{steps:09d}.ckpt",
    )
    return run_dir


def _uncontract(contracted: torch.Tensor) -> torch.Tensor:
    """Inverse of nerfacto's L-inf scene contraction (|x| > 1 maps to 2 - 1/|x|)."""
    norm = contracted.abs().amax(dim=-1, keepdim=True).clamp(1e-6, 2 - 1e-3)
    outside = contracted / norm / (2 - norm)
    return torch.where(norm > 1, outside, contracted)


def _point_samples(positions: torch.Tensor) -> RaySamples:
    """Zero-length samples at `positions`, looking along +z (colour is view-independent here)."""
    directions = torch.zeros_like(positions)
    directions[:, 2] = 1
    frustums = Frustums(
        origins=positions[:, None], directions=directions[:, None],
        starts=positions.new_zeros(len(positions), 1, 1), ends=positions.new_zeros(len(positions), 1, 1),
        pixel_area=positions.new_ones(len(positions), 1, 1),
    )
    return RaySamples(frustums=frustums, camera_indices=torch.zeros(len(positions), 1, 1, dtype=torch.long,
                                                                    device=positions.device))
