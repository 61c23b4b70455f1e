"""The memory plan (engine/memory_plan.py): its model against benchmarks/memory.py's measurements, its weight count
against loaded weights, and the refusal of an edit that cannot fit, before anything is written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tiny_sd import build_tiny_stable_diffusion

from sked_ns.engine import memory_plan, step_time
from sked_ns.engine.memory_plan import GB, StepWork, nerf_side, sd_bytes
from sked_ns.errors import SkedUserError
from sked_ns.guidance.stable_diffusion import StableDiffusionGuidanceConfig
from sked_ns.method.options import SkedOptions

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "memory.json"
EDIT_SIZE = RESULTS.parent / "edit_size.json"
WITHIN = 0.25
"""The plan's promise: within 25% of what the benchmark measured."""


def _measured():
    result = json.loads(RESULTS.read_text())
    assert result["steps"], "benchmarks/results/memory.json has no steps"
    return result


def _work(entry) -> StepWork:
    """The entry's step as the plan counts it (benchmarks/memory.py, entry_work)."""
    settings = entry["settings"]
    work = dict(settings["work"])
    if settings.get("field_chunk") is not None:
        rays = settings["rays"]
        work.update(rays=float(rays["random_view"]), sketch_rays=float(rays["sketch_views"] + rays["photo"]))
    return StepWork(**work)


def _close(planned: float, measured: float, what: str) -> None:
    assert abs(planned - measured) <= WITHIN * measured, f"{what}: planned {planned:.3f} GB, measured {measured:.3f} GB"


def test_the_plan_predicts_every_measured_step_within_a_quarter():
    """Each base kind at each size, chunked and unchunked: the NeRF (splat) side of the step, what it holds when
    the guidance runs, and the whole step composed with Stable Diffusion's side."""
    result = _measured()
    for key, entry in result["steps"].items():
        representation = key.split("@")[0]
        settings = entry["settings"]
        work = _work(entry)
        weights = settings["base_weights_gb"] * GB
        step, held = nerf_side(representation, work, weights)
        _close(step / GB, entry["chunked"]["step_peak_gb"], f"{key} step")
        _close(held / GB, entry["chunked"]["held_at_guidance_gb"], f"{key} held at the guidance")
        # Measured before NeRF edits trained a local residual: whole copies.
        options = SkedOptions(prompt="a hat", nerf_edit_field=settings.get("nerf_edit_field", "full-copy"))
        resident = memory_plan.resident_bytes(representation, weights, options)  # not carving
        _close(resident / GB, sum(entry["resident_gb"].values()), f"{key} resident")
        unchunked = entry.get("unchunked", {})
        if "step_peak_gb" in unchunked:
            step, _ = nerf_side(representation, StepWork(work.rays, work.sketch_rays, work.sample_scale, 0), weights)
            _close(step / GB, unchunked["step_peak_gb"], f"{key} unchunked step")
        sd = result.get("stable_diffusion")
        if sd and "total_fp32_gb" in entry:
            plan = memory_plan.MemoryPlan("cpu", resident, *nerf_side(representation, work, weights),
                                          sd_weights=sum(sd["weights_gb"].values()) * GB,
                                          sd_step=memory_plan.SD_STEP_BYTES_AT_512 * (sd["image_size"] / 512) ** 2)
            _close(plan.peak / GB, entry["total_fp32_gb"], f"{key} whole step")


def test_the_plan_holds_what_the_edits_representation_holds():
    """A local NeRF edit holds its base's modules frozen and trains its local field (or residual) alone; a whole-field
    copy trains and holds Adam's moments for all of it: each planned as benchmarks/edit_size.py measured it at
    nerfstudio's sizes."""
    from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig
    from sked_ns.models.nerf.ngp import SkedNGPModelConfig

    configs = {"nerfacto": SkedNerfactoModelConfig, "instant-ngp": SkedNGPModelConfig}
    measured = json.loads(EDIT_SIZE.read_text())
    for base, config in configs.items():
        for field, entry in measured[base].items():
            options = config(prompt="a hat", nerf_edit_field=field)
            weights = entry["base_weight_bytes"]
            resident = memory_plan.resident_bytes(base, weights, options)
            _close(resident / GB, sum(entry["resident_bytes"].values()) / GB, f"{base} {field} resident")
            trained = memory_plan.trained_bytes(base, weights, options)
            if field in ("local", "local-residual"):  # nerfstudio's sizes put the table at its cap: the plan is exact
                assert trained == pytest.approx(4 * entry["trainable_parameters"]), base
            else:
                assert trained == weights, base
    # The step's gradients are the trained weights': a local edit's residual, not its base.
    work = StepWork(4096.0, 1000.0, 1.0, 65536)
    local = configs["nerfacto"](prompt="a hat", nerf_edit_field="local")
    weights = 80e6
    whole, _ = nerf_side("nerfacto", work, weights)
    residual, _ = nerf_side("nerfacto", work, weights, memory_plan.trained_bytes("nerfacto", weights, local))
    assert whole - residual == pytest.approx(weights - memory_plan.trained_bytes("nerfacto", weights, local))


def _checkpoint(path: Path, state) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"pipeline": {f"_model.{key}": value for key, value in state.items()}, "step": 1}, path)
    return path


def _gaussians(count: int):
    shapes = {"means": (3,), "scales": (3,), "quats": (4,), "features_dc": (3,), "features_rest": (15, 3),
              "opacities": (1,)}
    return {f"gauss_params.{name}": torch.zeros(count, *shape) for name, shape in shapes.items()}


def test_an_edit_saved_as_its_changes_weighs_the_scene_it_composes(tmp_path):
    """A splat edit saved as its changes (its edited and new Gaussians, and which of its base's it keeps) weighs as
    many Gaussians as its scene holds; a local NeRF edit weighs its residual and the base its config names."""
    from sked_ns.engine.weight_bytes import checkpoint_weight_bytes

    whole = checkpoint_weight_bytes(_checkpoint(tmp_path / "splat" / "base.ckpt", _gaussians(20)))
    kept = torch.zeros(20, dtype=torch.bool)
    kept[:12] = True
    changes = checkpoint_weight_bytes(_checkpoint(tmp_path / "splat" / "edit.ckpt",
                                                  {**_gaussians(5), "kept_in_base": kept}))
    assert changes == pytest.approx(whole * 17 / 20)
    base = _checkpoint(tmp_path / "nerf" / "base.ckpt", {"field.weights": torch.zeros(1000)})
    edit = _checkpoint(tmp_path / "nerf" / "edit" / "nerfstudio_models" / "step-1.ckpt",
                       {"local_field.encoding.table": torch.zeros(100)})
    (edit.parent.parent / "config.yml").write_text(
        "!!python/object:types.SimpleNamespace\npipeline: !!python/object:types.SimpleNamespace\n"
        f"  model: !!python/object:types.SimpleNamespace\n    base_checkpoint: {base}\n")
    assert checkpoint_weight_bytes(edit) == 4 * (1000 + 100)
    (edit.parent.parent / "config.yml").unlink()  # its base unknown: what it holds itself
    assert checkpoint_weight_bytes(edit.rename(edit.with_name("step-2.ckpt"))) == 4 * 100


def test_the_default_step_fits_the_targets():
    """The default edit (nerfacto, 128 px): its NeRF side at most 3 GB (fp32, torch hash grids), the whole step
    projected to fp16 at most 8 GB, as measured."""
    entry = _measured()["steps"]["nerfacto@128"]
    assert entry["nerf_side_peak_gb"] <= 3.0
    if "projected_fp16_total_gb" in entry:
        assert entry["projected_fp16_total_gb"] <= 8.0


@pytest.fixture(scope="module")
def tiny_sd(tmp_path_factory):
    return build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny-sd"))


def test_stable_diffusions_weights_are_counted_from_the_file_headers(tiny_sd):
    from diffusers import AutoencoderKL, UNet2DConditionModel

    unet = UNet2DConditionModel.from_pretrained(tiny_sd / "unet")
    vae = AutoencoderKL.from_pretrained(tiny_sd / "vae")
    encoder = sum(p.numel() for name, p in vae.named_parameters() if name.startswith(("encoder.", "quant_conv.")))
    parameters = sum(p.numel() for p in unet.parameters()) + encoder
    config = StableDiffusionGuidanceConfig(model=str(tiny_sd), image_size=512)
    weights, step = sd_bytes(config, "cpu")
    assert weights == 4 * parameters  # fp32 on the CPU, the decoder never loaded
    assert sd_bytes(config, "cuda")[0] == 2 * parameters  # fp16 on a GPU
    config.half_precision = False
    assert sd_bytes(config, "cuda")[0] == 4 * parameters
    config.vae_checkpointing = True
    assert sd_bytes(config, "cpu")[1] <= step
    assert sd_bytes(StableDiffusionGuidanceConfig(model=str(tiny_sd), image_size=256), "cpu")[1] == pytest.approx(step / 4)


def test_chunking_bounds_the_step_and_its_absence_does_not():
    weights = 1e8
    rays = StepWork(rays=128**2, sketch_rays=2 * 128**2, chunk=65536)
    small, _ = nerf_side("nerfacto", rays, weights)
    unchunked, _ = nerf_side("nerfacto", StepWork(rays.rays, rays.sketch_rays, 1.0, 0), weights)
    assert small < unchunked
    bigger, _ = nerf_side("nerfacto", StepWork(4 * rays.rays, rays.sketch_rays, 1.0, 65536), weights)
    huge, _ = nerf_side("nerfacto", StepWork(4 * rays.rays, rays.sketch_rays, 1.0, 0), weights)
    assert bigger - small < huge - unchunked  # rays cost their kept bytes only, not their activations


def _config(scene, tmp_path, **model):
    from sked_ns.engine.edit_run import edit_config

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path / "out", iterations=5)
    model.setdefault("field_chunk", 65536)  # the plan's refusals at a fixed chunk (the auto choice: its own test)
    for key, value in model.items():
        setattr(config.pipeline.model, key, value)
    return config


def test_an_edit_that_cannot_fit_is_refused_with_the_options_that_do(scene, tmp_path, monkeypatch, capsys):
    from sked_ns.engine.trainer import resolve_edit

    memory_plan._PRINTED.clear()
    config = _config(scene, tmp_path, guidance_resolution=128, silhouette_resolution=128)
    resolve_edit(config)
    plan = memory_plan.plan_edit(config)
    printed = capsys.readouterr().out
    assert plan.peak > 0 and "Expected peak memory on cpu" in printed
    assert f"Expected time per step on cpu: about {step_time.duration(plan.step_time.seconds)}" in printed
    small = memory_plan.plan_edit(_resolved(scene, tmp_path / "small", guidance_resolution=64,
                                            silhouette_resolution=64)).peak
    assert small < plan.peak
    # A machine with room for the 64 px edit but not the 128 px one: refused, naming the option that fits.
    monkeypatch.setattr(memory_plan, "_free_swap_bytes", lambda: 0.0)
    monkeypatch.setattr(memory_plan, "_free_bytes", lambda device: (small + plan.peak) / 2)
    config = _config(scene, tmp_path, guidance_resolution=128, silhouette_resolution=128)
    with pytest.raises(SkedUserError) as refused:
        resolve_edit(config)
    message = str(refused.value)
    assert "--pipeline.model.guidance-resolution 64" in message and "this machine" in message and "swap" in message
    assert not (tmp_path / "out").exists()  # refused before anything is written
    monkeypatch.setattr(memory_plan, "_free_bytes", lambda device: small / 10)
    with pytest.raises(SkedUserError, match="None of the memory options fits"):
        resolve_edit(_config(scene, tmp_path, guidance_resolution=128, silhouette_resolution=128))
    # Swap can hold it: it runs, with a warning that it will swap.
    monkeypatch.setattr(memory_plan, "_free_swap_bytes", lambda: 2.0 * plan.peak)
    with pytest.warns(UserWarning, match="it will swap"):
        resolve_edit(_config(scene, tmp_path, guidance_resolution=128, silhouette_resolution=128))
    assert not (tmp_path / "out").exists()


def _resolved(scene, tmp_path, **model):
    from sked_ns.engine.trainer import resolve_edit

    config = _config(scene, tmp_path, **model)
    resolve_edit(config)
    return config


@pytest.mark.parametrize("representation, name", [("nerfacto", "nerfacto"), ("instant-ngp", "ngp")])
def test_a_local_edits_step_is_planned_from_its_own_measurement(representation, name):
    """A local NeRF edit's step (benchmarks/memory.py --edit-field local) is planned within a quarter with its own
    coefficients, which are that file's; the whole copy's would plan it well above what it holds."""
    from sked_ns.models.registry import representation_named

    result = json.loads((RESULTS.parent / f"memory_{name}_local_field.json").read_text())
    options = representation_named(representation).sked_config_class()(prompt="a hat", nerf_edit_field="local")
    local = memory_plan.LOCAL_STEP_MODELS[representation]
    for key, value in result["plan_coefficients"][representation].items():
        if key not in ("activation_per_ray", "resident_per_weight_byte"):  # unchunked: not measured; resident: apart
            assert getattr(local, key) == pytest.approx(value, rel=0.01), key
    for key, entry in result["steps"].items():
        assert entry["settings"]["nerf_edit_field"] == "local", key
        weights = entry["settings"]["base_weights_gb"] * GB
        trained = memory_plan.trained_bytes(representation, weights, options)
        step, held = nerf_side(representation, _work(entry), weights, trained, local=True)
        _close(step / GB, entry["chunked"]["step_peak_gb"], f"{key} local step")
        _close(held / GB, entry["chunked"]["held_at_guidance_gb"], f"{key} local held at the guidance")
        whole_copy, _ = nerf_side(representation, _work(entry), weights, trained)
        assert whole_copy > (1 + WITHIN) * entry["chunked"]["step_peak_gb"] * GB, key


def test_no_nan_in_the_plan_at_the_extremes():
    for representation in memory_plan.STEP_MODELS:
        for work in (StepWork(0.0, 0.0, 1.0, 0), StepWork(1e9, 1e9, 8.0, 1), StepWork(1.0, 0.0, 0.25, 10**9)):
            for local in (False, True):
                step, held = nerf_side(representation, work, 0.0, local=local)
                assert torch.isfinite(torch.tensor([step, held])).all() and step >= held >= 0


def test_the_plans_coefficients_are_the_benchmarks():
    """STEP_MODELS and the SD figures are what benchmarks/memory.py derived from its measurements (rerun it, then
    copy its plan_coefficients)."""
    coefficients = _measured()["plan_coefficients"]
    for representation, model in memory_plan.STEP_MODELS.items():
        if representation not in coefficients:
            continue
        for name, value in coefficients[representation].items():
            assert getattr(model, name) == pytest.approx(value, rel=0.01, abs=1.0), f"{representation}.{name}"
    sd = coefficients.get("stable_diffusion")
    if sd:
        assert memory_plan.SD_STEP_BYTES_AT_512 == pytest.approx(sd["step_bytes_at_512"], rel=0.01)
        assert memory_plan.VAE_CHECKPOINTING_SHARE == pytest.approx(sd["vae_checkpointing_share"], rel=0.01)


def test_the_field_chunk_is_chosen_by_the_plan_where_left_to_it(scene, tmp_path, monkeypatch):
    """-1: no chunks where the unchunked step fits the device's free memory, the checkpointed chunk where it does not;
    a chunk the user typed is kept."""
    from sked_ns.method.options import AUTO_FIELD_CHUNK, CHECKPOINTED_FIELD_CHUNK

    memory_plan._PRINTED.clear()
    unchunked = _config(scene, tmp_path / "a", field_chunk=0, guidance_resolution=64, silhouette_resolution=64)
    chunked = _config(scene, tmp_path / "b", field_chunk=CHECKPOINTED_FIELD_CHUNK, guidance_resolution=64,
                      silhouette_resolution=64)
    peaks = [memory_plan.plan_edit(_resolved_copy(config)).peak for config in (unchunked, chunked)]
    assert peaks[1] < peaks[0]
    for free, expected in ((10 * peaks[0], 0), ((peaks[0] + peaks[1]) / 2, CHECKPOINTED_FIELD_CHUNK)):
        monkeypatch.setattr(memory_plan, "_free_bytes", lambda device, free=free: free)
        config = _config(scene, tmp_path / "c", field_chunk=AUTO_FIELD_CHUNK, guidance_resolution=64,
                         silhouette_resolution=64)
        _resolve(config)
        assert config.pipeline.model.field_chunk == expected
    typed = _config(scene, tmp_path / "d", field_chunk=4096, guidance_resolution=64, silhouette_resolution=64)
    _resolve(typed)
    assert typed.pipeline.model.field_chunk == 4096


def _resolve(config):
    from sked_ns.engine.trainer import resolve_edit

    resolve_edit(config)


def _resolved_copy(config):
    import copy

    config = copy.deepcopy(config)
    _resolve(config)
    return config


def _reference_step_seconds(device, rays, sketch_rays, samples_per_ray, scale, sd_size):
    """A step's expected seconds, written out: every field sample at the device's rate, plus SD's step scaled
    by its input's area."""
    speed = step_time.STEP_SPEEDS[device]
    sd = speed.sd_step_at_512 * (sd_size / 512) ** 2 if sd_size else 0.0
    return (rays + sketch_rays) * samples_per_ray * scale * speed.per_field_sample + sd


@pytest.mark.parametrize("device", ["cpu", "cuda"])
@pytest.mark.parametrize("representation", ["nerfacto", "instant-ngp"])
@pytest.mark.parametrize("rays, sketch_rays, scale, sd_size", [
    (128**2, 1854, 1.0, 512), (1024**2, 1854, 1.0, 512), (24**2, 100, 0.25, None), (64**2, 0, 1.5, 256)])
def test_the_step_time_is_its_samples_and_its_guidance_at_the_devices_rates(device, representation, rays,
                                                                          sketch_rays, scale, sd_size):
    work = StepWork(float(rays), float(sketch_rays), scale)
    samples = memory_plan.field_samples(representation, work)
    time = step_time.step_time(device, samples, sd_size)
    expected = _reference_step_seconds(device, rays, sketch_rays, memory_plan.STEP_MODELS[representation]
                                       .samples_per_ray, scale, sd_size)
    assert time.whole and time.seconds == pytest.approx(expected, rel=1e-9)


def test_a_step_time_without_a_measured_rate_is_a_lower_bound_or_none():
    splat = memory_plan.field_samples("splatfacto", StepWork(128.0**2))
    assert splat is None  # no splat step measured per pixel: only the guidance's step counts
    bound = step_time.step_time("cpu", splat, 512)
    assert not bound.whole and bound.seconds == step_time.STEP_SPEEDS["cpu"].sd_step_at_512
    assert step_time.step_time("cpu", splat, None) is None
    assert step_time.step_time("mps", 1e6, 512) is None  # no step measured on an Apple GPU
    # Stable Diffusion on another device is timed at that device's rate.
    on_gpu = step_time.step_time("cpu", 1e6, 512, sd_device_type="cuda")
    assert on_gpu.seconds == pytest.approx(1e6 * step_time.STEP_SPEEDS["cpu"].per_field_sample
                                           + step_time.STEP_SPEEDS["cuda"].sd_step_at_512)


def test_the_cpu_rates_are_the_measured_full_size_step():
    """STEP_SPEEDS["cpu"] is benchmarks/results/gpu_check_cpu_full.json divided out: its step less its bare SD step,
    over its random view and two sketch views (whole, at the random view's size, when it was measured) at nerfacto's
    samples per ray."""
    from nerfstudio.models.nerfacto import NerfactoModelConfig

    result = json.loads((RESULTS.parent / "gpu_check_cpu_full.json").read_text())
    nerfacto = NerfactoModelConfig()
    samples_per_ray = nerfacto.num_nerf_samples_per_ray + sum(nerfacto.num_proposal_samples_per_ray)
    assert samples_per_ray == memory_plan.STEP_MODELS["nerfacto"].samples_per_ray
    side = result["settings"]["guidance_resolution"]
    assert result["settings"]["sd_image_size"] == 512 and result["settings"]["precision"].startswith("fp32")
    speed = step_time.STEP_SPEEDS["cpu"]
    assert speed.sd_step_at_512 == pytest.approx(result["sd_floor_ms"] / 1000, rel=1e-3)
    nerf_seconds = (result["ms_per_iteration"] - result["sd_floor_ms"]) / 1000
    assert speed.per_field_sample == pytest.approx(nerf_seconds / (3 * side**2 * samples_per_ray), rel=1e-3)


def test_a_step_of_minutes_is_warned_at_the_threshold_with_what_to_lower():
    threshold = step_time.SLOW_STEP_SECONDS
    assert step_time.slow_step_warning(step_time.StepTime(threshold, True, "x"), "cpu") is None
    message = step_time.slow_step_warning(step_time.StepTime(threshold * 1.01, True, "x"), "cpu")
    assert "guidance-resolution" in message and "--machine.device-type cuda" in message
    on_gpu = step_time.slow_step_warning(step_time.StepTime(threshold * 1.01, True, "x"), "cuda")
    assert "guidance-resolution" in on_gpu and "device-type" not in on_gpu
    # The case found: a 1024 px guidance render of a nerfacto edit on the CPU, warned; the default 128 px on a GPU not.
    large = step_time.step_time("cpu", memory_plan.field_samples("nerfacto", StepWork(1024.0**2, 1854.0)), 512)
    assert step_time.slow_step_warning(large, "cpu") is not None
    default = step_time.step_time("cuda", memory_plan.field_samples("nerfacto", StepWork(128.0**2, 1854.0)), 512)
    assert step_time.slow_step_warning(default, "cuda") is None


@pytest.mark.parametrize("seconds, said", [(0.25, "0.25 s"), (1.41, "1.4 s"), (42, "42 s"), (150, "2.5 min"),
                                           (7200, "2.0 h"), (20 * 3600, "20 h"), (3 * 86400, "3.0 days"),
                                           (2593 * 86400, "2,593 days")])
def test_durations_are_said_in_their_unit(seconds, said):
    assert step_time.duration(seconds) == said


@pytest.mark.parametrize("device, argv, warned", [
    ("cpu", ["ns-train", "sked", "--mixed-precision", "True"], True),
    ("cpu", ["ns-train", "sked"], False),  # the preset's own True: for a GPU, not typed
    ("cuda", ["ns-train", "sked", "--mixed-precision", "True"], False),
])
def test_mixed_precision_typed_for_the_cpu_is_warned(device, argv, warned):
    import warnings

    from sked_ns.engine.edit_inputs import warn_idle_mixed_precision
    from sked_ns.engine.presets import edit_preset

    config = edit_preset()
    config.machine.device_type = device
    assert config.mixed_precision
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warn_idle_mixed_precision(config, argv)
    assert any("--mixed-precision True: has no effect on the CPU" in str(w.message) for w in seen) == warned
