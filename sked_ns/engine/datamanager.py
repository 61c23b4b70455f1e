"""Datamanager: the base's dataset stays attached; SKED draws random and sketch views.

Keeping nerfstudio's `VanillaDataManager` (train dataset, pixel sampler, dataparser
outputs) is what lets `ns-export`, `ns-render` and the appearance embeddings work on an
edited scene. SKED adds one random view aimed at the edit box per iteration and the fixed
sketch views, rendered every iteration at reduced resolution for L_sil. Both come as rays
(a NeRF renders rays) and as nerfstudio `Cameras` (a splat model renders whole images). An edit loaded to render
after its data moved reads the edit's own record of its cameras instead of the data (engine/moved_data.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from sked_ns.engine.moved_data import KEPT_VIEWS, KeptViewsConfig, PhotolessDataset, data_path, kept_frame
from sked_ns.method.edit_box import EditBox
from sked_ns.sketches.cameras import cameras_of, pinhole_rays
from sked_ns.sketches.data_frame import SKETCH_FRAME, TRAINING_CAMERAS
from sked_ns.sketches.random_views import ELEVATION_RANGE_DEG, FOV_RANGE_DEG, RandomViewSampler, focal_from_fov
from sked_ns.sketches.sketch_set import DataparserTransform, SketchSet, sketch_view_at


@dataclass
class SkedDataManagerConfig(VanillaDataManagerConfig):
    _target: Type = field(default_factory=lambda: SkedDataManager)
    radius_scale_range: Tuple[float, float] = (0.8, 1.2)
    """Random-view distance to the edit box centre, relative to the sketch cameras' distance."""
    elevation_range: Tuple[float, float] = ELEVATION_RANGE_DEG
    """Random-view elevation above the edit box centre, degrees, uniform (the authors' polar angle 0-150)."""
    azimuth_range: Tuple[float, float] = (-180.0, 180.0)
    """Random-view azimuth relative to the first sketch view, degrees."""
    fov_range: Tuple[float, float] = FOV_RANGE_DEG
    """Random-view horizontal field of view, degrees (the authors' 40-80), narrowed by edit_fill for a small edit."""
    edit_fill: float = 0.7
    """The random views' field of view range is narrowed, in proportion, until the edit box's bounding sphere spans
    at least this share of a view's width at the range's middle (in the authors' 40-80 deg a flower on a vase spans
    2-3 px of a 24 px render, where no guidance can shape it). 0: fov_range as given."""
    seed: int = 0
    """Seed of the random views (resumed runs continue the sequence from the step)."""
    train_num_rays_per_batch: int = 512
    """Rays of the base's photos per step (the photo anchor, of which ~3/4 are kept): a small batch beside the
    renders SKED needs anyway (nerfstudio's 1,024 or nerfacto's 4,096 would double a step's cost)."""




def outputs_transform(outputs) -> DataparserTransform:
    """The transform a dataparser applied (its dataparser_transforms.json), from its outputs."""
    return DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64), float(outputs.dataparser_scale))


def sketch_frame_metadata(dataparser_config, outputs, frame: Optional[DataparserTransform] = None) -> Dict:
    """The train dataset's metadata the model loads the sketch set with, from the train dataparser outputs: the
    data -> model frame (`frame` where it is known already) and the training cameras' positions with the scene box
    centre."""
    from sked_ns.sketches.data_frame import data_frame_transform

    if frame is None:
        frame = data_frame_transform(dataparser_config, outputs_transform(outputs))
    return {SKETCH_FRAME: frame,
            TRAINING_CAMERAS: (outputs.cameras.camera_to_worlds[:, :, 3].numpy().astype(np.float64),
                               outputs.scene_box.get_center().numpy().astype(np.float64))}


class SkedDataManager(VanillaDataManager):
    config: SkedDataManagerConfig

    def __init__(self, config: SkedDataManagerConfig, *args, **kwargs):
        # Set by the pipeline for an edit loaded to render after its data moved: read in place of the data.
        self.kept_views = vars(config).pop(KEPT_VIEWS, None)
        if self.kept_views is not None:
            self.moved_from = data_path(config)
            config = replace(config, data=None, dataparser=KeptViewsConfig(data=self.moved_from, views=self.kept_views))
        super().__init__(config, *args, **kwargs)
        frame = kept_frame(self.kept_views) if self.kept_views is not None else None
        # nerfstudio hands the train dataset's metadata to the model: the sketch set needs this frame.
        self.train_dataset.metadata.update(sketch_frame_metadata(self.config.dataparser, self.train_dataparser_outputs,
                                                                 frame))

    def create_train_dataset(self):
        if self.kept_views is None:
            return super().create_train_dataset()
        return PhotolessDataset(self.train_dataparser_outputs, self.config.camera_res_scale_factor, self.moved_from,
                                blank_items=True)  # the viewer draws each camera with its photo

    def create_eval_dataset(self):
        if self.kept_views is None:
            return super().create_eval_dataset()
        outputs = self.dataparser.get_dataparser_outputs(split=self.test_split)
        return PhotolessDataset(outputs, self.config.camera_res_scale_factor, self.moved_from)

    def setup_train(self) -> None:
        if self.kept_views is None:  # without photos there is nothing to cache or sample
            super().setup_train()

    def next_train(self, step: int):
        if self.kept_views is None:
            return super().next_train(step)
        # Without photos, rays through random pixels of the training cameras and no colours: what ns-export's point
        # cloud samples (it keeps the model's colours along them).
        from nerfstudio.model_components.ray_generators import RayGenerator

        cameras = self.train_dataset.cameras
        if getattr(self, "train_ray_generator", None) is None:
            self.train_ray_generator = RayGenerator(cameras.to(self.device))
        count = self.config.train_num_rays_per_batch
        image = torch.randint(len(cameras), (count,))
        row = (torch.rand(count) * cameras.height[image, 0]).long()
        column = (torch.rand(count) * cameras.width[image, 0]).long()
        indices = torch.stack([image, row, column], dim=-1)
        return self.train_ray_generator(indices), {"indices": indices}

    def setup_eval(self) -> None:
        if self.kept_views is None:
            super().setup_eval()
            return
        # What nerfstudio's evaluations iterate, reading a photo only when asked (which says where it was).
        from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader, RandIndicesEvalDataloader

        self.fixed_indices_eval_dataloader = FixedIndicesEvalDataloader(input_dataset=self.eval_dataset,
                                                                        device=self.device)
        self.eval_dataloader = RandIndicesEvalDataloader(input_dataset=self.eval_dataset, device=self.device)

    @property
    def dataparser_transform(self) -> DataparserTransform:
        return outputs_transform(self.train_dataparser_outputs)

    @property
    def data_frame_transform(self) -> DataparserTransform:
        """A sketch set's data frame (the data's transforms.json) -> model frame (sketches.data_frame.data_frame_transform)."""
        return self.train_dataset.metadata[SKETCH_FRAME]

    def attach_sketches(self, sketch_set: SketchSet, edit_box: EditBox, silhouette_resolution: int, guidance_resolution: int) -> None:
        """Precompute the sketch views (cameras, rays and masks) and the random-view sampler."""
        rays, masks = [], []
        # Per sketch view its camera (1 view) and mask (H x W, float), on the device: splats render whole views.
        self.sketch_cameras: List[Tuple[Cameras, torch.Tensor]] = []
        for view in sketch_set.views:
            camera, mask = sketch_view_at(view, silhouette_resolution)
            rays.append(camera.generate_rays(camera_indices=0, keep_shape=True).flatten())
            masks.append(mask)
            self.sketch_cameras.append((camera.to(self.device), mask.float().to(self.device)))
        # Views may differ in size: rays and masks are kept flat, in the same order.
        self.sketch_rays: RayBundle = _concatenate(rays).to(self.device)
        self.sketch_masks = torch.cat([mask.flatten() for mask in masks]).float().to(self.device)
        # L_sil counts only the masks' pixels: a NeRF renders those rays alone (found once here, not per step).
        self.sketch_pixels = torch.nonzero(self.sketch_masks > 0)[:, 0]
        self.masked_sketch_rays: RayBundle = self.sketch_rays[self.sketch_pixels]
        self.random_views = RandomViewSampler.around_sketches(
            edit_box.center, [view.camera_to_world for view in sketch_set.views],
            radius_scale_range=tuple(self.config.radius_scale_range),
            elevation_range_deg=tuple(self.config.elevation_range),
            azimuth_range_deg=tuple(self.config.azimuth_range),
            fov_range_deg=tuple(self.config.fov_range),
            edit_radius=0.5 * float(np.linalg.norm(edit_box.size)),
            edit_fill=float(self.config.edit_fill),
        )
        scale = self.random_views.fov_scale
        if scale < 1.0:
            low, high = (scale * value for value in self.config.fov_range)
            CONSOLE.print(f"Random views: field of view {low:.0f}-{high:.0f} deg, framing the edit box "
                          f"(--pipeline.datamanager.edit-fill {self.config.edit_fill:g}; 0 keeps --pipeline.datamanager.fov-range)")
        self.guidance_resolution = guidance_resolution

    def next_sked(self, step: int, photo_rays: bool = False, photo_view: bool = False,
                  random_view_camera: bool = True) -> Dict:
        """One random view (rays shaped H x W, and with `random_view_camera` its camera on the device, for a model
        that renders cameras), the fixed sketch views (flat rays and masks, the rays at the masks' pixels with those
        pixels' indices, and per view a camera and mask), and
        (photo_rays) a batch of the base's training rays with their photo colours, drawn as nerfstudio draws them
        for training, or (photo_view) one whole training photo."""
        generator = torch.Generator().manual_seed(self.config.seed * 1_000_003 + step)  # resumable
        pose, fov, direction = self.random_views.sample(generator)
        size = self.guidance_resolution
        focal = focal_from_fov(fov, size)
        pose_tensor = torch.tensor(pose, dtype=torch.float32)
        # The pose crosses to the device (12 numbers) and the rays are made there: nerfstudio's generate_rays would
        # build them with a dozen host copies and scalar reads.
        ray_bundle = pinhole_rays(pose_tensor.to(self.device), focal, size)
        data = {
            "random_view": ray_bundle,
            "random_camera": {"camera_to_world": pose, "focal": focal, "direction": direction},
            "sketch_rays": self.sketch_rays,
            "sketch_masks": self.sketch_masks,
            "masked_sketch_rays": self.masked_sketch_rays,
            "sketch_pixels": self.sketch_pixels,
            "sketch_views": self.sketch_cameras,
        }
        if random_view_camera:
            camera = cameras_of(pose_tensor[None], focal, focal, size / 2, size / 2, size, size)
            data["random_view_camera"] = camera.to(self.device)
        if photo_rays:
            rays, batch = self.next_train(step)
            data["photo"] = (rays.to(self.device), batch["image"].to(self.device))
        if photo_view:
            data["photo_view"] = self.photo_view(step)
        return data

    def photo_view(self, step: int) -> Dict:
        """The base's training photo `step` mod their number, whole, with its camera, for a model that renders
        images (splats): {"camera", "image" (H, W, C) float, "index", "native"}, its longer side at most the
        guidance resolution (area-averaged), cached; "native"() gives the same photo at its own resolution, the one
        the base was trained at (uncached)."""
        index = step % len(self.train_dataset)
        cache = self.__dict__.setdefault("_photo_views", {})
        if index not in cache:
            cache[index] = {**self._photo_at(index, self.guidance_resolution), "index": index,
                            "native": lambda: self._photo_at(index, None)}
        return cache[index]

    def _photo_at(self, index: int, longer_side: Optional[int]) -> Dict:
        """Training photo `index` and its camera, area-averaged down to `longer_side` (None: as it is)."""
        dataset = self.train_dataset
        camera = dataset.cameras[index:index + 1]
        if longer_side is not None:
            camera.rescale_output_resolution(min(1.0, longer_side / float(max(camera.width, camera.height))))
        size = (int(camera.height), int(camera.width))
        image = dataset.get_image_float32(index)
        if tuple(image.shape[:2]) != size:
            image = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=size,
                                                    mode="area")[0].permute(1, 2, 0)
        return {"camera": camera.to(self.device), "image": image.to(self.device)}


def _concatenate(bundles) -> RayBundle:
    return RayBundle(
        origins=torch.cat([b.origins for b in bundles]),
        directions=torch.cat([b.directions for b in bundles]),
        pixel_area=torch.cat([b.pixel_area for b in bundles]),
        camera_indices=torch.cat([b.camera_indices for b in bundles]),
    )
