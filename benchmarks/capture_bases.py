"""Bases of a photographed capture on the CPU, scored as nerfstudio scores them (ns-eval on its own eval split).

    python benchmarks/capture_bases.py eval RUN/config.yml [--output results.json]
    python benchmarks/capture_bases.py splat DATA NERFACTO_RUN OUTPUT [--steps 300 --gaussians 8000] [--output r.json]

`eval` is nerfstudio's `ns-eval` (its ComputePSNR, at every photo of the dataset's eval split) with two things a
CPU without a network needs: LPIPS (an AlexNet download) scores NaN, and a splatfacto run renders with SKED's
torch rasterizer (nerfstudio 1.1.5's splatfacto renders with gsplat's CUDA kernels only).

`splat` is what a user without CUDA has for a splatfacto base of a capture: the nerfacto base's point cloud
(nerfstudio's `ns-export pointcloud`, in the data frame, as COLMAP's cloud would seed `ns-train splatfacto`) seeds
splatfacto fitted on the CPU (`sked_ns.demo.splat_base`), saved as `ns-train splatfacto` saves a run at
OUTPUT/EXPERIMENT/splatfacto/base; the cloud is kept beside it (cloud.ply) and the fit's own figures printed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shlex
import sys
from pathlib import Path

import harness
import numpy as np
import torch
import yaml

CHUNK = 4096
"""Rays a NeRF renders at a time in `eval`, as SKED's edits render."""


@contextlib.contextmanager
def offline_nerfstudio():
    """LPIPS as NaN (no AlexNet download); splatfacto's eval render through the torch rasterizer off CUDA."""
    import torchmetrics.image.lpip as lpip_module
    from nerfstudio.models.splatfacto import SplatfactoModel

    from sked_ns.evaluation.render import render_splatfacto

    class NoLpips(torch.nn.Module):
        def forward(self, *images):
            return torch.tensor(float("nan"))

    def cpu_outputs(model, camera):
        outputs = render_splatfacto(model, camera)
        return {**outputs, "accumulation": outputs["accumulation"], "background": model._get_background_color()}

    saved = lpip_module.LearnedPerceptualImagePatchSimilarity, SplatfactoModel.get_outputs
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: NoLpips()
    if not torch.cuda.is_available():
        SplatfactoModel.get_outputs = cpu_outputs
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity, SplatfactoModel.get_outputs = saved


def evaluate(config: Path, output: Path) -> dict:
    """`ns-eval --load-config CONFIG --output-path OUTPUT`; returns what it wrote. A NeRF renders CHUNK rays at a
    time (nerfacto's 32,768 take over 5 GB on a CPU; the figures do not depend on it)."""
    from nerfstudio.scripts import eval as ns_eval

    plain = ns_eval.eval_setup

    def setup(*args, **kwargs):
        config, pipeline, *rest = plain(*args, **kwargs)
        if hasattr(pipeline.model.config, "eval_num_rays_per_chunk"):
            pipeline.model.config.eval_num_rays_per_chunk = min(CHUNK, pipeline.model.config.eval_num_rays_per_chunk)
        return (config, pipeline, *rest)

    ns_eval.eval_setup = setup
    try:
        with offline_nerfstudio():
            ns_eval.ComputePSNR(load_config=config, output_path=output).main()
    finally:
        ns_eval.eval_setup = plain
    return json.loads(output.read_text())


def export_cloud(config: Path, out: Path, points: int) -> Path:
    """`ns-export pointcloud --save-world-frame True --normal-method open3d`: the cloud in the data frame."""
    from nerfstudio.scripts.exporter import ExportPointCloud

    with offline_nerfstudio():
        ExportPointCloud(load_config=config, output_dir=out, num_points=points, save_world_frame=True,
                         normal_method="open3d").main()
    return out / "point_cloud.ply"


def framed(config, nerfacto: Path):
    """The splat run in the nerfacto base's frame: its dataparser's settings (e.g. --center-method focus)."""
    base = yaml.load((nerfacto / "config.yml").read_text(), Loader=yaml.Loader)
    dataparser = base.pipeline.datamanager.dataparser
    for name in ("center_method", "orientation_method", "auto_scale_poses", "scale_factor", "scene_scale",
                 "train_split_fraction", "eval_mode"):
        setattr(config.pipeline.datamanager.dataparser, name, getattr(dataparser, name))
    return config


def fit_splat(data: Path, nerfacto: Path, output: Path, experiment: str, steps: int, gaussians: int,
              cloud_points: int, refine_every: int = 40) -> dict:
    """The splatfacto base, seeded from the nerfacto base's exported cloud; returns the fit's figures."""
    import open3d

    from sked_ns.demo import splat_base
    from sked_ns.demo.splat_base import SplatFit, fit_splat_base, last_fit

    cloud_dir = output / experiment / "cloud"
    ply = cloud_dir / "point_cloud.ply"
    if not ply.exists():
        export_cloud(nerfacto / "config.yml", cloud_dir, cloud_points)
    cloud = open3d.io.read_point_cloud(str(ply))
    points = torch.as_tensor(np.asarray(cloud.points), dtype=torch.float64)
    colours = torch.as_tensor(np.asarray(cloud.colors), dtype=torch.float32)
    fit = SplatFit(steps=steps, num_gaussians=gaussians, refine_every=refine_every)
    plain = splat_base.splatfacto_config
    splat_base.splatfacto_config = lambda *args, **kwargs: framed(plain(*args, **kwargs), nerfacto)
    try:
        run_dir = fit_splat_base(data, output, fit, seed_points=(points, colours), experiment=experiment)
    finally:
        splat_base.splatfacto_config = plain
    return {"run": str(run_dir), "cloud_points": len(points), "fit": vars(fit), **last_fit}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    scored = commands.add_parser("eval")
    scored.add_argument("config", type=Path)
    scored.add_argument("--output", type=Path)
    splat = commands.add_parser("splat")
    splat.add_argument("data", type=Path)
    splat.add_argument("nerfacto", type=Path, help="the nerfacto base's run folder")
    splat.add_argument("output", type=Path, help="as ns-train's --output-dir")
    splat.add_argument("--experiment", default="fox")
    splat.add_argument("--steps", type=int, default=300)
    splat.add_argument("--gaussians", type=int, default=8000)
    splat.add_argument("--cloud-points", type=int, default=20000)
    splat.add_argument("--refine-every", type=int, default=40, help="densify every N steps (over --steps: never)")
    splat.add_argument("--output", dest="results", type=Path, help="the fit's figures as a results file")
    arguments = parser.parse_args(argv)
    if arguments.command == "eval":
        if arguments.output is not None:
            harness.claim("capture_bases.py", arguments.output)
        raw = (arguments.output or Path("ns-eval.json")).with_suffix(".ns-eval.json")
        harness.publish(evaluate(arguments.config, raw), arguments.output)
    else:
        if arguments.results is not None:
            harness.claim("capture_bases.py", arguments.results)
        fit = fit_splat(arguments.data, arguments.nerfacto, arguments.output, arguments.experiment, arguments.steps,
                        arguments.gaussians, arguments.cloud_points, arguments.refine_every)
        fit["command"] = shlex.join(["python", "benchmarks/capture_bases.py", *map(str, argv or sys.argv[1:])])
        harness.publish(fit, arguments.results)


if __name__ == "__main__":
    main(sys.argv[1:])
