"""The photo anchor for Gaussians: the base's training photos, at their pixels whose ray keeps away from the
editable region, hold the edit to the base there."""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

Render = Callable[[Cameras, Tensor], Dict[str, Tensor]]
"""(camera, background) -> the edited scene's outputs ("rgb")."""


class SplatPhotoAnchor:
    """The anchor's loss on one photo, and which pixels of each photo it may use (cached per photo while beta and
    the threshold stay). What it needs of the model is given, not read from it."""

    def __init__(self, render: Render, composite: Callable[[Tensor, Tensor], Tensor],
                 away_from_edit: Callable[[Tensor, Tensor, Tensor, Tensor], Tensor],
                 explains_photos: Callable[[Tensor, Tensor], bool], photos_checked: Callable[[], bool]) -> None:
        """`composite(image, background)`: a photo on the render's background; `away_from_edit(origins, directions,
        nears, fars)`: which rays keep away from the editable region (on the model's device); `explains_photos(predicted, truth)`: the
        once-per-run check that the base explains its photos, `photos_checked()` whether it was made."""
        self.render, self.composite = render, composite
        self.away_from_edit, self.explains_photos, self.photos_checked = away_from_edit, explains_photos, photos_checked
        self.pixels: Dict[Tuple, Tensor] = {}

    def loss(self, photo: Dict, background: Tensor, metrics: Dict[str, Tensor], settings: Tuple) -> Optional[Tensor]:
        """MSE to one of the base's training photos at its pixels whose ray never comes near the editable region
        (None: no such pixel, or the base does not explain its photos). `settings`: what the pixels depend on
        besides the photo (beta, the threshold)."""
        if not self.photos_checked():
            # Judged at the photo's own resolution, the base's: far below it a render point-samples Gaussians the
            # downscaled photo averages over, and the base's own photos would score as another scene's.
            with torch.no_grad():
                native = self.anchored_pixels(photo["native"]() if "native" in photo else photo, None, background,
                                              settings)
            if native is None or not self.explains_photos(*native[:2]):
                return None
        anchored = self.anchored_pixels(photo, photo.get("index"), background, settings)
        if anchored is None:
            return None
        predicted, truth, safe = anchored
        metrics["photo_rays_kept"] = safe.float().mean()
        return torch.nn.functional.mse_loss(predicted.float(), truth.float())

    def anchored_pixels(self, photo: Dict, index: Optional[int], background: Tensor,
                        settings: Tuple) -> Optional[Tuple[Tensor, Tensor, Tensor]]:
        """(the edit's render, the photo) at the photo's pixels whose ray keeps away from the editable region, and
        which pixels those are; None if there is none. `index` caches the pixels per photo."""
        camera, image = photo["camera"], photo["image"]
        safe = self.pixels_kept(camera, index, settings)
        if not safe.any():
            return None
        outputs = self.render(camera, background)
        image = image.to(outputs["rgb"].device)
        if image.dtype == torch.uint8:
            image = image.float() / 255.0
        truth = self.composite(image.float(), background)
        return outputs["rgb"][safe], truth[safe], safe

    @torch.no_grad()
    def pixels_kept(self, camera: Cameras, index: Optional[int], settings: Tuple) -> Tensor:
        """(H, W) which pixels' rays keep away from the editable region."""
        key = (index, *settings, int(camera.width.reshape(-1)[0]))
        if index is None or key not in self.pixels:
            rays = camera.generate_rays(camera_indices=0, keep_shape=True)
            origins, directions = rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3)
            nears = torch.zeros(len(origins), 1, device=origins.device)
            fars = torch.full((len(origins), 1), 1e10, device=origins.device)
            self.pixels[key] = self.away_from_edit(origins, directions, nears, fars).reshape(rays.origins.shape[:-1])
        return self.pixels[key]
