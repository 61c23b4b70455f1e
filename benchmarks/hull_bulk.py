"""How much of the sketches' visual hull an edit has filled beyond the intended part (issue 23).

    python benchmarks/hull_bulk.py EDIT_RUN SCENE SKETCHES [--png top.png]

A grid over the edit box (in the benchmark scene's data frame), kept where every sketch's mask agrees
(the visual hull). At each point the new occupancy the edit made, relu(alpha_edit - alpha_base) with
alpha = 1 - exp(-sigma delta) at L_pres's fixed delta, is averaged over the hull points on the exact
added part (`part`) and over those farther than `margin` from it (`bulk`): a bulky edit has bulk near
part, a shaped one bulk near 0. `--png` writes the largest new occupancy seen from above (the hull's
outline in grey): the shape the novel views see.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch

MARGIN = 0.03
"""Hull points this far (data-frame units) from the added part count as bulk: about a pixel and a half of the
sketch views, past the masks' 3 px dilation's reach on the part's sides."""


def hull_bulk(edit_run: Path, scene: str, sketches: Path, samples: int = 64, margin: float = MARGIN,
              png: Optional[Path] = None) -> Dict[str, float]:
    """The figures of a saved edit run (module docstring)."""
    from sked_ns.demo.scenes.catalogue import scene_named
    from sked_ns.evaluation.render import load_pipeline
    from sked_ns.sketches.sketch_set import DataparserTransform, load_sketch_set

    model = load_pipeline(edit_run).model
    transform = DataparserTransform.from_json(edit_run / "dataparser_transforms.json")
    return model_bulk(model, transform, scene_named(scene).edit_sdf, load_sketch_set(sketches).views, samples,
                      margin, png)


@torch.no_grad()
def model_bulk(model, transform, part_sdf, views, samples: int = 64, margin: float = MARGIN,
               png: Optional[Path] = None) -> Dict[str, float]:
    """The figures of a NeRF edit model (a local residual or a whole-field copy, with `base_field`): `transform` maps the data
    frame, where `part_sdf` (the added part's signed distance) and the sketch `views` live, to the model's."""
    from sked_ns.method.edit_box import compute_edit_box
    from sked_ns.method.preservation import SketchDistanceField

    box = compute_edit_box(views)
    counts = np.maximum(8, np.ceil(samples * box.size / box.size.max())).astype(int)
    axes = [np.linspace(box.min[k], box.max[k], counts[k]) for k in range(3)]
    grid = torch.tensor(np.stack(np.meshgrid(*axes, indexing="ij"), -1), dtype=torch.float32)
    points = grid.reshape(-1, 3)
    inside = SketchDistanceField(views).hull_distance(points) <= 0
    distance = part_sdf(points)
    model_points = transform.points_to_model(points)
    delta = model.config.preservation_delta

    def alpha(density_fn) -> torch.Tensor:
        densities = torch.cat([density_fn(chunk)[..., 0] for chunk in model_points.split(1 << 15)])
        return 1.0 - torch.exp(-densities.clamp_min(0) * delta)

    # A local edit's density is its base's moved by its residual; a whole-field copy's is its own field's.
    edited = model.field_density if getattr(model, "local_field", None) is not None else model.field.density_fn
    new = (alpha(edited) - alpha(model.base_field.density_fn)).clamp_min(0)
    part, bulk = inside & (distance < 0), inside & (distance > margin)
    result = {"hull_points": int(inside.sum()), "part_points": int(part.sum()), "bulk_points": int(bulk.sum()),
              "part": float(new[part].mean()) if part.any() else float("nan"),
              "bulk": float(new[bulk].mean()) if bulk.any() else float("nan"),
              "bulk_over_half": float((new[bulk] > 0.5).float().mean()) if bulk.any() else float("nan")}
    if png is not None:
        import cv2

        seen = torch.where(inside, new, torch.zeros_like(new)).reshape(grid.shape[:3]).amax(dim=2)
        outline = inside.reshape(grid.shape[:3]).any(dim=2).float() * 0.25
        on_part = (distance < 0).reshape(grid.shape[:3]).any(dim=2)
        image = torch.stack([seen, torch.maximum(seen, outline), torch.where(on_part, 1.0, outline)], -1)
        image = image.flip(1).transpose(0, 1).numpy()  # rows: y down the page; columns: x
        cv2.imwrite(str(png), cv2.resize((image[..., ::-1] * 255).astype(np.uint8), None, fx=4, fy=4,
                                         interpolation=cv2.INTER_NEAREST))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("edit_run", type=Path)
    parser.add_argument("scene")
    parser.add_argument("sketches", type=Path)
    parser.add_argument("--png", type=Path, default=None)
    args = parser.parse_args()
    print(json.dumps(hull_bulk(args.edit_run, args.scene, args.sketches, png=args.png), indent=2))


if __name__ == "__main__":
    main()
