"""Build and run an edit from Python, exactly as `ns-train sked` does (used by the demo and tests)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Optional

from sked_ns.engine.presets import edit_preset
from sked_ns.engine.trainer import SkedTrainerConfig
from sked_ns.guidance import guidance_config
from sked_ns.run_lock import release


def edit_config(
    base: Path, data: Path, sketches: Path, output_dir: Path, *, prompt: Optional[str] = None,
    guidance: str = "reference", iterations: int = 100, guidance_resolution: int = 32,
    silhouette_resolution: int = 24, device: str = "cpu", steps_per_save: int = 50, dataparser=None,
) -> SkedTrainerConfig:
    """The `ns-train sked --load-dir BASE --sketches SKETCHES ... <dataparser> --data DATA` config;
    the dataparser defaults to the base's own (as the user types it: the same subcommand and settings)."""
    from sked_ns.engine.base_scene import resolve_base

    if dataparser is None:
        dataparser = copy.deepcopy(resolve_base(Path(base)).config.pipeline.datamanager.dataparser)
    dataparser.data = Path(data)
    config: SkedTrainerConfig = edit_preset()
    config.output_dir = Path(output_dir)
    config.experiment_name = "edit"
    config.load_dir = Path(base)
    config.sketches = Path(sketches)
    config.data = Path(data)
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.dataparser = dataparser
    config.machine.device_type = device
    config.mixed_precision = device == "cuda"
    config.vis = "tensorboard"
    config.max_num_iterations = iterations
    config.steps_per_save = steps_per_save
    config.steps_per_eval_image = 10**9
    config.pipeline.model.prompt = prompt
    config.pipeline.model.guidance = guidance_config(guidance)
    config.pipeline.model.guidance_resolution = guidance_resolution
    config.pipeline.model.silhouette_resolution = silhouette_resolution
    config.pipeline.model.edit_box_warmup = max(1, iterations // 2)
    return config


def resume_config(run: Path, output_dir: Optional[Path] = None, *, iterations: Optional[int] = None) -> SkedTrainerConfig:
    """The `ns-train sked --load-dir RUN [--output-dir OUT] [--max-num-iterations N]` config: the preset's
    defaults but for what is typed; resolving it takes everything else from the saved edit."""
    config: SkedTrainerConfig = edit_preset()
    config.load_dir = Path(run)
    if output_dir is not None:
        config.output_dir = Path(output_dir)
    if iterations is not None:
        config.max_num_iterations = iterations
    return config


def run_edit(config: SkedTrainerConfig, trainer_class=None):
    """What `ns-train` does with a config: seed, save it, set up the trainer, train. Returns the trainer.
    `trainer_class`: a subclass of the config's trainer to run it with (config.yml still names the config's own)."""
    import random

    import numpy as np
    import torch

    # Seeded as ns-train's train_loop seeds (random, numpy, torch): the edit must not depend on what ran before.
    random.seed(config.machine.seed)
    np.random.seed(config.machine.seed)
    torch.manual_seed(config.machine.seed)
    config.set_timestamp()
    try:
        config.save_config()  # takes the run folder for this edit (ns-train holds it until the process ends)
        trainer = config.setup(local_rank=0, world_size=1) if trainer_class is None else \
            trainer_class(config, local_rank=0, world_size=1)
        trainer.setup()
        trainer.train()
    finally:
        release(config.get_base_dir())  # this process goes on: the next edit (or a resume) may write there
        close_event_writers()
    return trainer


def close_event_writers() -> None:
    """nerfstudio's event writers are the process's, and every later run logs to them all: one logging into a run
    folder since moved or removed would fail in the next edit this process runs."""
    from nerfstudio.utils import writer

    for event_writer in writer.EVENT_WRITERS:
        if getattr(event_writer, "tb_writer", None) is not None:
            event_writer.tb_writer.close()
    writer.EVENT_WRITERS.clear()
