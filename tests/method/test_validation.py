"""Range checks of every SKED setting: refused naming the flag as typed, warned where legal but surely a mistake."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
import pytest
from conftest import random_pose

from sked_ns.engine.datamanager import SkedDataManagerConfig
from sked_ns.engine.presets import PRESETS, read_preset
from sked_ns.errors import SkedOptionError, SkedOptionWarning
from sked_ns.method.validation import (
    LOSS_WEIGHTS,
    USUAL_RANGES,
    check_optimizers,
    check_options,
    check_sketch_pixels,
    unusual,
    warn_unusual_options,
)
from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig
from sked_ns.models.nerf.ngp import SkedNGPModelConfig
from sked_ns.sketches.sketch_set import SketchSet, SketchView


@pytest.mark.parametrize("name", ["lambda_pres", "lambda_colour", "lambda_sil", "lambda_sp", "lambda_new_mass",
                                  "lambda_carve", "lambda_photo"])
@pytest.mark.parametrize("value", [-5.0, float("nan"), float("inf")])
def test_a_negative_or_non_finite_weight_is_refused_by_its_flag(name, value):
    options = SkedNerfactoModelConfig(**{name: value})
    with pytest.raises(SkedOptionError, match=f"--pipeline.model.{name.replace('_', '-')} "):
        check_options(options)


@pytest.mark.parametrize("name, value", [
    ("beta", 0.0), ("beta", -0.1), ("preservation_delta", 0.0), ("samples_per_ray_scale", 0.0),
    ("samples_per_ray_scale", float("nan")), ("occupancy_threshold", -1.0), ("photo_threshold", 1.5),
    ("photo_threshold", -0.1), ("guidance_resolution", 0), ("guidance_resolution", -64),
    ("silhouette_resolution", 0), ("silhouette_resolution", -1), ("silhouette_resolution", 12.5),
    ("edit_box_warmup", -1), ("keep_threshold", 0.0), ("keep_threshold", 1.5), ("num_seeds", -1), ("num_seeds", 10.5), ("num_seeds", 1_000_000_000),
    ("seed_opacity", 0.0), ("seed_opacity", 1.0), ("seed_size", 0.0), ("seed_size", float("inf")),
    ("splat_supersampling", 0), ("splat_supersampling", 1.5),
])
def test_each_field_out_of_its_range_is_refused_by_its_flag(name, value):
    with pytest.raises(SkedOptionError, match=f"--pipeline.model.{name.replace('_', '-')} "):
        check_options(SkedNerfactoModelConfig(**{name: value}))


@pytest.mark.parametrize("name, value", [
    ("fov_range", (0.0, 80.0)), ("fov_range", (80.0, 40.0)), ("elevation_range", (-100.0, 90.0)),
    ("radius_scale_range", (-1.0, 1.2)), ("azimuth_range", (10.0, -10.0)), ("train_num_rays_per_batch", 0),
])
def test_random_view_and_photo_batch_settings_are_checked(name, value):
    datamanager = SkedDataManagerConfig(**{name: value})
    with pytest.raises(SkedOptionError, match=f"--pipeline.datamanager.{name.replace('_', '-')} "):
        check_options(SkedNerfactoModelConfig(), datamanager)


def test_all_problems_are_reported_at_once():
    with pytest.raises(SkedOptionError) as error:
        check_options(SkedNerfactoModelConfig(lambda_pres=-5.0, lambda_sil=-1.0, beta=0.0))
    assert all(f in str(error.value) for f in ("lambda-pres", "lambda-sil", "beta"))


@pytest.mark.parametrize("config", [SkedNerfactoModelConfig, SkedNGPModelConfig])
def test_defaults_and_every_preset_pass_silently(config):
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedOptionWarning)
        check_options(config(), SkedDataManagerConfig())
        for name in PRESETS:
            check_options(dataclasses.replace(config(), **read_preset(name)["model"]))
        check_options(config(lambda_pres=0.0, lambda_photo=0.0, edit_box_warmup=0))  # ablations are legal


def test_a_guidance_render_larger_than_sd_is_warned():
    with pytest.warns(SkedOptionWarning, match="guidance-resolution 1024"):
        warn_unusual_options(SkedNerfactoModelConfig(guidance_resolution=1024))


@pytest.mark.parametrize("scale", [0.01, 20.0])
def test_samples_per_ray_far_from_the_base_are_warned(scale):
    with pytest.warns(SkedOptionWarning, match=f"samples-per-ray-scale {scale:g}: "):
        check_options(SkedNerfactoModelConfig(samples_per_ray_scale=scale))


def test_a_photo_threshold_that_silences_the_anchor_is_warned():
    with pytest.warns(SkedOptionWarning, match="photo-threshold 1: .*never acts"):
        check_options(SkedNerfactoModelConfig(photo_threshold=1.0))


def test_resolve_edit_refuses_before_anything_is_written(tmp_path):
    from sked_ns.engine.presets import edit_preset

    config = edit_preset()
    config.output_dir = tmp_path
    config.pipeline.model = SkedNerfactoModelConfig(lambda_pres=-5.0)
    with pytest.raises(SkedOptionError, match="--pipeline.model.lambda-pres -5.0"):
        config.save_config()
    assert not any(tmp_path.iterdir())


def _view(size: int, blob: int, rng) -> SketchView:
    mask = np.zeros((size, size), dtype=bool)
    mask[size // 2: size // 2 + blob, size // 2: size // 2 + blob] = True
    return SketchView(mask=mask, camera_to_world=random_pose(rng), fl_x=size, fl_y=size, cx=size / 2, cy=size / 2,
                      name=f"masks/{blob}px.png")


def test_a_sketch_under_a_pixel_at_the_silhouette_resolution_is_refused(rng):
    sketches = SketchSet(views=[_view(256, 40, rng), _view(256, 4, rng)])
    assert check_sketch_pixels(sketches, 128) == [400, 4]  # 40 px at half size: 20 x 20
    with pytest.raises(SkedOptionError, match=r"silhouette-resolution 32: the sketch of masks/4px.png covers no pixel"):
        check_sketch_pixels(sketches, 32)
    with pytest.raises(SkedOptionError, match="silhouette-resolution 1: "):
        check_sketch_pixels(sketches, 1)
    with pytest.warns(SkedOptionWarning, match=r"masks/4px.png \(4 px\)"):
        check_sketch_pixels(sketches, 128)


def test_splat_settings_are_typeable_for_any_base_and_reach_the_splat_model():
    """`ns-train sked` parses the nerfacto-shaped preset: the splat settings must be there to be typed, and the
    splat config built for a splatfacto base must keep what was typed."""
    from nerfstudio.models.splatfacto import SplatfactoModelConfig

    from sked_ns.engine.trainer import edit_model_config
    from sked_ns.models.splat.model import SkedSplatModelConfig

    typed = SkedNerfactoModelConfig(keep_threshold=0.95, num_seeds=600, seed_opacity=0.02, seed_size=0.8,
                                    splat_learning_rates="splatfacto", splat_supersampling=3)
    splat = edit_model_config(typed, SplatfactoModelConfig())
    assert isinstance(splat, SkedSplatModelConfig)
    assert (splat.keep_threshold, splat.num_seeds, splat.seed_opacity, splat.seed_size,
            splat.splat_learning_rates, splat.splat_supersampling) == (0.95, 600, 0.02, 0.8, "splatfacto", 3)


@pytest.mark.parametrize("name, value", [("keep_threshold", 0.3), ("num_seeds", 500_000), ("splat_supersampling", 8)])
def test_splat_settings_that_edit_too_much_are_warned(name, value):
    with pytest.warns(SkedOptionWarning, match=f"--pipeline.model.{name.replace('_', '-')} "):
        warn_unusual_options(SkedNerfactoModelConfig(**{name: value}))


@pytest.mark.parametrize("name, refused, warned, warning", [
    ("field_chunk", -2, 8, "field-chunk 8: chunks this small"),
    ("base_proposal_grid", -1, 4, "base-proposal-grid 4: a grid this coarse"),
    ("hull_proposal_grid", -2, 512, "hull-proposal-grid 512: 134,217,728 log scales"),
])
def test_grid_and_chunk_sizes_below_zero_are_refused_and_unusual_ones_warned(name, refused, warned, warning):
    with pytest.raises(SkedOptionError, match=f"{name.replace('_', '-')} {refused}"):
        check_options(SkedNerfactoModelConfig(**{name: refused}))
    with pytest.warns(SkedOptionWarning, match=warning):
        check_options(SkedNerfactoModelConfig(**{name: warned}))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedOptionWarning)
        # 0 is legal for each: no chunks (the fastest), the base's proposal networks, 0.9's evenly sampled hull.
        check_options(SkedNerfactoModelConfig(**{name: 0}))


def test_the_field_chunks_default_is_legal_and_unwarned():
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedOptionWarning)
        check_options(SkedNerfactoModelConfig(field_chunk=-1))  # the memory plan chooses


EXTREMES = [1e-12, 1e12, 1e3]
"""Values typed by mistake (a lost minus sign in an exponent, a wrong unit): each warned where outside its range."""


@pytest.mark.parametrize("name", LOSS_WEIGHTS)
@pytest.mark.parametrize("value", EXTREMES)
def test_a_loss_weight_orders_of_magnitude_off_is_warned(name, value):
    with pytest.warns(SkedOptionWarning, match=re.escape(f"--pipeline.model.{name.replace('_', '-')} {value:g}: ")):
        check_options(SkedNerfactoModelConfig(**{name: value}))


@pytest.mark.parametrize("name", ["preservation_delta", "seed_size"])
@pytest.mark.parametrize("value", EXTREMES)
def test_a_length_orders_of_magnitude_off_is_warned(name, value):
    with pytest.warns(SkedOptionWarning, match=re.escape(f"--pipeline.model.{name.replace('_', '-')} {value:g}: ")):
        check_options(SkedNerfactoModelConfig(**{name: value}))


@pytest.mark.parametrize("name", LOSS_WEIGHTS + ("preservation_delta", "seed_size"))
def test_each_knobs_default_is_in_its_usual_range(name):
    usual = USUAL_RANGES["loss_weight" if name in LOSS_WEIGHTS else name]
    default = getattr(SkedNerfactoModelConfig(), name)
    assert default == 0 or usual.low <= default <= usual.high
    assert unusual(name, default, usual) is None


def _presets_optimizers():
    from sked_ns.engine.presets import edit_preset
    from sked_ns.method.options import SkedOptions
    from sked_ns.models.splat.rates import splat_optimizers

    yield from (edit_preset(name).optimizers for name in PRESETS)
    for iterations in (1, 30, 500, 10_000, 30_000):  # the splat edit's rates follow its length and seed opacity
        for seed_opacity in (1e-3, 0.005, 0.5):
            yield splat_optimizers(iterations, SkedOptions(seed_opacity=seed_opacity))
    yield splat_optimizers(10_000)  # splatfacto's own


def test_every_presets_and_splat_edits_learning_rates_pass_silently():
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedOptionWarning)
        for optimizers in _presets_optimizers():
            assert check_optimizers(optimizers) == []


@pytest.mark.parametrize("group", ["proposal_networks", "fields", "hash_grids"])
@pytest.mark.parametrize("setting, typed", [("optimizer", "optimizer.lr"), ("scheduler", "scheduler.lr-final")])
@pytest.mark.parametrize("value", EXTREMES)
def test_a_learning_rate_orders_of_magnitude_off_is_warned_by_its_flag(group, setting, typed, value):
    from sked_ns.engine.presets import edit_preset

    optimizers = edit_preset().optimizers
    field = "lr" if setting == "optimizer" else "lr_final"
    setattr(optimizers[group][setting], field, value)
    flag_typed = f"--optimizers.{group.replace('_', '-')}.{typed} {value:g}: Adam moves"
    with pytest.warns(SkedOptionWarning, match=re.escape(flag_typed)):
        assert len(check_optimizers(optimizers)) == 1


@pytest.mark.parametrize("value", [-5e-3, float("nan"), float("inf")])
def test_a_negative_or_non_finite_learning_rate_is_refused(value):
    from sked_ns.engine.presets import edit_preset

    optimizers = edit_preset().optimizers
    optimizers["fields"]["optimizer"].lr = value
    with pytest.raises(SkedOptionError, match="--optimizers.fields.optimizer.lr "):
        check_optimizers(optimizers)
    optimizers["fields"]["optimizer"].lr = 0.0  # a frozen group: legal, and not warned
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkedOptionWarning)
        check_optimizers(optimizers)


def test_edit_inputs_check_the_learning_rates_before_anything_is_written(tmp_path):
    """The edit's inputs are checked at its start (trainer.resolve_edit), before the base or data are read."""
    from sked_ns.engine.edit_inputs import check_edit_inputs
    from sked_ns.engine.presets import edit_preset

    config = edit_preset()
    config.output_dir = tmp_path
    config.machine.device_type = "cpu"
    config.optimizers["hash_grids"]["optimizer"].lr = -1.0
    with pytest.raises(SkedOptionError, match="--optimizers.hash-grids.optimizer.lr -1.0"):
        check_edit_inputs(config)
    assert not any(tmp_path.iterdir())
