"""The sampler the edit trains and renders with (issue 12: anneal, SKED's step, NGP culling, the base's sampler)."""

from __future__ import annotations

import torch
from nerfstudio.field_components.field_heads import FieldHeadNames

from sked_ns.engine.edit_run import edit_config, run_edit
from sked_ns.engine.trainer import resolve_edit
from sked_ns.evaluation.render import load_pipeline


def _pipeline(scene, tmp_path, **model_settings):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=1)
    for key, value in model_settings.items():
        setattr(config.pipeline.model, key, value)
    resolve_edit(config)
    return config.pipeline.setup(device="cpu", test_mode="val")


def test_nerfacto_edit_samples_the_base_fully_annealed_from_step_0(scene, tmp_path):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=2,
                         guidance_resolution=8, silhouette_resolution=8)
    anneals = []
    trainer = _setup(config)
    iteration = trainer.train_iteration
    trainer.train_iteration = lambda step: (anneals.append(trainer.pipeline.model.proposal_sampler._anneal), iteration(step))[1]
    trainer.train()
    # nerfacto's own anneal would start at 0: weights ** 0 = uniform sampling of the trained base.
    assert anneals == [1.0, 1.0]


def test_warmup_fades_with_the_proposal_anneal_off(scene, tmp_path):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=6,
                         guidance_resolution=8, silhouette_resolution=8)
    config.pipeline.model.use_proposal_weight_anneal = False
    config.pipeline.model.edit_box_warmup = 4
    boosts = []
    trainer = _setup(config)
    iteration = trainer.train_iteration
    trainer.train_iteration = lambda step: (boosts.append(trainer.pipeline.model.edit_box_boost()), iteration(step))[1]
    trainer.train()
    assert boosts == [1.0, 0.75, 0.5, 0.25, 0.0, 0.0]


def test_a_loaded_edit_renders_with_the_sampler_training_ended_with(scene, tmp_path):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=6,
                         guidance_resolution=8, silhouette_resolution=8, steps_per_save=100)
    config.pipeline.model.edit_box_warmup = 3
    run = run_edit(config).base_dir
    loaded = load_pipeline(run).model  # as ns-render, ns-viewer, ns-export and sked-eval load it
    assert loaded.sked_step == 5 and loaded.edit_box_boost() == 0.0
    # The step also travels in the weights themselves, for loaders that never call update_to_step.
    fresh = _pipeline(scene, tmp_path / "fresh")
    assert fresh.model.edit_box_boost() == 1.0
    checkpoint = torch.load(next((run / "nerfstudio_models").glob("*.ckpt")), map_location="cpu")
    fresh.load_state_dict(checkpoint["pipeline"])
    assert fresh.model.sked_step == 5 and fresh.model.edit_box_boost() == 0.0


def test_ngp_training_renders_keep_the_empty_edit_box_samples(ngp_scene, tmp_path):
    pipeline = _pipeline(ngp_scene, tmp_path)
    model = pipeline.model.train()
    assert model.config.alpha_thre > 0  # instant-ngp's default culls samples with alpha below it
    box_min = torch.tensor(model.edit_box.min, dtype=torch.float32)
    box_max = torch.tensor(model.edit_box.max, dtype=torch.float32)
    rays = model._collide(pipeline.datamanager.sketch_rays)
    with model._average_appearance():
        _, samples, field_outputs = model._render(rays)
    positions = samples.frustums.get_positions().reshape(-1, 3)
    inside = ((positions >= box_min) & (positions <= box_max)).all(-1)
    empty = field_outputs[FieldHeadNames.DENSITY].reshape(-1) * model.config.render_step_size < model.config.alpha_thre
    # At step 0 the new content's cells are empty (alpha ~0): culling them would leave L_sil no gradient there.
    assert (inside & empty).sum() > 100, int((inside & empty).sum())


def test_ngp_base_renders_deterministically_with_its_own_density(ngp_scene, tmp_path):
    model = _pipeline(ngp_scene, tmp_path).model.eval()
    base_sampler = model.frozen_base.sampler
    assert base_sampler.density_fn is not None, "the base's sampler culls with the base's density in training"
    rays = model._collide(_sketch_rays(model))
    first, second = model.render_base(rays), model.render_base(rays)
    assert torch.equal(first["rgb"], second["rgb"]), "evaluation renders of the base are not jittered"
    model.train()
    assert model.render_base(rays)["rgb"].shape == first["rgb"].shape and base_sampler.training


def _sketch_rays(model):
    from sked_ns.sketches.sketch_set import sketch_view_at

    camera, _ = sketch_view_at(model.sketch_set.views[0], 24)
    return camera.generate_rays(camera_indices=0, keep_shape=True).flatten()


def _setup(config):
    config.set_timestamp()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def _box_points(model, count=20_000):
    generator = torch.Generator().manual_seed(0)
    low, high = (torch.tensor(v, dtype=torch.float32) for v in (model.edit_box.min, model.edit_box.max))
    return low + torch.rand(count, 3, generator=generator) * (high - low)


def test_nerfacto_warmup_boost_lands_only_in_the_sketches_visual_hull(scene, tmp_path):
    """New mass belongs where every sketch agrees; boosting the box's empty corners grows haze (issue 9)."""
    model = _pipeline(scene, tmp_path).model
    points = _box_points(model)
    hull = model.in_sketch_hull(points)
    assert 0.02 < hull.float().mean() < 0.9  # the hull is a real part of the box, not all of it
    model.eval()  # kept space from the base's proposal networks, not the training step's grid of them
    with torch.no_grad():
        boosted = model.density_fns[0](points[:, None, :])[:, 0, 0]
        plain = model.proposal_networks[0].density_fn(points[:, None, :])[:, 0, 0]
    added = boosted - plain
    assert (added[hull] > 0).all() and (added[~hull].abs() < 1e-6).all()


def test_ngp_switches_on_only_the_cells_the_visual_hull_reaches(ngp_scene, tmp_path):
    from sked_ns.models.nerf.occupancy import occupied

    model = _pipeline(ngp_scene, tmp_path).model
    grid = model.occupancy_grid
    # Offered every cell of the grid, the hull keeps only a few near the sketches (the demo's box is so tight
    # at 32^3 that all its own cells touch the hull: offer more to see the filter work).
    everything = torch.ones_like(model.edit_box_cells)
    reached = model._hull_cells(everything)
    assert 0 < reached.sum() < 0.05 * everything.sum() and (model.edit_box_cells <= reached).all()
    # Every box point inside the hull lies in a switched-on cell.
    points = _box_points(model)
    inside = points[model.in_sketch_hull(points)]
    assert len(inside) > 100 and occupied(model.edit_box_cells, grid.aabbs.cpu(), inside).all()
