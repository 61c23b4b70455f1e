"""An edit of a photographed capture, measured at its held-out photos against the photos and the composite target.

    python benchmarks/capture_measure.py EDIT [--output results.json]

EDIT is a SKED edit's run folder whose guidance was the composite target (`--pipeline.model.guidance.primitive`,
docs/captures.md). At every photo nerfstudio held out for evaluation (its own split), through the photo's lens:

- kept content: PSNR and SSIM of the frozen base and of the edit against the photo outside the primitive's
  silhouette, and their difference (a base-photo gap is the base's, not the edit's); and the edit against its base
  there (what the edit moved);
- what the edit must not do there: `leak` (sked-eval's: new opacity outside the silhouette; a capture's wall
  makes every pixel opaque already, so also `changed_outside_share`: the share of pixels outside the silhouette
  whose colour moved by over CHANGED);
- the changed region: the pixels where the edit differs from its base by over CHANGED against the composite's
  changed pixels (intersection over union), and the edit's PSNR against the composite inside the silhouette.

At the sketch views (SKETCH_RESOLUTION px, as sked-eval): IoS of the edit and its base (any opacity, so the wall
behind a sketch fills it before any edit), region IoS (opacity of content near the sketches only), the primitive's own
IoS (its silhouette's share of the sketch), the share the composite shows it in (depth-tested) and, of those pixels,
the share the edit changed by over CHANGED (`fill_shown`).
With --strip, a PNG of photo | base | edit | |edit - base| x DIFFERENCE_GAIN at the first held-out photos.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence

import harness
import torch

CHANGED = 0.1
"""A pixel the edit changed: its colour moved by over this (of 1) in some channel from the base's."""
SKETCH_RESOLUTION = 64
"""The sketch views' render side for IoS, px (sked-eval's benchmark setting)."""
DIFFERENCE_GAIN = 4
"""The strip's difference column: |edit - base| times this, so a small change shows."""


def sketch_views(model, primitive) -> dict:
    """IoS and region IoS of the edit and its frozen base at each sketch view, the IoS of the `primitive`'s silhouette
    ("ios_target") and of the part where the composite shows it ("ios_target_shown", depth-tested against the base:
    what an edit that made exactly the target would fill of the sketch)."""
    from sked_ns.evaluation.metrics import intersection_over_sketch
    from sked_ns.evaluation.render import render_at, render_base_at, resized_mask
    from sked_ns.sketches.sketch_set import sketch_view_at

    rows = []
    for view in model.sketch_set.views:
        edited, base = render_at(model, view, SKETCH_RESOLUTION), render_base_at(model, view, SKETCH_RESOLUTION)
        mask = resized_mask(view, SKETCH_RESOLUTION)
        row = {"view": view.name, "ios": intersection_over_sketch(edited["accumulation"], mask),
               "ios_base": intersection_over_sketch(base["accumulation"], mask)}
        target = composite_target(model, primitive, sketch_view_at(view, SKETCH_RESOLUTION)[0])
        row["ios_target"] = intersection_over_sketch(target["silhouette"].float(), mask)
        # Where the base's own content stands in front of the part, the target shows the base: no edit fills there.
        shown = target["changed"].cpu() & mask.bool()
        row["ios_target_shown"] = intersection_over_sketch(shown.float(), mask)
        # Of the sketch pixels where the target shows the part, those the edit changed (edit_quality's fill; the
        # region IoS also weighs opacity by 1 - w, which the preservation falloff keeps below 1 at the hull's rim).
        moved = (edited["rgb"] - base["rgb"]).abs().amax(dim=-1) > CHANGED
        row["fill_shown"] = float((moved & shown).sum() / shown.sum()) if shown.any() else None
        if "preservation_weight" in edited:
            row["ios_region"] = intersection_over_sketch(1.0 - edited["preservation_weight"], mask)
            row["ios_region_base"] = intersection_over_sketch(1.0 - base["preservation_weight"], mask)
        rows.append(row)
    return {"views": rows, "mean": view_means(rows)}


def view_means(rows: Sequence[dict], label: str = "view") -> dict:
    """Each figure's mean over the views (photos) that have it: one where neither the target nor the edit shows the
    part has no fill or changed IoU to score (None), and leaving it out must not drop the others' figure."""
    scored = {key: [row[key] for row in rows if isinstance(row.get(key), (int, float))] for key in rows[0] if key != label}
    return {key: sum(values) / len(values) for key, values in scored.items() if values}


def composite_target(model, primitive, camera) -> dict:
    """sked_ns.demo.composite_target's target at a photo's camera, keeping the frozen base's render whole ("base":
    rgb and accumulation; the model in eval mode, as `render_camera` renders it), so the base renders once."""
    from sked_ns.demo.composite_target import composite, render_base_with_depth

    base = {key: value.cpu() for key, value in render_base_with_depth(model, camera).items()}
    cast = primitive.cast(base["origins"].double(), base["directions"].double())
    cast = {"hit": cast["hit"], "distance": cast["distance"].to(base["depth"]), "rgb": cast["rgb"].to(base["rgb"])}
    return {**composite(base, cast), "base": base, "silhouette": cast["hit"]}


def save_strip(tiles: list, path: Path) -> None:
    """Rows of (photo, base, edit, edit - base) tiles, one row a photo, as one PNG."""
    from PIL import Image

    rows = [torch.cat([photo, base, edited, ((edited - base).abs() * DIFFERENCE_GAIN).clamp(0, 1)], dim=1)
            for photo, base, edited in tiles]
    Image.fromarray((torch.cat(rows, dim=0).clamp(0, 1) * 255).round().byte().numpy()).save(path)


def measure(edit: Path, photos: int = 0, strip: Optional[Path] = None, strip_photos: int = 3,
            indices: Optional[Sequence[int]] = None, sketch: bool = True) -> dict:
    """The figures at the first `photos` held-out photos (0: all) or at those `indices`, and at the sketch views
    unless not `sketch`; `strip`: where the pictures of the first `strip_photos` measured go."""
    from sked_ns.demo.composite_target import target_primitive
    from sked_ns.evaluation.metrics import psnr_inside, psnr_outside, ssim_outside
    from sked_ns.evaluation.render import load_pipeline, render_camera

    pipeline = load_pipeline(edit)
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    model.eval()
    guidance = model.config.guidance
    if getattr(guidance, "primitive", "none") == "none":
        raise SystemExit(f"error: {edit}: not an edit towards the composite target (--pipeline.model.guidance.primitive)")
    primitive = target_primitive(model, guidance.primitive, guidance.primitive_colour, guidance.primitive_centre,
                                 guidance.primitive_size)
    rows, tiles = [], []
    if indices is None:
        indices = range(len(dataset) if photos <= 0 else min(photos, len(dataset)))
    for index in indices:
        camera = dataset.cameras[index:index + 1]
        photo = dataset.get_image_float32(index)[..., :3]
        renders = {False: render_camera(model, camera)}
        target = composite_target(model, primitive, camera)
        renders[True] = target["base"]
        base, edited = renders[True]["rgb"], renders[False]["rgb"]
        silhouette = target["silhouette"].cpu().float()
        changed = (edited - base).abs().amax(dim=-1) > CHANGED
        expected = target["changed"].cpu()
        union = (changed | expected).sum()
        outside = ~silhouette.bool()
        accumulation = {flag: render["accumulation"] for flag, render in renders.items()}
        if strip is not None and len(tiles) < strip_photos:
            tiles.append((photo, base, edited))
        rows.append({
            "photo": dataset.image_filenames[index].name,
            "base_psnr_photo": psnr_outside(base, photo, silhouette),
            "edit_psnr_photo": psnr_outside(edited, photo, silhouette),
            "base_ssim_photo": ssim_outside(base, photo, silhouette),
            "edit_ssim_photo": ssim_outside(edited, photo, silhouette),
            "edit_psnr_base": psnr_outside(edited, base, silhouette),
            "leak": float((accumulation[False] - accumulation[True]).clamp_min(0)[outside].mean()),
            "changed_outside_share": float((changed & outside).sum() / outside.sum()),
            "composite_changed_pixels": int(expected.sum()),
            "edit_changed_pixels": int(changed.sum()),
            "changed_iou": float((changed & expected).sum() / union) if union else None,
            "edit_psnr_composite_inside": (psnr_inside(edited, target["rgb"].cpu(), silhouette)
                                           if silhouette.any() else None),
        })
    for row in rows:
        row["kept_difference_db"] = row["edit_psnr_photo"] - row["base_psnr_photo"]
    mean = view_means(rows, "photo")
    if tiles:
        save_strip(tiles, strip)
    return {"edit": str(edit), "changed_threshold": CHANGED, "photos": rows, "mean": mean,
            **({"sketch_views": sketch_views(model, primitive)} if sketch else {}), **({"strip": str(strip)} if tiles else {})}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("edit", type=Path)
    parser.add_argument("--output", type=Path)
    parser.add_argument("--photos", type=int, default=0, help="measure at the first N held-out photos (0: all)")
    parser.add_argument("--strip", type=Path, help="a PNG of photo | base | edit | difference at three held-out photos")
    parser.add_argument("--indices", type=int, nargs="+", help="measure at these held-out photos (their split's order)")
    parser.add_argument("--no-sketch-views", action="store_true", help="leave the sketch views out")
    arguments = parser.parse_args(argv)
    if arguments.output is not None:  # the one writer of the results file, before the minutes of measuring
        harness.claim("capture_measure.py", arguments.output)
    with torch.no_grad():
        result = measure(arguments.edit, arguments.photos, arguments.strip, indices=arguments.indices,
                         sketch=not arguments.no_sketch_views)
    harness.publish(result, arguments.output)


if __name__ == "__main__":
    main(sys.argv[1:])
