"""Registers `sked`, `sked-fast` and `sked-quality` with nerfstudio, one per preset in configs/.

A preset names the knobs users trade speed for accuracy with (iterations, render sizes,
samples per ray, mixed precision); everything else is as docs/method.md gives it. Presets are
YAML files installed with the package (`sked_ns.configs`), so they work after a normal install.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields
from importlib import resources
from typing import Dict, Tuple, Type

import yaml
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from sked_ns.engine.datamanager import SkedDataManagerConfig
from sked_ns.engine.pipeline import SkedPipelineConfig
from sked_ns.engine.trainer import SkedTrainerConfig
from sked_ns.models.nerf.field_edit import SkedOptions
from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig

LEARNING_RATE = 5e-3  # docs/method.md, Optimisation: Adam 5e-3, hash grids 10x
PRESETS = ("sked", "sked-fast", "sked-quality")
PRESET_KEYS = {"description", "iterations", "mixed_precision", "model"}


@dataclass
class SkedAdamOptimizerConfig(AdamOptimizerConfig):
    """nerfstudio's Adam with betas, which its config lacks (`setup` passes every field to torch.optim.Adam)."""

    betas: Tuple[float, float] = (0.9, 0.99)
    """Adam's moment decay rates; (0.9, 0.99) as the authors' code (torch's default is (0.9, 0.999))."""


def _adam(lr: float, iterations: int) -> dict:
    # lr decays exponentially to 0.1x by the end of the edit (docs/method.md, Optimisation).
    return {
        "optimizer": SkedAdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr * 0.1, max_steps=iterations),
    }


def read_preset(name: str, folder=None) -> Dict:
    """The preset's YAML, checked: unknown keys are errors that name the file and the key."""
    path = (resources.files("sked_ns.configs") if folder is None else folder) / f"{name}.yml"
    preset = yaml.safe_load(path.read_text())
    if not isinstance(preset, dict) or "iterations" not in preset or "description" not in preset:
        raise ValueError(f"{path}: a preset is a YAML mapping with at least 'description' and 'iterations'.")
    unknown = set(preset) - PRESET_KEYS
    model_keys = {option.name for option in fields(SkedOptions)}
    unknown |= {f"model.{key}" for key in preset.get("model", {}) if key not in model_keys}
    if unknown:
        raise ValueError(f"{path}: unknown preset keys {sorted(unknown)}; allowed: {sorted(PRESET_KEYS)}, "
                         f"model.<any SKED option>.")
    return preset


def sked_trainer_config(preset: Dict, method_name: str,
                        config_class: Type[SkedTrainerConfig] = SkedTrainerConfig) -> SkedTrainerConfig:
    """The preset as a trainer config of `config_class` (the session layer registers its subclass)."""
    iterations = int(preset["iterations"])
    model = SkedNerfactoModelConfig()
    for key, value in preset.get("model", {}).items():
        setattr(model, key, copy.deepcopy(value))
    return config_class(
        method_name=method_name,
        steps_per_eval_batch=0,
        steps_per_eval_image=1000,
        steps_per_eval_all_images=0,
        steps_per_save=500,
        max_num_iterations=iterations,
        mixed_precision=bool(preset.get("mixed_precision", True)),
        pipeline=SkedPipelineConfig(
            datamanager=SkedDataManagerConfig(dataparser=NerfstudioDataParserConfig()),
            model=model,
        ),
        optimizers={
            "proposal_networks": _adam(LEARNING_RATE, iterations),
            "fields": _adam(LEARNING_RATE, iterations),
            "hash_grids": _adam(10 * LEARNING_RATE, iterations),
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


def method_from_preset(name: str, config_class: Type[SkedTrainerConfig] = SkedTrainerConfig) -> MethodSpecification:
    """`ns-train <name>`'s registry entry: the preset's config and description."""
    preset = read_preset(name)
    return MethodSpecification(config=sked_trainer_config(preset, name, config_class), description=preset["description"])


def edit_preset(name: str = "sked") -> SkedTrainerConfig:
    """A fresh config of the preset for an edit built from Python (no viewer session: its sketches are given)."""
    return sked_trainer_config(read_preset(name), name)
