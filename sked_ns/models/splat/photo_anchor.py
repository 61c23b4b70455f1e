"""The photo anchor for Gaussians: the base's training photos, at their pixels whose ray keeps away from the
editable region, hold the edit to the base there."""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from sked_ns.method.photo_anchor import rays_away_from_edit


class SplatPhotoAnchor:
    """Mixed into the splat edit model (which renders with `_render_edit` and composites on a background)."""

    def _photo_anchor(self, photo: Dict, background: Tensor, metrics: Dict[str, Tensor]) -> Optional[Tensor]:
        """MSE to one of the base's training photos at its pixels whose ray never comes near the editable region
        (None: no such pixel, or the base does not explain its photos)."""
        if not self._photos_checked:
            # Judged at the photo's own resolution, the base's: far below it a render point-samples Gaussians the
            # downscaled photo averages over, and the base's own photos would score as another scene's.
            with torch.no_grad():
                native = self._anchored_pixels(photo["native"]() if "native" in photo else photo, None, background)
            if native is None or not self.check_photos_once(*native[:2]):
                return None
        anchored = self._anchored_pixels(photo, photo.get("index"), background)
        if anchored is None:
            return None
        predicted, truth, safe = anchored
        metrics["photo_rays_kept"] = safe.float().mean()
        return torch.nn.functional.mse_loss(predicted.float(), truth.float())

    def _anchored_pixels(self, photo: Dict, index: Optional[int],
                      background: Tensor) -> Optional[Tuple[Tensor, Tensor, Tensor]]:
        """(the edit's render, the photo) at the photo's pixels whose ray keeps away from the editable region, and
        which pixels those are; None if there is none. `index` caches the pixels per photo."""
        camera, image = photo["camera"], photo["image"].to(self.device)
        safe = self._photo_pixels_kept(camera, index)
        if not safe.any():
            return None
        outputs = self._render_edit(camera, background)
        if image.dtype == torch.uint8:
            image = image.float() / 255.0
        truth = self.composite_with_background(image.float(), background)
        return outputs["rgb"][safe], truth[safe], safe

    @torch.no_grad()
    def _photo_pixels_kept(self, camera: Cameras, index: Optional[int]) -> Tensor:
        """(H, W) which pixels' rays keep away from the editable region; cached per photo while beta stays."""
        key = (index, self.config.beta, self.config.photo_threshold, int(camera.width.reshape(-1)[0]))
        if index is None or key not in self._photo_pixels:
            rays = camera.generate_rays(camera_indices=0, keep_shape=True).to(self.device)
            origins, directions = rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3)
            nears = torch.zeros(len(origins), 1, device=self.device)
            fars = torch.full((len(origins), 1), 1e10, device=self.device)
            safe = rays_away_from_edit(origins, directions, nears, fars, self.editable_box(),
                                       lambda p: self.preservation_weight(p)[..., 0], self.config.photo_threshold)
            self._photo_pixels[key] = safe.reshape(rays.origins.shape[:-1])
        return self._photo_pixels[key]
