"""Pipeline: loads the sketch set once and hands it to the datamanager and the model."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

from nerfstudio.pipelines.base_pipeline import Pipeline, VanillaPipeline, VanillaPipelineConfig
from torch.cuda.amp.grad_scaler import GradScaler

from sked_ns.base_scene import check_same_frame, resolve_base
from sked_ns.sked_datamanager import SkedDataManagerConfig
from sked_ns.sked_model import SkedModelConfig
from sked_ns.sketches import load_sketch_set


@dataclass
class SkedPipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: SkedPipeline)
    datamanager: SkedDataManagerConfig = field(default_factory=SkedDataManagerConfig)
    model: SkedModelConfig = field(default_factory=SkedModelConfig)


class SkedPipeline(VanillaPipeline):
    config: SkedPipelineConfig

    def __init__(
        self,
        config: SkedPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ):
        Pipeline.__init__(self)
        self.config = config
        self.test_mode = test_mode
        self.world_size = world_size
        self.datamanager = config.datamanager.setup(device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank)
        self.datamanager.to(device)
        if config.model.sketches is None:
            raise ValueError("SKED needs a sketch set: pass --sketches <folder with sketches.json>.")
        sketch_set = load_sketch_set(config.model.sketches).in_model_frame(self.datamanager.dataparser_transform)
        self._model = config.model.setup(
            scene_box=self.datamanager.train_dataset.scene_box,
            num_train_data=len(self.datamanager.train_dataset),
            metadata=self.datamanager.train_dataset.metadata,
            device=device,
            grad_scaler=grad_scaler,
            sketch_set=sketch_set,
        )
        if config.model.base_checkpoint is not None:  # after the model's own checks (image count is clearer)
            check_same_frame(resolve_base(Path(config.model.base_checkpoint)), self.datamanager.dataparser_transform)
        self.model.to(device)
        self.datamanager.attach_sketches(
            sketch_set, self.model.edit_box, config.model.silhouette_resolution, config.model.guidance_resolution
        )
        self._guidance_ready = False

    def prepare_guidance(self) -> None:
        """Load the guidance once, just before the first training step (never for export)."""
        if self._guidance_ready:
            return
        model = self.model
        carving = model.config.guidance == "stable-diffusion" and not (model.config.prompt and model.config.prompt.strip())
        if not carving:
            guidance_config = model.config.sds if model.config.guidance == "stable-diffusion" else model.config.reference
            guidance = guidance_config.setup()
            guidance.prepare(model.config.prompt, str(model.device), {"dataparser_transform": self.datamanager.dataparser_transform})
            model.guidance = guidance
        self._guidance_ready = True

    def get_train_loss_dict(self, step: int):
        self.prepare_guidance()
        data = self.datamanager.next_sked(step, photo_rays=self.model.config.effective_lambda_photo > 0)
        return self.model.get_sked_loss_dict(
            data["random_view"], data["random_camera"], data["sketch_rays"], data["sketch_masks"], step,
            photo=data.get("photo"),
        )
