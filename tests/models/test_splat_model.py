"""The splatfacto edit model (sked_ns/models/splat/model.py) on a tiny splat base saved as `ns-train splatfacto` saves one.

The base is Gaussians on the demo sphere (not fitted: these tests need a real run folder, not a good scene); the
renders are 16-24 px. Each loss has a test that fails without it.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from sked_ns.demo.scenes import sphere as demo_scene

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

NUM_BASE = 1000
NUM_SEEDS = 120
SH_C0_TEST = 0.28209479177387814  # colour = 0.5 + SH_C0 * features_dc


@pytest.fixture(scope="module")
def splat_scene(tmp_path_factory):
    """The demo dataset (8 views, 40 px), hat sketches, and a splatfacto run of Gaussians on the sphere."""
    from nerfstudio.engine.optimizers import Optimizers
    from nerfstudio.models.splatfacto import RGB2SH

    from sked_ns.demo.splat_base import SplatFit, save_run, splatfacto_config
    from sked_ns.method.options import without_lpips
    from sked_ns.sketches.sketch_set import save_sketch_set

    root = tmp_path_factory.mktemp("splat")
    demo_scene.write_demo_dataset(root / "data", num_views=8, size=40)
    save_sketch_set(demo_scene.demo_sketch_set(size=40), root / "sketches")
    torch.manual_seed(0)
    config = splatfacto_config(root / "data", root / "runs", SplatFit(steps=1, num_gaussians=16))
    with without_lpips():
        pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    outputs = pipeline.datamanager.train_dataparser_outputs
    scale, transform = float(outputs.dataparser_scale), outputs.dataparser_transform
    directions = torch.nn.functional.normalize(torch.randn(NUM_BASE, 3), dim=-1)
    points = directions * demo_scene.SPHERE_RADIUS * 0.87  # inside the surface: their blur reaches it
    spacing = math.sqrt(4 * math.pi * (demo_scene.SPHERE_RADIUS * scale) ** 2 / NUM_BASE)
    gaussians = {
        "means": (points @ transform[:, :3].T + transform[:, 3]) * scale,
        "scales": torch.full((NUM_BASE, 3), math.log(0.4 * spacing)),
        "quats": torch.nn.functional.normalize(torch.randn(NUM_BASE, 4), dim=-1),
        "features_dc": RGB2SH(demo_scene.shade(directions * demo_scene.SPHERE_RADIUS, demo_scene.sphere_sdf,
                                               lambda p: demo_scene.albedo(p, edit_sdf=demo_scene.sphere_sdf))),
        "features_rest": 0.01 * torch.randn(NUM_BASE, 15, 3),
        "opacities": torch.full((NUM_BASE, 1), 2.0),
    }
    for name, value in gaussians.items():
        pipeline.model.gauss_params[name] = torch.nn.Parameter(value)
    run = save_run(config, pipeline, Optimizers(copy.deepcopy(config.optimizers), pipeline.model.get_param_groups()), 0)
    return {"root": root, "data": root / "data", "sketches": root / "sketches", "base": run, "gaussians": gaussians}


def edit_pipeline(scene, tmp_path, prompt=None, guidance="reference", **settings):
    """The pipeline `ns-train sked --load-dir <splat base>` sets up (not trained), with model settings."""
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.engine.trainer import resolve_edit

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path / "out", prompt=prompt,
                         guidance=guidance, iterations=10, guidance_resolution=24, silhouette_resolution=16)
    resolve_edit(config)
    for name, value in {"num_seeds": NUM_SEEDS, **settings}.items():
        setattr(config.pipeline.model, name, value)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    pipeline.prepare_guidance()
    return config, pipeline


def train(config, pipeline, steps: int, start: int = 0):
    """nerfstudio's training iterations (callbacks, loss, backward, Adam, schedulers); returns the optimizers."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
    from nerfstudio.engine.optimizers import Optimizers

    model = pipeline.model
    optimizers = Optimizers(copy.deepcopy(config.optimizers), model.get_param_groups())
    callbacks = model.get_training_callbacks(TrainingCallbackAttributes(optimizers=optimizers, grad_scaler=None,
                                                                        pipeline=pipeline, trainer=None))
    model.train()
    for step in range(start, start + steps):
        for callback in callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        optimizers.zero_grad_all()
        _, losses, _ = pipeline.get_train_loss_dict(step)
        sum(losses.values()).backward()
        optimizers.optimizer_step_all()
        optimizers.scheduler_step_all(step)
        for callback in callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return optimizers


def kept_mask(model, scene):
    return model.preservation_weight(scene["gaussians"]["means"])[:, 0] > model.config.keep_threshold


def sked_losses(pipeline, step: int = 0):
    pipeline.model.train()
    return pipeline.get_train_loss_dict(step)[1]


def test_the_base_splits_into_kept_and_editable_and_the_edit_starts_as_the_base(splat_scene, tmp_path):
    from sked_ns.models.splat.model import SkedSplatModel

    _, pipeline = edit_pipeline(splat_scene, tmp_path, num_seeds=0)
    model = pipeline.model
    assert isinstance(model, SkedSplatModel)
    kept = kept_mask(model, splat_scene)
    assert 0 < int(kept.sum()) < NUM_BASE  # the sketches are near part of the sphere only
    for name, value in splat_scene["gaussians"].items():
        assert torch.equal(model.kept[name], value[kept])
        assert torch.equal(model.gauss_params[name].detach(), value[~kept])
        # what the viewer and ns-export gaussian-splat read: kept rows first, exactly the base's
        assert torch.equal(getattr(model, name)[: int(kept.sum())], value[kept])
    assert model.num_points == NUM_BASE
    model.eval()
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    with torch.no_grad():
        edit, base = model.get_outputs(camera), model.render_base(camera)
    for key in ("rgb", "accumulation", "depth", "preservation_weight"):
        assert torch.equal(edit[key], base[key]), key
    assert float(edit["preservation_weight"].min()) < 0.5 < float(edit["preservation_weight"].max())


def test_seeds_lie_in_the_sketches_visual_hull_and_start_nearly_transparent(splat_scene, tmp_path):
    _, pipeline = edit_pipeline(splat_scene, tmp_path)
    model = pipeline.model
    seeds = ~model.reference.from_base
    assert int(seeds.sum()) == NUM_SEEDS
    assert bool(model.in_sketch_hull(model.gauss_params["means"][seeds].detach()).all())
    assert torch.allclose(torch.sigmoid(model.gauss_params["opacities"][seeds]), torch.tensor(model.config.seed_opacity))
    model.eval()
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    with torch.no_grad():
        change = (model.get_outputs(camera)["rgb"] - model.render_base(camera)["rgb"]).abs().amax()
    assert 0 < float(change) < 0.1  # faint grey where the hull is seen, nothing more


def test_carving_seeds_nothing_and_empties_the_sketched_region(splat_scene, tmp_path):
    _, pipeline = edit_pipeline(splat_scene, tmp_path, prompt=None, guidance="stable-diffusion")
    model = pipeline.model
    assert bool(model.reference.from_base.all())  # nothing new is made
    losses = sked_losses(pipeline)
    assert "carve_loss" in losses and "silhouette_loss" not in losses
    losses["carve_loss"].backward()
    grad = model.gauss_params["opacities"].grad[:, 0]
    free = 1 - model.preservation_weight(model.gauss_params["means"])[:, 0]
    assert bool((grad[free > 0.5] > 0).all())  # descent lowers their opacity


def test_preservation_loss_pulls_a_moved_editable_base_gaussian_back(splat_scene, tmp_path):
    for ablation, pulls in (("none", True), ("no-preserve", False)):
        _, pipeline = edit_pipeline(splat_scene, tmp_path, ablation=ablation)
        model = pipeline.model
        weight = model.preservation_weight(model.reference.means)[:, 0] * model.reference.from_base
        index = int(weight.argmax())  # the most preserved editable base Gaussian
        with torch.no_grad():
            model.gauss_params["means"][index] += 0.05
            model.gauss_params["opacities"][index] -= 3.0
        loss = sked_losses(pipeline)["preservation_loss"]
        if not pulls:
            assert float(loss) == 0.0
            continue
        loss.backward()
        assert float(model.gauss_params["means"].grad[index].sum()) > 0  # descent moves it back by -0.05
        assert float(model.gauss_params["opacities"].grad[index]) < 0  # and makes it opaque again


def editable_opacity_in_sketches(model, sketch_views) -> float:
    with torch.no_grad():
        background = torch.zeros(3)
        total = [(model._render_edit(camera, background, "editable")["extra"][..., 0] * mask).sum() / mask.sum()
                 for camera, mask in sketch_views]
    return float(sum(total) / len(total))


def test_silhouette_loss_raises_the_editable_opacity_in_the_sketches(splat_scene, tmp_path):
    for ablation, fills in (("none", True), ("no-silhouette", False)):
        _, pipeline = edit_pipeline(splat_scene, tmp_path, ablation=ablation)
        model = pipeline.model
        sketch_views = pipeline.datamanager.sketch_cameras
        before = editable_opacity_in_sketches(model, sketch_views)
        optimizer = torch.optim.Adam([model.gauss_params["opacities"]], lr=1.0)
        for step in range(4):
            optimizer.zero_grad()
            loss = sked_losses(pipeline, step)["silhouette_loss"]
            if not fills:
                assert float(loss) == 0.0
                break
            loss.backward()
            optimizer.step()
        after = editable_opacity_in_sketches(model, sketch_views)
        assert (after > before + 0.05) if fills else after == before


def test_sparsity_loss_is_the_random_views_accumulation_entropy(splat_scene, tmp_path):
    _, pipeline = edit_pipeline(splat_scene, tmp_path, lambda_sp=1.0)
    model = pipeline.model
    loss = sked_losses(pipeline)["sparsity_loss"]
    assert float(loss) > 0
    loss.backward()
    assert float(model.gauss_params["opacities"].grad.abs().sum()) > 0


def test_kept_gaussians_stay_bit_identical_through_densification_and_pruning(splat_scene, tmp_path):
    # Refine every 2 steps from step 2, growing every Gaussian seen, pruning what falls under the seeds' opacity.
    config, pipeline = edit_pipeline(splat_scene, tmp_path, warmup_length=1, refine_every=2, densify_grad_thresh=1e-12,
                                     cull_alpha_thresh=0.0049)
    model = pipeline.model
    kept = {name: value.clone() for name, value in model.kept.tensors().items()}
    editable_before = len(model.gauss_params["means"])
    optimizers = train(config, pipeline, steps=5)
    editable_after = len(model.gauss_params["means"])
    assert editable_after != editable_before  # the strategy did refine the editable set
    for name, value in model.kept.tensors().items():
        assert torch.equal(value, kept[name]), name
    for name, parameter in model.gauss_params.items():
        assert len(model.reference[name]) == editable_after  # L_pres's targets follow the refinement
        assert optimizers.optimizers[name].param_groups[0]["params"][0] is parameter
    assert model.num_points == len(kept["means"]) + editable_after


def test_a_saved_edit_loads_its_refined_gaussians(splat_scene, tmp_path):
    config, pipeline = edit_pipeline(splat_scene, tmp_path, warmup_length=1, refine_every=2, densify_grad_thresh=1e-12)
    train(config, pipeline, steps=3)
    saved = pipeline.model.state_dict()
    assert "reference.means" in saved and "kept.means" not in saved  # refined: L_pres's targets moved, saved
    _, fresh = edit_pipeline(splat_scene, tmp_path, warmup_length=1, refine_every=2, densify_grad_thresh=1e-12)
    parameter = fresh.model.gauss_params["means"]
    assert len(parameter) != len(saved["gauss_params.means"])
    fresh.model.load_state_dict(saved)
    assert fresh.model.gauss_params["means"] is parameter  # resized in place: a resumed run's optimisers hold it
    for key, value in fresh.model.state_dict().items():
        if torch.is_tensor(value):
            assert torch.equal(value, saved[key]), key
    for name, value in pipeline.model.reference.tensors().items():
        assert torch.equal(fresh.model.reference[name], value), name


@pytest.mark.parametrize("beta, supersampling", [(1e-3, 1), (1.0, 4)])
def test_no_nan_at_beta_opacity_and_scale_extremes(splat_scene, tmp_path, beta, supersampling):
    _, pipeline = edit_pipeline(splat_scene, tmp_path, beta=beta, splat_supersampling=supersampling)
    model = pipeline.model
    with torch.no_grad():
        count = len(model.gauss_params["means"])
        model.gauss_params["opacities"][: count // 4] = 40.0
        model.gauss_params["opacities"][count // 4: count // 2] = -40.0
        model.gauss_params["scales"][::3] = -25.0
        model.gauss_params["scales"][1::3] = 3.0
    losses = sked_losses(pipeline)
    assert all(bool(torch.isfinite(value)) for value in losses.values()), losses
    sum(losses.values()).backward()
    for name, parameter in model.gauss_params.items():
        assert bool(torch.isfinite(parameter.grad).all()), name


def test_ns_train_sked_edits_a_splatfacto_run_exports_it_and_resumes(splat_scene, tmp_path):
    """`ns-train sked --load-dir <splatfacto run>`, `ns-export gaussian-splat` of the edit (its kept rows are the
    base's, bit for bit), and resuming the edit to a longer total, which ns-export and ns-render open."""
    import numpy as np
    import PIL.Image
    from nerfstudio.scripts.exporter import ExportGaussianSplat
    from nerfstudio.scripts.render import RenderInterpolated
    from plyfile import PlyData

    from sked_ns.engine.edit_run import edit_config, resume_config, run_edit

    config = edit_config(splat_scene["base"], splat_scene["data"], splat_scene["sketches"], tmp_path / "out",
                         iterations=3, steps_per_save=2, guidance_resolution=24, silhouette_resolution=16)
    trainer = run_edit(config)
    model = trainer.pipeline.model
    kept = kept_mask(model, splat_scene)
    assert "photo_loss" in trainer.pipeline.get_train_loss_dict(3)[1]  # the base-photo anchor is on
    ExportGaussianSplat(load_config=trainer.base_dir / "config.yml", output_dir=tmp_path / "ply").main()
    vertex = PlyData.read(str(tmp_path / "ply" / "splat.ply"))["vertex"]
    rows = int(kept.sum())
    visible = model.opacities.detach()[:, 0] >= math.log(1 / 254)  # the exporter drops what gsplat skips (< 1/255)
    assert vertex.count == int(visible.sum()) and bool(visible[:rows].all())
    base = splat_scene["gaussians"]
    exported = {"means": np.stack([vertex[axis] for axis in "xyz"], axis=-1),
                "opacities": np.asarray(vertex["opacity"])[:, None],
                "scales": np.stack([vertex[f"scale_{i}"] for i in range(3)], axis=-1),
                "quats": np.stack([vertex[f"rot_{i}"] for i in range(4)], axis=-1),
                "features_dc": np.stack([vertex[f"f_dc_{i}"] for i in range(3)], axis=-1)}
    for name, values in exported.items():
        assert np.array_equal(values[:rows], base[name][kept].numpy().astype(np.float32)), name

    resumed = run_edit(resume_config(trainer.base_dir, tmp_path / "resumed", iterations=5))
    assert resumed.pipeline.model.sked_step == 4
    assert torch.equal(resumed.pipeline.model.kept.means, base["means"][kept])
    # The resumed run opens in ns-export and ns-render (their eval_setup loads its own latest checkpoint).
    ExportGaussianSplat(load_config=resumed.base_dir / "config.yml", output_dir=tmp_path / "resumed-ply").main()
    assert PlyData.read(str(tmp_path / "resumed-ply" / "splat.ply"))["vertex"].count >= rows
    RenderInterpolated(load_config=resumed.base_dir / "config.yml", output_path=tmp_path / "frames",
                       output_format="images", pose_source="train", interpolation_steps=1,
                       rendered_output_names=["rgb"]).main()
    frames = sorted((tmp_path / "frames").glob("*.jpg"))
    assert len(frames) >= 4 and np.asarray(PIL.Image.open(frames[0])).std() > 5, "rendered, not blank"


def test_photo_anchor_removes_a_floater_in_front_of_a_training_photo(splat_scene, tmp_path):
    for lambda_photo in (1.0, 0.0):
        _, pipeline = edit_pipeline(splat_scene, tmp_path, lambda_photo=lambda_photo)
        model = pipeline.model
        photo = pipeline.datamanager.photo_view(0)
        assert photo["image"].shape[:2] == (int(photo["camera"].height), int(photo["camera"].width))
        safe = model.photo_anchor.pixels_kept(photo["camera"], 0, (model.config.beta, model.config.photo_threshold))
        assert 0.2 < float(safe.float().mean()) < 1.0  # rays through the sketched region are left to the edit
        # A floater: an opaque editable Gaussian half-way along a safe pixel's ray.
        rays = photo["camera"].generate_rays(camera_indices=0, keep_shape=True)
        row, column = [int(i) for i in safe.nonzero()[len(safe.nonzero()) // 2]]
        floater = rays.origins[row, column] + 0.5 * rays.directions[row, column]
        with torch.no_grad():
            model.gauss_params["means"][-1] = floater
            model.gauss_params["scales"][-1] = math.log(0.03)
            model.gauss_params["opacities"][-1] = 3.0
        model.train()
        data = pipeline.datamanager.next_sked(0, photo_view=lambda_photo > 0)
        losses = model.get_sked_loss_dict(data, 0)[1]
        if lambda_photo == 0:
            assert "photo_loss" not in losses and "photo_view" not in pipeline.datamanager.next_sked(0)
            continue
        losses["photo_loss"].backward()
        assert float(model.gauss_params["opacities"].grad[-1]) > 0  # descent fades the floater


def test_viewmat_is_splatfactos_camera_convention():
    """The one world-to-camera map the splat edit and the splat-base fitter use equals splatfacto's own."""
    from nerfstudio.models.splatfacto import get_viewmat

    from sked_ns.sketches.cameras import viewmat

    camera_to_world = torch.randn(4, 3, 4, generator=torch.Generator().manual_seed(0))
    reference = getattr(get_viewmat, "__wrapped__", get_viewmat)  # splatfacto compiles it
    torch.testing.assert_close(viewmat(camera_to_world), reference(camera_to_world))


def test_edit_rates_let_a_seed_form_in_a_third_of_the_edit_and_stay_finite():
    from sked_ns.models.splat.rates import FORMATION_SHARE, SPLATFACTO_RATES, edit_rates, seed_ranges

    for iterations in (100, 500):
        rates, ranges = edit_rates(iterations, 0.005), seed_ranges(0.005)
        for name, span in ranges.items():
            assert rates[name] * FORMATION_SHARE * iterations >= span * (1 - 1e-9), name  # Adam: ~rate a step
    assert edit_rates(30_000, 0.005) == SPLATFACTO_RATES  # a splatfacto-length run gets splatfacto's rates
    for iterations, seed_opacity in ((0, 0.005), (1, 1e-12), (10**9, 0.999), (100, 1 - 1e-12)):
        rates = edit_rates(iterations, seed_opacity)
        assert all(math.isfinite(rate) and SPLATFACTO_RATES[name] <= rate < 10 for name, rate in rates.items())


def test_a_typed_splat_learning_rates_reaches_the_optimisers(splat_scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.engine.trainer import resolve_edit
    from sked_ns.models.splat.rates import SPLATFACTO_RATES, edit_rates

    for choice in ("edit", "splatfacto"):
        config = edit_config(splat_scene["base"], splat_scene["data"], splat_scene["sketches"], tmp_path / choice,
                             iterations=200)
        config.pipeline.model.splat_learning_rates = choice
        resolve_edit(config)
        expected = edit_rates(200, config.pipeline.model.seed_opacity) if choice == "edit" else SPLATFACTO_RATES
        assert {name: group["optimizer"].lr for name, group in config.optimizers.items()} == expected


def test_seeds_turn_opaque_and_take_a_colour_within_a_short_edit(splat_scene, tmp_path):
    """30 steps of an edit (L_sil and reference guidance towards the red hat): under the edit's rates the seeds fill
    the sketches and leave grey; under splatfacto's (sized for 30,000 steps) they stay a faint grey haze."""
    from sked_ns.models.splat.rates import splat_optimizers

    steps, formed = 30, {}
    for choice in ("edit", "splatfacto"):
        config, pipeline = edit_pipeline(splat_scene, tmp_path, splat_learning_rates=choice)
        config.optimizers = splat_optimizers(steps, config.pipeline.model)
        model = pipeline.model
        seeds = ~model.reference.from_base
        train(config, pipeline, steps)
        colour = model.gauss_params["features_dc"].detach()[seeds] * SH_C0_TEST  # colour - grey
        formed[choice] = (editable_opacity_in_sketches(model, pipeline.datamanager.sketch_cameras),
                          float(colour.abs().amax(dim=-1).quantile(0.9)))
    assert formed["edit"][0] > 0.7 and formed["edit"][1] > 0.25, formed  # measured 0.79, 0.35
    assert formed["splatfacto"][0] < formed["edit"][0] - 0.1 and formed["splatfacto"][1] < 0.05, formed  # 0.58, 0.02


def test_area_downsample_is_the_block_mean():
    from sked_ns.models.splat.model import area_downsample

    image = torch.rand(12, 18, 4)
    for factor in (1, 2, 3):
        fast = area_downsample(image, factor)
        height, width = 12 // factor, 18 // factor
        plain = torch.stack([torch.stack([image[y * factor:(y + 1) * factor, x * factor:(x + 1) * factor].reshape(-1, 4)
                                          .mean(dim=0) for x in range(width)]) for y in range(height)])
        assert fast.shape == (height, width, 4) and torch.allclose(fast, plain, atol=1e-6), factor


def test_supersampled_training_renders_keep_the_guidance_reference_sampled_as_the_edit(splat_scene, tmp_path):
    """At splat_supersampling 2 the random view is rendered at 2x and averaged down to the guidance's size, and so is the
    base render the reference guidance uses outside the change: an unchanged edit (no seeds) matches it, and the guidance
    is told how the image was sampled."""
    images = {}
    for factor in (1, 2):
        _, pipeline = edit_pipeline(splat_scene, tmp_path / str(factor), num_seeds=0, splat_supersampling=factor)
        model, seen = pipeline.model, {}
        original = model.guidance_losses

        def capture(image, random_camera, base_image, step, samples_per_side=1, original=original, seen=seen):
            seen["image"], seen["base"] = image.detach(), (base_image() if callable(base_image) else base_image)
            seen["samples_per_side"] = samples_per_side
            return original(image, random_camera, lambda: seen["base"], step, samples_per_side)

        model.guidance_losses = capture
        torch.manual_seed(0)
        sked_losses(pipeline)
        assert seen["image"].shape[-2:] == (24, 24)  # the guidance's resolution, whatever the sampling
        assert float((seen["image"] - seen["base"]).abs().max()) < 1e-5, factor  # 0.76 if the base were sampled once
        assert seen["samples_per_side"] == factor  # so the reference target is sampled as the image was
        images[factor] = seen["image"]
    assert not torch.equal(images[1], images[2])  # 2x2 samples a pixel do change the image (its edges)


def test_random_views_frame_the_edit_box_the_pipeline_computed(splat_scene, tmp_path):
    """`ns-train sked` hands the datamanager the edit box: its bounding sphere sizes the random views' field of view,
    and each view's focal length says the narrowed one (edit-fill 0: the authors' 40-80 deg)."""
    from sked_ns.sketches.random_views import focal_from_fov

    for fill in (0.0, 0.7):
        config, pipeline = edit_pipeline(splat_scene, tmp_path / str(fill), num_seeds=0)
        datamanager = pipeline.datamanager
        datamanager.config.edit_fill = fill
        datamanager.attach_sketches(pipeline.model.sketch_set, pipeline.model.edit_box, 16, 24)
        sampler = datamanager.random_views
        assert sampler.edit_radius == pytest.approx(0.5 * float(np.linalg.norm(pipeline.model.edit_box.size)))
        low, high = (sampler.fov_scale * value for value in (40.0, 80.0))
        focals = [datamanager.next_sked(step)["random_camera"]["focal"] for step in range(20)]
        assert all(focal_from_fov(high, 24) - 1e-6 <= focal <= focal_from_fov(low, 24) + 1e-6 for focal in focals)
        if fill == 0.0:
            assert sampler.fov_scale == 1.0
        else:
            assert sampler.fov_scale < 1.0  # the demo part is small beside its scene


def test_the_base_is_judged_on_its_own_photos_at_their_resolution(splat_scene, tmp_path):
    """The anchor's photos are averaged down to the guidance resolution, where a render point-samples the Gaussians:
    judged there, a base's own photos would read as another scene's and switch the anchor off."""
    import shutil
    import warnings

    import cv2

    from sked_ns.method.photo_anchor import SkedPhotoWarning

    data = tmp_path / "data"
    shutil.copytree(splat_scene["data"], data)
    _, pipeline = edit_pipeline(splat_scene, tmp_path)
    dataset = pipeline.datamanager.train_dataset
    for index, path in enumerate(dataset.image_filenames):  # photos the base renders exactly: its own
        rgb = pipeline.model.render_base(dataset.cameras[index:index + 1])["rgb"].numpy()
        cv2.imwrite(str(data / path.relative_to(splat_scene["data"])), (rgb * 255).round().astype(np.uint8)[..., ::-1])
    _, pipeline = edit_pipeline({**splat_scene, "data": data}, tmp_path, guidance_resolution=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedPhotoWarning)
        losses = sked_losses(pipeline)
    assert pipeline.model.base_photo_psnr > 35 and "photo_loss" in losses
