"""An edit of a photographed capture, measured at its held-out photos against the photos and the composite target.

    python benchmarks/capture_measure.py EDIT [--output results.json]

EDIT is a SKED edit's run folder whose guidance was the composite target (`--pipeline.model.guidance.primitive`,
docs/captures.md). At every photo nerfstudio held out for evaluation (its own split), through the photo's lens:

- kept content: PSNR and SSIM of the frozen base and of the edit against the photo outside the primitive's
  silhouette, and their difference (a base-photo gap is the base's, not the edit's); and the edit against its base
  there (what the edit moved);
- the changed region: the pixels where the edit differs from its base by over CHANGED against the composite's
  changed pixels (intersection over union), and the edit's PSNR against the composite inside the silhouette.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import harness
import torch

CHANGED = 0.1
"""A pixel the edit changed: its colour moved by over this (of 1) in some channel from the base's."""


def measure(edit: Path, photos: int = 0) -> dict:
    """The figures at the first `photos` held-out photos (0: all)."""
    from sked_ns.demo.composite_target import Primitive, composite_target
    from sked_ns.evaluation.metrics import psnr_inside, psnr_outside, ssim_outside
    from sked_ns.evaluation.render import load_pipeline, render_camera

    pipeline = load_pipeline(edit)
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    guidance = model.config.guidance
    if getattr(guidance, "primitive", "none") == "none":
        raise SystemExit(f"error: {edit}: not an edit towards the composite target (--pipeline.model.guidance.primitive)")
    primitive = Primitive.in_edit_box(guidance.primitive, guidance.primitive_colour, guidance.primitive_centre,
                                      guidance.primitive_size, model.edit_box)
    rows = []
    for index in range(len(dataset) if photos <= 0 else min(photos, len(dataset))):
        camera = dataset.cameras[index:index + 1]
        photo = dataset.get_image_float32(index)[..., :3]
        base, edited = (render_camera(model, camera, base=flag)["rgb"] for flag in (True, False))
        target = composite_target(model, primitive, camera)
        silhouette = target["silhouette"].cpu().float()
        changed = (edited - base).abs().amax(dim=-1) > CHANGED
        expected = target["changed"].cpu()
        union = (changed | expected).sum()
        rows.append({
            "photo": dataset.image_filenames[index].name,
            "base_psnr_photo": psnr_outside(base, photo, silhouette),
            "edit_psnr_photo": psnr_outside(edited, photo, silhouette),
            "base_ssim_photo": ssim_outside(base, photo, silhouette),
            "edit_ssim_photo": ssim_outside(edited, photo, silhouette),
            "edit_psnr_base": psnr_outside(edited, base, silhouette),
            "composite_changed_pixels": int(expected.sum()),
            "edit_changed_pixels": int(changed.sum()),
            "changed_iou": float((changed & expected).sum() / union) if union else None,
            "edit_psnr_composite_inside": (psnr_inside(edited, target["rgb"].cpu(), silhouette)
                                           if silhouette.any() else None),
        })
    for row in rows:
        row["kept_difference_db"] = row["edit_psnr_photo"] - row["base_psnr_photo"]
    mean = {key: sum(row[key] for row in rows) / len(rows) for key in rows[0]
            if all(isinstance(row[key], (int, float)) for row in rows)}
    return {"edit": str(edit), "changed_threshold": CHANGED, "photos": rows, "mean": mean}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("edit", type=Path)
    parser.add_argument("--output", type=Path)
    parser.add_argument("--photos", type=int, default=0, help="measure at the first N held-out photos (0: all)")
    arguments = parser.parse_args(argv)
    if arguments.output is not None:  # the one writer of the results file, before the minutes of measuring
        harness.claim("capture_measure.py", arguments.output)
    with torch.no_grad():
        result = measure(arguments.edit, arguments.photos)
    harness.publish(result, arguments.output)


if __name__ == "__main__":
    main(sys.argv[1:])
