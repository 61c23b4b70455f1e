"""Pipeline: nerfstudio's VanillaPipeline, with the model's sketch set handed to the datamanager.

The datamanager is set up first and tells the model the data's frame (dataset metadata); the
model loads the sketch set in that frame; this pipeline then checks the base's frame and gives
the datamanager the same sketch set. Devices are VanillaPipeline's business (it moves the datamanager,
an nn.Module in nerfstudio 1.1.5). An edit records its cameras when it starts training, and one loaded to render
after its data moved is set up from that record (engine/moved_data.py).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from torch.cuda.amp.grad_scaler import GradScaler

from sked_ns.engine.base_scene import check_same_frame, edited_base
from sked_ns.engine.datamanager import SkedDataManagerConfig
from sked_ns.engine.moved_data import KEPT_VIEWS, keep_views, views_for_moved_data
from sked_ns.errors import SkedUserError
from sked_ns.guidance import check_guidance
from sked_ns.guide import guide
from sked_ns.method.options import is_carving
from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig
from sked_ns.models.registry import renders_cameras
from sked_ns.sketches.placement import warn_views_off_photos


@dataclass
class SkedPipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: SkedPipeline)
    datamanager: SkedDataManagerConfig = field(default_factory=SkedDataManagerConfig)
    model: SkedNerfactoModelConfig = field(default_factory=SkedNerfactoModelConfig)


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
        refuse_multi_device(world_size)
        if config.model.sketches is None:  # before any data is read
            raise SkedUserError("SKED needs a sketch set: pass --sketches <folder with sketches.json>.")
        check_guidance(config.model.guidance, config.model.prompt)  # e.g. --prompt "" would carve: refused first
        if test_mode != "val":  # loaded to render: its photos are not needed, so its data may have moved
            end_viewer_quietly()
            views = views_for_moved_data(config)
            if views is not None:
                setattr(config.datamanager, KEPT_VIEWS, views)
        # nerfstudio's set-up; the model loads the sketch set in the data's frame (model_frame_sketches).
        super().__init__(config, device, test_mode=test_mode, world_size=world_size, local_rank=local_rank,
                         grad_scaler=grad_scaler)
        if config.model.base_checkpoint is not None:  # after the model's own checks (image count is clearer)
            check_same_frame(edited_base(config.model), self.datamanager.dataparser_transform)
        # The same sketch set, loaded once, for the sketch views and random views.
        self.datamanager.attach_sketches(
            self.model.sketch_set, self.model.edit_box, config.model.silhouette_resolution, config.model.guidance_resolution
        )
        self._guidance_ready = False
        if test_mode == "val":  # an edit about to train (not one loaded to render)
            self.model.warn_if_off_base()
            photos = getattr(self.datamanager, "train_dataset", None)
            if photos is not None:
                warn_views_off_photos(self.model.sketch_set.views, photos.cameras.camera_to_worlds[:, :3, 3].cpu().numpy(),
                                      self.model.edit_box.center, str(config.model.sketches))

    def prepare_guidance(self) -> None:
        """Load the guidance once, just before the first training step (never for export)."""
        if self._guidance_ready:
            return
        model = self.model
        if not is_carving(model.config):
            guidance = model.config.guidance.setup()
            guidance.prepare(model.config.prompt, str(model.device),
                             {"dataparser_transform": self.datamanager.dataparser_transform, "model": model})
            model.guidance = guidance
        self._guidance_ready = True

    def keep_views(self) -> None:
        """Record the edit's cameras beside its copy of the base, once it trains (it has that copy by then)."""
        kept = getattr(self.model.config, "base_kept", None)
        if kept is not None and not getattr(self, "_views_kept", False) and Path(kept).parent.is_dir():
            keep_views(self.datamanager, Path(kept).parent)
        self._views_kept = True

    def get_train_loss_dict(self, step: int):
        self.prepare_guidance()
        self.keep_views()
        photos = self.model.photo_anchor_acts()
        images = renders_cameras(self.model)  # splats render whole photos, NeRFs ray batches
        data = self.datamanager.next_sked(step, photo_rays=photos and not images, photo_view=photos and images,
                                          random_view_camera=images)
        return self.model.get_sked_loss_dict(data, step)


def end_viewer_quietly() -> None:
    """`ns-viewer` serves until Ctrl-C, which nerfstudio's serving loop (a sleep in run_viewer._start_viewer) leaves
    to Python, a traceback. In an ns-viewer process that loads an edit, and only there (stock methods' viewers are
    left as nerfstudio has them), Ctrl-C ends it with one line instead; any other exception is shown as before."""
    if Path(sys.argv[0]).name != "ns-viewer" or getattr(sys.excepthook, "ends_viewer_quietly", False):
        return
    shown = sys.excepthook

    def hook(kind, value, traceback) -> None:
        if issubclass(kind, KeyboardInterrupt):
            sys.stderr.write("ns-viewer: stopped (Ctrl-C).\n")
            return
        shown(kind, value, traceback)

    hook.ends_viewer_quietly = True
    sys.excepthook = hook


def refuse_multi_device(world_size: int) -> None:
    """SKED's step renders through the model directly (not DDP's forward), so gradients would not be synced."""
    if world_size > 1:
        raise SkedUserError(
            f"SKED edits on one device, but this run has {world_size} processes (--machine.num-devices x "
            "--machine.num-machines). Run with --machine.num-devices 1 --machine.num-machines 1. Two ways scale "
            "instead: a second GPU for the diffusion model (pipeline.model.guidance:stable-diffusion "
            "--pipeline.model.guidance.device cuda:1), and many edits at once, one per GPU, here or as a Slurm job "
            f"array: sked-batch ({guide('batch.md')})."
        )
