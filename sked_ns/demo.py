"""`sked-demo`: the sketch geometry of the embedded demo scene, end to end on the CPU.

Writes the demo dataset and its two hat sketches, maps the sketches into nerfstudio's
model frame through the dataparser (as `ns-train sked` will), and renders the
preservation-weight field over the scene to `preservation_weights.png`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from sked_ns import demo_scene
from sked_ns.edit_box import compute_edit_box
from sked_ns.preservation import SketchDistanceField, check_beta, preservation_weight
from sked_ns.sketches import DataparserTransform, SketchSet, load_sketch_set, save_sketch_set

MARKER = ".sked-demo"  # marks a folder the demo made, so a rerun may replace it


def dataparser_transform_of(data: Path) -> DataparserTransform:
    """The transform nerfstudio's own dataparser applies to this dataset."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    outputs = NerfstudioDataParserConfig(data=data).setup().get_dataparser_outputs("train")
    return DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64), float(outputs.dataparser_scale))


def to_model(points: torch.Tensor, transform: DataparserTransform) -> torch.Tensor:
    matrix = torch.as_tensor(transform.transform, dtype=points.dtype)
    return (points @ matrix[:, :3].T + matrix[:, 3]) * transform.scale


def overlay(rgb: np.ndarray, weight: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Tint the surface red where it may change (w near 0), leave it as is where it is kept."""
    editable = (1.0 - weight)[..., None] * hit[..., None]
    return rgb * (1 - 0.7 * editable) + np.array([1.0, 0.1, 0.1]) * 0.7 * editable


def weight_slice(field: SketchDistanceField, transform: DataparserTransform, beta: float, size: int) -> np.ndarray:
    """Heat map of w on the vertical plane through the object facing the first sketch view."""
    axis = np.linspace(-1.0, 1.0, size)
    x, z = np.meshgrid(axis, axis[::-1], indexing="xy")
    points = torch.tensor(np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3), dtype=torch.float32)
    weight = field.preservation_weight(to_model(points, transform), beta).reshape(size, size).numpy()
    heat = cv2.applyColorMap((weight * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1] / 255.0
    inside = (demo_scene.sphere_sdf(points) < 0).reshape(size, size).numpy()
    heat[inside] = heat[inside] * 0.6 + 0.4  # outline the base object
    return heat


def run(output: Path, beta: float = 0.025, size: int = 256) -> dict:
    check_beta(beta)
    output = Path(output)
    if output.exists() and any(output.iterdir()) and not (output / MARKER).exists():
        raise FileExistsError(f"{output} exists and was not made by sked-demo: choose another --output.")
    output.mkdir(parents=True, exist_ok=True)
    (output / MARKER).touch()

    data = output / "data"
    demo_scene.write_demo_dataset(data)
    save_sketch_set(demo_scene.demo_sketch_set(), output / "sketches", overwrite=True)
    sketches: SketchSet = load_sketch_set(output / "sketches")  # the user's path: from disk
    transform = dataparser_transform_of(data)
    model_sketches = sketches.in_model_frame(transform)
    field = SketchDistanceField(model_sketches.views)
    edit_box = compute_edit_box(model_sketches.views, scene_box=np.array([[-1.0] * 3, [1.0] * 3]))

    # The edited object seen from a view that is not a sketch view.
    pose = demo_scene.orbit_pose(60.0, 25.0, 2.4)
    render = demo_scene.render(demo_scene.edited_sdf, pose, 1.2 * size, size, size)
    weight = field.preservation_weight(to_model(render["points"], transform), beta)
    weight = torch.where(render["hit"], weight, torch.ones_like(weight)).numpy()
    hit = render["hit"].numpy()
    on_hat = (demo_scene.hat_sdf(render["points"]) < 2e-3).numpy() & hit
    on_sphere = hit & ~on_hat

    first = model_sketches.views[0]
    first_render = demo_scene.render(demo_scene.edited_sdf, sketches.views[0].camera_to_world, first.fl_x, first.width, first.height)
    first_panel = overlay(first_render["rgb"].numpy(), 1.0 - first.mask.astype(float), np.ones_like(first.mask))
    panels = [
        cv2.resize(first_panel, (size, size), interpolation=cv2.INTER_NEAREST),
        overlay(render["rgb"].numpy(), weight, hit),
        weight_slice(field, transform, beta, size),
    ]
    image = (np.concatenate(panels, axis=1).clip(0, 1) * 255).round().astype(np.uint8)
    cv2.imwrite(str(output / "preservation_weights.png"), image[..., ::-1])

    summary = {
        "beta": beta,
        "edit_box_model_frame": {"min": edit_box.min.tolist(), "max": edit_box.max.tolist()},
        "mean_weight_on_hat": float(weight[on_hat].mean()),
        "mean_weight_on_sphere": float(weight[on_sphere].mean()),
        "image": str(output / "preservation_weights.png"),
    }
    (output / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def entrypoint() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--output", type=Path, default=Path("demo_output"), help="folder for everything the demo writes")
    parser.add_argument("--beta", type=float, default=0.025, help="preservation falloff, image widths")
    parser.add_argument("--size", type=int, default=256, help="render size in pixels")
    args = parser.parse_args()
    summary = run(args.output, args.beta, args.size)
    print(
        f"edit box (model frame): min {np.round(summary['edit_box_model_frame']['min'], 3).tolist()} "
        f"max {np.round(summary['edit_box_model_frame']['max'], 3).tolist()}\n"
        f"mean preservation weight on the hat: {summary['mean_weight_on_hat']:.3f} (edited), "
        f"on the sphere: {summary['mean_weight_on_sphere']:.3f} (kept)\n"
        f"wrote {summary['image']}  (left: sketch view 1 with its mask; middle: a new view, red = may change; "
        "right: w on a vertical slice)"
    )


if __name__ == "__main__":
    entrypoint()
