"""Two sketch views (issue 23): their visual hull is bulkier than the part, and L_new keeps the edit from filling it.

L_sil asks each sketch ray for one opaque point but pulls every point of the ray's stretch of the hull alike, so
it fills the hull; once a ray is opaque its pull vanishes, but nothing removes the mass no loss asks for. L_new
(the opacity the edit adds over the base) does.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sked_ns.method.losses import new_mass_loss, silhouette_loss

DELTA = 0.07


def test_the_marker_scenes_hull_is_much_larger_than_the_marker():
    from sked_ns.demo.scenes.objects import SCENES
    from sked_ns.drawing.hull_check import check_hull
    from sked_ns.method.edit_box import compute_edit_box
    from sked_ns.method.preservation import SketchDistanceField

    scene = SCENES["marker"]
    views = scene.sketch_set().views
    assert len(views) == 2
    assert check_hull(views).underdetermined  # measured 3.4x from above
    box = compute_edit_box(views)
    axes = [np.linspace(box.min[k], box.max[k], 48) for k in range(3)]
    points = torch.tensor(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), dtype=torch.float32)
    hull = SketchDistanceField(views).hull_distance(points) <= 0
    part = scene.edit_sdf(points) < 0
    assert (part & ~hull).sum() <= 0.01 * part.sum()  # the sketches hold the marker
    assert hull.sum() > 5 * part.sum()  # measured 8.6x


def _toy_two_view_edit(lambda_new: float, steps: int = 150) -> dict:
    """A 2-D density grid seen by two orthographic sketch views (rows and columns) whose masks are the silhouettes
    of a diagonal part: their hull is the whole square, the part its diagonal. Starts as L_sil leaves it, the hull
    filled evenly; a stand-in guidance asks for the part (its cells opaque) and says nothing of the rest."""
    size = 12
    part = torch.eye(size, dtype=torch.bool)
    log_density = torch.full((size, size), float(np.log(8.0)), requires_grad=True)  # each ray opaque: 12 x 8 x 0.07
    optimiser = torch.optim.Adam([log_density], lr=0.05)
    masks = torch.ones(2, size)
    for _ in range(steps):
        density = log_density.exp()
        rows, columns = density.sum(dim=1) * DELTA, density.sum(dim=0) * DELTA
        accumulation = 1.0 - torch.exp(-torch.stack([rows, columns]))
        guidance = (torch.exp(-density[part] * DELTA)).mean()  # transparency where the part is: wants it solid
        loss = silhouette_loss(accumulation, masks) + guidance
        if lambda_new:
            loss = loss + lambda_new * new_mass_loss(density[..., None], torch.zeros(size, size, 1),
                                                     torch.zeros(size, size, 1), DELTA)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        density = log_density.exp()
        alpha = 1.0 - torch.exp(-density * DELTA)
        rays = 1.0 - torch.exp(-torch.stack([density.sum(dim=1), density.sum(dim=0)]) * DELTA)
    return {"bulk": float(alpha[~part].mean()), "part": float(alpha[part].mean()), "rays": float(rays.min())}


def test_without_l_new_the_filled_hull_stays_filled_with_it_only_the_part_remains():
    paper, ours = _toy_two_view_edit(0.0), _toy_two_view_edit(1.0)
    # Measured (150 Adam steps): bulk alpha 0.43 -> 0.69 without L_new (L_sil keeps pulling it up), -> 0.016 with it
    # (0.014-0.017 at weights 0.3-5); the part and every sketch ray stay opaque either way.
    assert paper["bulk"] > 0.4, paper
    assert ours["bulk"] < 0.1 * paper["bulk"], ours
    assert ours["part"] > 0.9 and ours["rays"] > 0.99, ours


def test_l_new_alone_cannot_empty_the_sketch_rays():
    # No guidance stand-in: L_sil holds each ray opaque against L_new (where along the ray is then open).
    size = 12
    log_density = torch.full((size, size), float(np.log(8.0)), requires_grad=True)
    optimiser = torch.optim.Adam([log_density], lr=0.05)
    for _ in range(150):
        density = log_density.exp()
        accumulation = 1.0 - torch.exp(-torch.stack([density.sum(dim=1), density.sum(dim=0)]) * DELTA)
        loss = silhouette_loss(accumulation, torch.ones(2, size)) + new_mass_loss(
            density[..., None], torch.zeros(size, size, 1), torch.zeros(size, size, 1), DELTA)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert float(accumulation.min()) > 0.5



def test_sketch_ray_opacity_reads_the_pixel_each_point_projects_to():
    from sked_ns.demo.scenes.objects import SCENES
    from sked_ns.method.hull_carving import SketchRayOpacity
    from sked_ns.sketches.cameras import pixel_directions
    from sked_ns.sketches.sketch_set import sketch_view_at

    views = SCENES["marker"].sketch_set(64).views
    lookup = SketchRayOpacity(views, 24)
    first, mask = sketch_view_at(views[0], 24)
    masks = torch.cat([sketch_view_at(view, 24)[1].flatten() for view in views]).float()
    opacity = torch.rand(lookup.num_pixels, generator=torch.Generator().manual_seed(0))
    height, width = mask.shape
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixels = torch.stack([u.flatten() + 0.5, v.flatten() + 0.5], dim=-1).float()
    intrinsics = torch.tensor([float(first.fx), float(first.fy), float(first.cx), float(first.cy)])
    pose = first.camera_to_worlds[0]
    points = pose[:, 3] + 2.0 * pixel_directions(pixels, pose, intrinsics)  # depth 2 along each pixel's ray
    single = SketchRayOpacity(views[:1], 24).gate(points, opacity[:height * width], masks[:height * width],
                                                  opaque=0.0)[..., 0]
    on = mask.flatten()
    torch.testing.assert_close(single[on], opacity[:height * width][on])  # a sketch pixel: its ray's opacity
    past = SketchRayOpacity(views[:1], 24).gate(points, opacity[:height * width], masks[:height * width])[..., 0]
    torch.testing.assert_close(past[on], ((opacity[:height * width][on] - 0.9) / 0.1).clamp(0, 1))  # past OPAQUE
    assert (single[~on] == 1).all()  # off the sketch no sketch asks for mass: fully gated in
    both = lookup.gate(points, opacity, masks, opaque=0.0)[..., 0]
    assert (both <= single + 1e-6).all() and both.shape == single.shape  # the smallest over the views
    assert (lookup.gate(points, torch.ones_like(opacity), masks) == 1).all()
    assert (lookup.gate(points, torch.zeros_like(opacity), masks)[..., 0][on] == 0).all()
    assert lookup.gate(torch.full((3, 3), float("nan")), opacity, masks).isfinite().all()


@pytest.fixture(scope="module")
def silhouette_only_bulk(scene, tmp_path_factory):
    """Hat edits of the demo base with guidance off (weight 0): L_sil alone grows the mass, in the hat's two-view
    hull, at half the base's samples; the hull's new occupancy off the hat (bulk) and on it. Cached per weight."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from hull_bulk import model_bulk

    from sked_ns.demo.scenes.sphere import SCENES
    from sked_ns.engine.edit_run import edit_config, run_edit
    from sked_ns.evaluation.metrics import intersection_over_sketch
    from sked_ns.evaluation.render import render_at, resized_mask
    from sked_ns.sketches.sketch_set import DataparserTransform, load_sketch_set

    root, runs = tmp_path_factory.mktemp("two-view"), {}

    def run(lambda_new: float) -> dict:
        if lambda_new not in runs:
            config = edit_config(scene["base"], scene["data"], scene["sketches"], root / str(lambda_new), iterations=40,
                                 guidance_resolution=24, silhouette_resolution=24, steps_per_save=10**6)
            model_config = config.pipeline.model
            model_config.guidance.weight, model_config.samples_per_ray_scale = 0.0, 0.5
            model_config.lambda_photo, model_config.lambda_new_mass = 0.0, lambda_new
            # L_new's gate as measured against the paper's model, a trainable copy of the whole field (the default,
            # pinned): the local residual empties its sketches under L_new alone (docs/benchmarks.md, How fast a local
            # edit fills and carves).
            model_config.nerf_edit_field = "full-copy"
            trainer = run_edit(config)
            transform = DataparserTransform.from_json(config.get_base_dir() / "dataparser_transforms.json")
            model = trainer.pipeline.model
            runs[lambda_new] = model_bulk(model, transform, SCENES["hat"].edit_sdf,
                                          load_sketch_set(scene["sketches"]).views, samples=40)
            masks = [resized_mask(view, 32) for view in model.sketch_set.views]
            runs[lambda_new]["ios"] = float(np.mean([intersection_over_sketch(render_at(model, view, 32)["accumulation"],
                                                                              mask)
                                                     for view, mask in zip(model.sketch_set.views, masks)]))
        return runs[lambda_new]
    return run


def test_l_new_thins_the_hull_l_sil_grows_and_the_sketches_stay_filled(silhouette_only_bulk):
    """With the guidance off nothing asks for the hat's shape: L_sil alone fills the hull, and L_new (gated: only
    where the sketch rays are already opaque with new mass) thins what L_sil no longer needs without emptying it.
    With a gate linear in the opacity (no OPAQUE threshold) the sketches settled at region IoS 0.69 (paper 1.0)."""
    paper, ours = silhouette_only_bulk(0.0), silhouette_only_bulk(1.0)
    assert paper["bulk"] > 0.1, paper
    assert ours["bulk"] < 0.7 * paper["bulk"], (paper, ours)
    assert ours["ios"] > 0.6 and ours["ios"] > paper["ios"] - 0.2, (paper, ours)
