"""`ns-train sked` on an instant-ngp base: the occupancy-grid model, on the CPU (torch marcher)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from reference import file_digests

from sked_ns.engine.edit_run import edit_config, resume_config, run_edit
from sked_ns.engine.trainer import resolve_edit
from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_outside
from sked_ns.evaluation.render import load_pipeline, render_at, render_base_at, resized_mask
from sked_ns.guidance import guidance_name
from sked_ns.method.frozen_base import read_model_state
from sked_ns.models.nerf.ngp import SkedNGPModel, SkedNGPModelConfig

ITERATIONS = 60



@pytest.fixture(scope="module")
def ngp_edited(ngp_scene):
    before = file_digests(ngp_scene["base"])
    config = edit_config(ngp_scene["base"], ngp_scene["data"], ngp_scene["sketches"], ngp_scene["root"] / "ngp-edits",
                         iterations=ITERATIONS, guidance_resolution=24, silhouette_resolution=24, steps_per_save=30)
    config.pipeline.model.nerf_edit_field = "local"  # its saved grid cells are tested below
    trainer = run_edit(config)
    return {"trainer": trainer, "run": trainer.base_dir, "base_digest_before": before}


def test_an_ngp_base_gets_the_occupancy_grid_model(ngp_scene, tmp_path):
    config = edit_config(ngp_scene["base"] / "nerfstudio_models", ngp_scene["data"], ngp_scene["sketches"], tmp_path)
    resolve_edit(config)
    model = config.pipeline.model
    assert isinstance(model, SkedNGPModelConfig)
    assert (model.grid_resolution, model.grid_levels, model.render_step_size) == (32, 2, 0.01)
    assert guidance_name(model.guidance) == "reference" and model.sketches == ngp_scene["sketches"]
    assert config.load_dir is None


def test_ngp_edit_starts_from_the_base_with_the_edit_box_switched_on(ngp_scene, tmp_path):
    config = edit_config(ngp_scene["base"], ngp_scene["data"], ngp_scene["sketches"], tmp_path, iterations=1)
    resolve_edit(config)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    model: SkedNGPModel = pipeline.model
    base = read_model_state(config.pipeline.model.base_checkpoint)
    for key, value in model.field.state_dict().items():
        assert torch.equal(value, base[f"field.{key}"]), key
    base_cells = base["occupancy_grid.binaries"]
    grid = model.occupancy_grid.binaries
    assert torch.equal(grid, base_cells | model.edit_box_cells)
    assert model.edit_box_cells.sum() > 0 and (model.edit_box_cells & ~base_cells).any(), "the hat's cells are new"
    assert torch.equal(model.frozen_base.occupancy_grid.binaries, base_cells), "the frozen grid is the base's"
    # The edit renders the base too, up to the faint density the base field has in the new cells.
    view = model.sketch_set.views[0]
    edit, frozen = render_at(model, view, 32), render_base_at(model, view, 32)
    difference = (edit["rgb"] - frozen["rgb"]).abs()
    assert difference.mean() < 2e-3 and difference.max() < 0.1, (difference.mean(), difference.max())


def test_no_cell_is_pruned_during_the_warmup(ngp_scene, tmp_path):
    config = edit_config(ngp_scene["base"], ngp_scene["data"], ngp_scene["sketches"], tmp_path, iterations=100)
    config.pipeline.model.keep_threshold = 1.0  # nothing held exactly: the grid follows the editable field everywhere
    config.pipeline.model.nerf_edit_field = "full-copy"  # a field whose own weights the test sets
    resolve_edit(config)
    model: SkedNGPModel = config.pipeline.setup(device="cpu", test_mode="val").model
    model.train()
    with torch.no_grad():
        for parameter in model.field.mlp_base.parameters():
            parameter.zero_()  # density exp(0) = 1: every cell's occupancy is now below the threshold
    before = model.occupancy_grid.binaries.clone()
    for step in range(0, 48, 16):
        model.update_to_step(step)  # SKED's step callback runs before the grid update, as in training
        model.update_occupancy_grid(step)
    assert torch.equal(model.occupancy_grid.binaries, before), "warm-up (50 its): nothing switched off"
    model.update_to_step(64)
    model.update_occupancy_grid(64)  # after the warm-up instant-ngp's own update applies
    assert model.occupancy_grid.binaries.sum() < before.sum()


def test_ngp_edit_fills_the_sketch_and_keeps_the_rest(ngp_scene, ngp_edited):
    pipeline = load_pipeline(ngp_edited["run"])
    model = pipeline.model
    assert isinstance(model, SkedNGPModel)
    for view in model.sketch_set.views:
        edit, base = render_at(model, view, 48), render_base_at(model, view, 48)
        mask = resized_mask(view, 48)
        ios_base, ios_edit = intersection_over_sketch(base["accumulation"], mask), intersection_over_sketch(edit["accumulation"], mask)
        # Measured: 0.17 / 0.28 -> 0.85 / 0.89 with PSNR outside 27-29 dB (see the closing note of issue 3).
        assert ios_edit > 0.7 and ios_edit > ios_base + 0.3, (ios_base, ios_edit)
        assert psnr_outside(edit["rgb"], base["rgb"], mask) > 24.0


def test_ngp_base_untouched_and_frozen(ngp_scene, ngp_edited):
    assert file_digests(ngp_scene["base"]) == ngp_edited["base_digest_before"]
    model = ngp_edited["trainer"].pipeline.model
    base = read_model_state(model.config.base_checkpoint)
    for key, value in model.base_field.state_dict().items():
        assert torch.equal(value.cpu(), base[f"field.{key}"]), key
    assert not any(key.startswith(("_base", "frozen_base")) for key in model.state_dict())


def test_ngp_edit_outputs_preservation_weight_and_resumes(ngp_scene, ngp_edited, tmp_path):
    pipeline = load_pipeline(ngp_edited["run"])
    view = pipeline.model.sketch_set.views[0]
    from sked_ns.sketches.sketch_set import sketch_view_at

    camera = sketch_view_at(view, 24)[0]
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(camera)
    weight = outputs["preservation_weight"]
    assert weight.shape == (24, 24, 1) and torch.isfinite(weight).all()
    assert weight.min() < 0.5 < weight.max(), "low inside the sketch, 1 elsewhere"
    # Resume: --load-dir on the edit continues it from its last checkpoint.
    config = resume_config(ngp_edited["run"], tmp_path, iterations=ITERATIONS + 2)
    resolve_edit(config)
    assert isinstance(config.pipeline.model, SkedNGPModelConfig)
    assert config.load_dir == ngp_edited["run"] / "nerfstudio_models"


def test_a_local_ngp_edit_saves_only_the_grid_cells_it_changed_and_renders_the_same_loaded(ngp_edited):
    model = ngp_edited["trainer"].pipeline.model.eval()
    assert model.local_field is not None
    (checkpoint,) = sorted((ngp_edited["run"] / "nerfstudio_models").glob("step-*.ckpt"))[-1:]
    saved = torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]
    assert not [key for key in saved if key.endswith(("occupancy_grid.occs", "occupancy_grid.binaries"))]
    changed = saved["_model.occupancy_grid.changed_cells"].long()
    # What the edit changed lies in its residual's box: every other cell is still the base's.
    assert 0 < len(changed) and torch.isin(changed, model.edit_cells.cpu()).all()
    assert len(model.edit_cells) < model.occupancy_grid.occs.numel()
    loaded = load_pipeline(ngp_edited["run"]).model
    assert torch.equal(loaded.occupancy_grid.occs, model.occupancy_grid.occs)
    assert torch.equal(loaded.occupancy_grid.binaries, model.occupancy_grid.binaries)
    for view in model.sketch_set.views:
        before, after = render_at(model, view, 32), render_at(loaded, view, 32)
        for key in ("rgb", "accumulation"):
            assert torch.equal(before[key], after[key]), key
    # An edit saved with its whole grid (0.8) loads that grid as it is.
    whole = {key: value for key, value in torch.nn.Module.state_dict(model).items() if not key.startswith("field.")}
    loaded.occupancy_grid.occs.zero_()
    loaded.load_state_dict(whole)
    assert torch.equal(loaded.occupancy_grid.occs, model.occupancy_grid.occs)


def test_a_progressive_ngp_edit_marches_the_earlier_edits_grid(ngp_scene, ngp_edited, tmp_path):
    """The earlier local edit saved its grid as changes to its base's: the next edit's base grid is that edit's
    whole grid, and the next edit's own changes are rebuilt over it."""
    config = edit_config(ngp_edited["run"], ngp_scene["data"], ngp_scene["sketches"], tmp_path, iterations=2,
                         guidance_resolution=16, silhouette_resolution=16, steps_per_save=2)
    config.progressive = True
    trainer = run_edit(config)
    model, earlier = trainer.pipeline.model.eval(), load_pipeline(ngp_edited["run"]).model
    assert torch.equal(model.frozen_base.occupancy_grid.occs, earlier.occupancy_grid.occs)
    assert torch.equal(model.frozen_base.occupancy_grid.binaries, earlier.occupancy_grid.binaries)
    view = model.sketch_set.views[0]
    assert torch.equal(render_base_at(model, view, 16)["rgb"], render_at(earlier, view, 16)["rgb"])
    loaded = load_pipeline(trainer.base_dir).model
    assert torch.equal(loaded.occupancy_grid.occs, model.occupancy_grid.occs)
    assert torch.equal(render_at(loaded, view, 16)["rgb"], render_at(model, view, 16)["rgb"])


def test_rendering_an_ngp_run_without_cuda_is_explained(ngp_scene):
    if torch.cuda.is_available():
        pytest.skip("this machine renders instant-ngp runs with nerfacc")
    with pytest.raises(ValueError, match="renders instant-ngp runs with CUDA kernels only"):
        load_pipeline(ngp_scene["base"])


def test_ns_train_sked_on_an_ngp_run_folder(ngp_scene, tmp_path):
    """The user's command, typed with the base's run folder, on the CPU."""
    import shutil
    import subprocess
    import sys

    ns_train = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    command = [
        ns_train, "sked", "--load-dir", str(ngp_scene["base"]), "--sketches", str(ngp_scene["sketches"]),
        "--pipeline.model.guidance-resolution", "16",
        "--pipeline.model.silhouette-resolution", "16", "--max-num-iterations", "3", "--steps-per-save", "2",
        "--machine.device-type", "cpu", "--mixed-precision", "False", "--vis", "tensorboard",
        "--output-dir", str(tmp_path), "pipeline.model.guidance:reference",
        "nerfstudio-data", "--data", str(ngp_scene["data"]),
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (config_path,) = tmp_path.rglob("config.yml")
    saved = config_path.read_text()
    assert "SkedNGPModelConfig" in saved and "grid_resolution: 32" in saved
    assert list((config_path.parent / "nerfstudio_models").glob("step-*.ckpt"))


@pytest.fixture(scope="module")
def bounded_base(ngp_scene, tmp_path_factory):
    """An instant-ngp-bounded base trained, as that method does, through the instant-ngp-data dataparser."""
    from sked_ns.demo.base import build_demo_base

    return build_demo_base(ngp_scene["data"], tmp_path_factory.mktemp("bounded"), steps=300, points_per_step=4096,
                           method="instant-ngp-bounded")


def test_instant_ngp_bounded_base_edits(ngp_scene, bounded_base, tmp_path):
    """instant-ngp-bounded: no scene contraction, one grid level, black background, alpha_thre 0."""
    from nerfstudio.data.dataparsers.instant_ngp_dataparser import InstantNGPDataParserConfig

    config = edit_config(bounded_base, ngp_scene["data"], ngp_scene["sketches"], tmp_path / "edits", iterations=20,
                         guidance_resolution=16, silhouette_resolution=16)
    assert isinstance(config.pipeline.datamanager.dataparser, InstantNGPDataParserConfig), "the base's dataparser"
    trainer = run_edit(config)
    model = trainer.pipeline.model
    assert isinstance(model, SkedNGPModel)
    assert model.config.disable_scene_contraction and model.config.grid_levels == 1 and model.config.alpha_thre == 0
    assert model.field.spatial_distortion is None
    assert trainer.skipped_steps == 0
    assert all(torch.isfinite(p).all() for p in model.parameters())
    view = model.sketch_set.views[0]
    # The sketch views, mapped through instant-ngp-data's frame (scale only), see the base's object.
    assert render_at(model, view, 24)["accumulation"].max() > 0.5, "the bounded base renders its object"


def test_ns_train_sked_on_a_bounded_run_with_instant_ngp_data(ngp_scene, bounded_base, tmp_path):
    """What an instant-ngp-bounded user types: the base's dataparser subcommand."""
    import shutil
    import subprocess
    import sys

    ns_train = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    common = [
        ns_train, "sked", "--load-dir", str(bounded_base), "--sketches", str(ngp_scene["sketches"]),
        "--pipeline.model.guidance-resolution", "16",
        "--pipeline.model.silhouette-resolution", "16", "--max-num-iterations", "2", "--steps-per-save", "2",
        "--machine.device-type", "cpu", "--mixed-precision", "False", "--vis", "tensorboard",
    ]
    result = subprocess.run(common + ["--output-dir", str(tmp_path / "ok"), "pipeline.model.guidance:reference",
                                      "instant-ngp-data", "--data",
                                      str(ngp_scene["data"])], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (config_path,) = (tmp_path / "ok").rglob("config.yml")
    assert "InstantNGPDataParserConfig" in config_path.read_text()
    # nerfstudio-data orients, centres and scales the same images differently: refused, with what to type.
    wrong = subprocess.run(common + ["--output-dir", str(tmp_path / "wrong"), "pipeline.model.guidance:reference",
                                     "nerfstudio-data", "--data",
                                     str(ngp_scene["data"])], capture_output=True, text=True, timeout=600)
    assert wrong.returncode != 0
    assert "dataparser_transforms.json" in wrong.stderr and "instant-ngp-data --data" in wrong.stderr, wrong.stderr[-3000:]
    assert not list((tmp_path / "wrong").rglob("step-*.ckpt")), "nothing trained in the wrong frame"
