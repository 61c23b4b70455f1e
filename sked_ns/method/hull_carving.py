"""Which new mass L_sil no longer needs: points whose sketch rays are already opaque.

L_sil asks each sketch ray for one opaque point and pulls every point of the ray's stretch of the visual
hull alike, so it fills the whole hull. Once every sketch ray through a point is opaque, that point's new
mass is no longer needed by any sketch: it stays only if the guidance asks for it. `SketchRayOpacity`
looks up, for any 3D point, the editable opacity its ray in each sketch view reached at the latest L_sil
render beyond the base's own (a table behind the sketch fills a ray without any new mass); the gate of L_new
(losses.new_mass_loss) is the smallest over the views, with pixels outside a sketch counting as opaque (no
sketch asks for new mass there at all). So L_new never competes with L_sil for a sketch ray the edit has not
filled yet, and empties the bulk of those it has.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from sked_ns.sketches.cameras import pixel_lookup, projection_rows
from sked_ns.sketches.sketch_set import SketchView

OPAQUE = 0.9
"""A sketch ray counts as filled from this new opacity on; the gate rises from 0 there to 1 at full opacity. A gate
linear in the opacity settles the edit at partial opacity (L_sil and L_new in balance: region IoS 0.69 instead of
1.0 on the demo hat without guidance); this one leaves every sketch ray at least this opaque."""


class SketchRayOpacity(nn.Module):
    """Per-point lookup into the sketch views' latest L_sil renders (their pixels concatenated, row-major, in the
    datamanager's order: `sketch_view_at(view, resolution)` for each view)."""

    def __init__(self, views: Sequence[SketchView], resolution: int) -> None:
        super().__init__()
        from sked_ns.sketches.sketch_set import sketch_view_at

        cameras = [sketch_view_at(view, resolution)[0] for view in views]
        widths = [int(camera.width) for camera in cameras]
        heights = [int(camera.height) for camera in cameras]
        starts = torch.tensor([0] + [w * h for w, h in zip(widths, heights)][:-1]).cumsum(0)
        intrinsics = torch.tensor([[float(c.fx), float(c.fy), float(c.cx), float(c.cy)] for c in cameras],
                                  dtype=torch.float64)
        camera_to_worlds = torch.cat([camera.camera_to_worlds for camera in cameras]).double()
        self.register_buffer("rows", projection_rows(camera_to_worlds, intrinsics).float(), persistent=False)
        self.register_buffer("starts", starts[:, None], persistent=False)
        self.register_buffer("sizes", torch.tensor([widths, heights], dtype=torch.float32)[..., None], persistent=False)
        self.num_pixels = sum(w * h for w, h in zip(widths, heights))

    @torch.no_grad()
    def gate(self, points: Tensor, opacity: Tensor, masks: Tensor, opaque: float = OPAQUE) -> Tensor:
        """min over views of how far past `opaque` the opacity at the sketch pixel each point (..., 3) projects to
        is, (opacity - opaque) / (1 - opaque) clamped to [0, 1]; 1 where it projects outside a view's sketch (or its
        image, or lies behind its camera). `opacity`, `masks`: the flat L_sil render and masks. Returns (..., 1)."""
        flat = points.reshape(-1, 3).float()
        opacity = ((opacity.detach().reshape(-1).float() - opaque) / max(1.0 - opaque, 1e-6)).clamp(0.0, 1.0)
        masks = masks.reshape(-1) > 0.5
        if opacity.numel() != self.num_pixels or masks.numel() != self.num_pixels:
            raise ValueError(f"L_sil render has {opacity.numel()} pixels and {masks.numel()} mask pixels; the sketch "
                             f"views hold {self.num_pixels}.")
        pixel, pixel_in, index, in_front = pixel_lookup(flat, self.rows, self.sizes, self.starts)
        on_sketch = in_front & (pixel == pixel_in).all(dim=0) & masks[index]
        per_view = torch.where(on_sketch, opacity[index], torch.ones_like(index, dtype=opacity.dtype))
        return per_view.amin(dim=0).reshape(*points.shape[:-1], 1)
