"""Registers the `sked` method with nerfstudio (entry point `nerfstudio.method_configs`)."""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from sked_ns.sked_model import SkedModelConfig

MAX_ITERATIONS = 10_000


def _adam(lr: float) -> dict:
    # lr decays exponentially to 0.1x by the end (method.md, Optimisation).
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr * 0.1, max_steps=MAX_ITERATIONS),
    }


sked_method = MethodSpecification(
    config=TrainerConfig(
        method_name="sked",
        steps_per_eval_batch=500,
        steps_per_save=1000,
        max_num_iterations=MAX_ITERATIONS,
        mixed_precision=True,
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(dataparser=NerfstudioDataParserConfig()),
            model=SkedModelConfig(),
        ),
        optimizers={"proposal_networks": _adam(5e-3), "fields": _adam(5e-2), "camera_opt": _adam(1e-4)},
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    ),
    description="SKED: sketch-guided text-based editing of a trained nerfacto / instant-ngp scene.",
)
