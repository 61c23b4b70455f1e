"""Registers the `sked` method with nerfstudio (entry point `nerfstudio.method_configs`)."""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from sked_ns.sked_datamanager import SkedDataManagerConfig
from sked_ns.sked_model import SkedModelConfig
from sked_ns.sked_pipeline import SkedPipelineConfig
from sked_ns.sked_trainer import SkedTrainerConfig

MAX_ITERATIONS = 10_000
LEARNING_RATE = 5e-3  # method.md: Adam 5e-3, hash grids 10x


def _adam(lr: float) -> dict:
    # lr decays exponentially to 0.1x by the end (method.md, Optimisation).
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr * 0.1, max_steps=MAX_ITERATIONS),
    }


sked_method = MethodSpecification(
    config=SkedTrainerConfig(
        method_name="sked",
        steps_per_eval_batch=0,
        steps_per_eval_image=1000,
        steps_per_eval_all_images=0,
        steps_per_save=500,
        max_num_iterations=MAX_ITERATIONS,
        mixed_precision=True,
        pipeline=SkedPipelineConfig(
            datamanager=SkedDataManagerConfig(dataparser=NerfstudioDataParserConfig()),
            model=SkedModelConfig(),
        ),
        optimizers={
            "proposal_networks": _adam(LEARNING_RATE),
            "fields": _adam(LEARNING_RATE),
            "hash_grids": _adam(10 * LEARNING_RATE),
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    ),
    description="SKED: sketch-guided text-based editing of a trained nerfacto / instant-ngp scene.",
)
