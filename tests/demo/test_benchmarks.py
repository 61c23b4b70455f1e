"""The benchmark scripts run end to end (smoke size) and their bookkeeping is right."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import speed_accuracy  # noqa: E402


def test_rows_carried_over_keep_the_commit_they_were_measured_at():
    older = {"commit": "new1", "runs": [{"name": "sked", "ios": 0.9}, {"name": "sweep", "note": "not re-measured: old0"},
                                        {"name": "other"}]}
    kept = speed_accuracy.carried_over(older, ["sked", "sweep"], "before.json")
    assert [run["name"] for run in kept] == ["sked", "sweep"]
    assert kept[0]["note"] == "not re-measured: from before.json (new1)" and kept[0]["ios"] == 0.9
    assert kept[1]["note"] == "not re-measured: old0"


def test_pareto_front_keeps_only_undominated_points():
    points = [(10.0, 20.0), (5.0, 18.0), (20.0, 19.0), (5.0, 18.0), (1.0, 10.0), (30.0, 25.0)]
    # (20, 19) is beaten by (10, 20); ties are on the front together.
    assert speed_accuracy.pareto(points) == [True, True, False, True, True, True]


def test_plan_scales_presets_and_covers_every_knob():
    runs = speed_accuracy.plan("cpu", quick=False)
    presets = {r["name"]: r for r in runs if r["group"] == "preset" and r["scene"] == "hat"}
    assert presets["sked"]["iterations"] == 100 and presets["sked"]["guidance_resolution"] == 32
    assert presets["sked-fast"]["iterations"] < presets["sked"]["iterations"] < presets["sked-quality"]["iterations"]
    assert {r["ablation"] for r in runs if r["group"] == "ablation"} == {"no-preserve", "no-silhouette", "text-only"}
    swept = {r["name"].split("=")[0] for r in runs if r["group"] == "sweep"}
    assert swept == {"guidance_resolution", "samples_per_ray_scale", "iterations", "mixed_precision", "log2_hashmap_size"}
    assert {r["scene"] for r in runs if r["group"] != "sweep"} == {"hat", "handle", "antenna"}


@pytest.mark.slow
def test_speed_accuracy_quick_run_writes_json_and_plot(tmp_path):
    output = tmp_path / "speed_accuracy.json"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "speed_accuracy.py"), "--quick", "--output", str(output)],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    data = json.loads(output.read_text())
    (row,) = data["summary"]
    for key in ("seconds_total", "ms_per_iteration", "peak_memory_mb", "ios", "psnr_outside", "psnr_target_inside"):
        assert row[key] > 0, key
    assert "CPU protocol" in data["protocol"] and output.with_suffix(".png").stat().st_size > 10_000
    assert not output.with_suffix(".partial.json").exists(), "a finished run leaves no partial results behind"
    assert "| sked-fast | preset |" in result.stdout


@pytest.mark.slow
def test_sds_iteration_smoke_run_with_a_tiny_model(tmp_path):
    output = tmp_path / "sds.json"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "sds_iteration.py"), "--size", "tiny", "--iterations", "2",
                             "--resolution", "16", "--image-size", "32", "--output", str(output)], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    data = json.loads(output.read_text())
    split = data["split_ms (synchronised)"]
    assert {"render", "vae_encode", "unet", "losses_and_backward_and_step"} <= set(split)
    assert all(value > 0 for value in split.values()) and data["iteration_ms"] > 0
    assert "random weights" in data["diffusion_model"]


@pytest.mark.slow
def test_gpu_check_smoke_run_on_the_cpu(tmp_path):
    """The CUDA check's CPU twin: every phase runs and the issue's figures are in the JSON."""
    output = tmp_path / "gpu_check.json"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "gpu_check.py"), "--device", "cpu", "--size", "tiny",
                             "--output", str(output)], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    data = json.loads(output.read_text())
    assert data["failed_phases"] == []
    for edit in ("nerfacto", "ngp", "splat"):
        entry = data[edit]
        assert entry["iterations"] == 3 and entry["ms_per_iteration"] > 0 and entry["ratio_to_sd_floor"] > 0
        assert entry["extrapolated_10k_seconds"] > 10_000 * entry["ms_per_iteration"] / 1000
    assert data["ngp"]["model"] == "SkedNGPModel" and data["nerfacto"]["model"] == "SkedNerfactoModel"
    assert data["splat"]["model"] == "SkedSplatModel" and "splat_raster_check" not in data["phases"]  # CUDA only
    assert data["marcher_check"]["relative_difference"] == 0.0  # the same torch marcher on both sides here
    assert data["ms_per_iteration"] == data["nerfacto"]["ms_per_iteration"] and data["sd_floor_ms"] > 0
    assert data["nerfacto"]["final_save_seconds"] > 0 and data["peak_rss_gb"] >= data["nerfacto"]["peak_rss_gb"] > 0.1
    assert "RANDOM weights" in data["description"]
    assert output.with_name("gpu_check_profile.txt").stat().st_size > 1000


def test_gpu_check_runs_every_test_file_with_cuda_only_tests():
    """Its CUDA phase names test files by path: each exists, and no file with a CUDA-only test is left out."""
    import gpu_check

    tests = BENCHMARKS.parent / "tests"
    listed = {tests / path for path in gpu_check.CUDA_TESTS}
    assert all(path.is_file() for path in listed)
    marker = "@pytest.mark.skipif(not torch.cuda.is_available()"
    cuda_only = {path for path in tests.rglob("test_*.py")
                 if marker in path.read_text() and path != Path(__file__).resolve()}  # this file names it only here
    assert cuda_only and cuda_only <= listed


def test_gpu_check_records_the_rasterizer_agreement(tmp_path, monkeypatch):
    """The splat rasterizer check writes its differences into the results, not only its status."""
    import gpu_check
    import splat_agreement

    monkeypatch.setattr(splat_agreement, "compare_with_gsplat",
                        lambda device: {"image": 2e-6, "image_scale": 1.0, "grad_means": 1e-5, "grad_means_scale": 0.5})
    check = gpu_check.Check(tmp_path / "gpu_check.json", budget_s=60)
    check.phase("splat_raster_check", lambda: gpu_check.splat_raster_check(check, "cpu"))
    written = json.loads((tmp_path / "gpu_check.json").read_text())
    assert written["phases"]["splat_raster_check"]["status"] == "ok"
    assert written["splat_raster_check"]["relative"] == {"image": 2e-6, "grad_means": 2e-5}
    assert written["splat_raster_check"]["worst_relative"] == 2e-5


def test_gpu_check_times_steady_iterations_without_the_final_save_and_counts_saves_once():
    """Synthetic clock: a compiling first step, 1 s steps, then nerfstudio's end-of-training save (5 s)."""
    import gpu_check

    starts, final_save, end = [0.0, 10.0, 11.0, 12.0], 13.0, 18.0
    durations = gpu_check.iteration_seconds(starts, [final_save], end)
    assert durations.tolist() == [10.0, 1.0, 1.0, 1.0]  # the last step ends where the save begins
    # A save inside the loop (step_check at steps_per_save) ends its step too.
    assert gpu_check.iteration_seconds([0.0, 4.0], [2.5, 6.0], 7.0).tolist() == [2.5, 2.0]
    # nerfstudio saves at steps 500, ..., 9500 of range(10_000) and once after the loop: 20, each counted once.
    assert gpu_check.checkpoint_saves(10_000, 500) == 20 and gpu_check.checkpoint_saves(3, 10**9) == 1
    entry = {"setup_seconds": 2.0, "load_diffusion_seconds": 3.0, "first_iteration_seconds": float(durations[0]),
             "ms_per_iteration": 1000 * float(durations[1:].mean()), "checkpoint_seconds": 5.0, "eval_image_seconds": 7.0}
    total = gpu_check.extrapolated_seconds(entry, 10_000, steps_per_save=500, steps_per_eval_image=1000)
    assert total == 2.0 + 3.0 + 10.0 + 9_999 * 1.0 + 20 * 5.0 + 9 * 7.0  # eval images at steps 1000, ..., 9000


def test_bare_sd_step_runs_under_the_edits_autocast(tmp_path):
    """The SD floor is timed in the edit's autocast context (dtype included), read inside SkedTrainer's iteration."""
    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "engine"))  # importable when tests/engine is not run
    import sds_iteration
    from test_nerfstudio_glue import toy_trainer

    def state():
        return torch.is_autocast_enabled("cpu"), torch.get_autocast_dtype("cpu")

    in_edit = []
    trainer = toy_trainer(tmp_path, lambda w: in_edit.append(state()) or (w**2).sum())
    trainer.mixed_precision, trainer.autocast_dtype = True, torch.float16  # not the CPU's default, bfloat16
    trainer.train_iteration(0)

    in_bare = []

    class Guidance:
        dtype, embeddings = torch.float32, {"": torch.zeros(77, 8), "front": torch.ones(77, 8)}

        def encode(self, image):
            in_bare.append(("encode", *state()))
            return image.mean(1, keepdim=True) * 2

        def _unet_forward(self, latents, t, encoder_hidden_states):
            in_bare.append(("unet", *state()))
            assert latents.shape[0] == 2 == encoder_hidden_states.shape[0] and not torch.is_grad_enabled()
            return latents

    trainer.pipeline.model.guidance = Guidance()
    image = torch.rand(1, 3, 4, 4, requires_grad=True)
    sds_iteration.bare_sd_step(trainer, image)
    assert in_edit == [(True, torch.float16)]
    assert in_bare == [("encode", *in_edit[0]), ("unet", *in_edit[0])]
    assert image.grad is not None and state() == (False, torch.bfloat16), "the encoder's backward ran, and autocast is off again"


def test_a_base_on_a_white_backdrop_trains_with_a_white_background(tmp_path, monkeypatch):
    """The demo sphere's photos show nothing but the object on white: its base is told so (nerfacto's default
    last_sample fills the empty space with white mass); the other scenes keep the default. A base trained with the
    other background is never reused."""
    import edit_quality
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    def base_config(scene):
        return tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.base_arguments(
            scene, tmp_path / "data", tmp_path / "runs", edit_quality.BASE_ITERATIONS))

    for scene in ("hat", "antenna"):
        config = base_config(scene)
        assert config.pipeline.model.background_color == "white", scene
        assert config.pipeline.datamanager.train_num_rays_per_batch == edit_quality.BASE_RAYS
    for scene in ("vase", "marker", "lawn"):
        assert base_config(scene).pipeline.model.background_color == "last_sample", scene
    # An earlier last_sample base in the same work folder is not taken for the hat's white one.
    (tmp_path / "runs" / "base" / "nerfacto" / "base" / "nerfstudio_models").mkdir(parents=True)
    trained = []
    monkeypatch.setattr(edit_quality, "run", lambda command, log: trained.append(command))
    run_dir = edit_quality.train_base("hat", tmp_path / "data", tmp_path / "runs", 400, tmp_path / "base.log")
    assert len(trained) == 1 and "white" in trained[0] and run_dir.name == "base-white"
    assert edit_quality.train_base("vase", tmp_path / "data", tmp_path / "runs", 400, tmp_path / "b.log").name == "base"
    assert len(trained) == 1, "the vase's last_sample base is reused"


def test_benchmark_command_lines_parse_as_ns_train_parses_them(tmp_path):
    """The benchmarks type `ns-train sked` as a user does: nerfstudio's own CLI must read what they mean."""
    import edit_quality
    import gpu_check
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    paths = {"sketches": tmp_path / "sketches", "data": tmp_path / "data"}
    protocol = {**edit_quality.PROTOCOLS["cpu-100"]}
    paper = next(flags for name, flags in edit_quality.VARIANTS.items() if name.startswith("paper"))
    config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
        tmp_path / "base", paths, "vase", protocol, tmp_path / "out", extra=paper))
    model = config.pipeline.model
    assert type(model.guidance).__name__ == "ReferenceGuidanceConfig" and model.guidance.target == "vase"
    assert model.lambda_photo == 0 and model.guidance_resolution == protocol["resolution"]
    # The paper variant is the paper's model: its L_pres target, its L_sil, no colour residual.
    assert (model.preservation_target, model.silhouette_opacity, model.colour_residual) == ("occupancy", "any", False)
    assert config.pipeline.datamanager.dataparser.data == paths["data"]
    # A variant's guidance flags reach the guidance (they must follow its subcommand).
    quiet = edit_quality.VARIANTS[edit_quality._variant("no-guidance")]  # named by its tag: the names hold commas
    with pytest.raises(SystemExit, match="no-guidance"):
        edit_quality._variant("no-such-variant")  # the error lists the tags
    config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
        tmp_path / "base", paths, "crate", protocol, tmp_path / "out", extra=quiet))
    assert config.pipeline.model.guidance.weight == 0 and config.pipeline.model.guidance.target == "crate"
    per_sketch = edit_quality.VARIANTS[edit_quality._variant("sketch-normalised-sil")]
    config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
        tmp_path / "base", paths, "antenna", protocol, tmp_path / "out", extra=per_sketch))
    assert config.pipeline.model.silhouette_normalisation == "sketch"
    faster = edit_quality.VARIANTS[edit_quality._variant("grid-lr-3x")]
    config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
        tmp_path / "base", paths, "antenna", protocol, tmp_path / "out", extra=faster))
    grids = config.optimizers["hash_grids"]
    assert grids["optimizer"].lr == 0.15 and grids["scheduler"].lr_final == 0.015
    # A tuple field's flag takes both its values; a guidance flag still follows its subcommand.
    narrow = edit_quality.VARIANTS[edit_quality._variant("fov-20-40")]
    point = edit_quality.VARIANTS[edit_quality._variant("point-target")]
    config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
        tmp_path / "base", paths, "vase", protocol, tmp_path / "out", extra=[*narrow, *point]))
    assert tuple(config.pipeline.datamanager.fov_range) == (20.0, 40.0) and config.pipeline.datamanager.edit_fill == 0
    assert config.pipeline.model.guidance.sampling == "pixel-centre"
    # The two NeRF edit fields, pinned whatever the default, and another seed for the run-to-run spread.
    for tag, value in (("local-field", "local"), ("full-copy", "full-copy")):
        flags = [*edit_quality.VARIANTS[edit_quality._variant(tag)], "--machine.seed", "3"]
        config = tyro.cli(AnnotatedBaseConfigUnion, args=edit_quality.edit_arguments(
            tmp_path / "base", paths, "hat", protocol, tmp_path / "out", extra=flags))
        assert config.pipeline.model.nerf_edit_field == value and config.machine.seed == 3
    assert edit_quality._run_tag("nerfacto", "cpu-100", "local-field", 3) != edit_quality._run_tag(
        "nerfacto", "cpu-100", "local-field")

    arguments = gpu_check.edit_arguments(tmp_path / "base", tmp_path, tmp_path / "sd", "nerfacto", 7, "tiny", "cpu")
    config = tyro.cli(AnnotatedBaseConfigUnion, args=["sked", *arguments])
    guidance = config.pipeline.model.guidance
    assert type(guidance).__name__ == "StableDiffusionGuidanceConfig"
    assert guidance.model == str(tmp_path / "sd") and guidance.image_size == 32 and config.max_num_iterations == 7
    # Full size at smaller renders (the CPU rehearsal): SD keeps its 512 px input, the views shrink.
    arguments = gpu_check.edit_arguments(tmp_path / "base", tmp_path, tmp_path / "sd", "nerfacto", 3, "full", "cpu", 64)
    model = tyro.cli(AnnotatedBaseConfigUnion, args=["sked", *arguments]).pipeline.model
    assert (model.guidance_resolution, model.silhouette_resolution, model.guidance.image_size) == (64, 64, 512)


def test_sketch_view_fill_credits_a_correct_edit_that_kept_content_hides():
    """A sketch holds the added part's hidden pixels too (the crate's wall in front of half the handle): the exact
    target fills only some of it by region IoS, all of it where the target shows the part, and nothing fills 0."""
    import edit_quality
    import torch

    from sked_ns.demo.scenes.objects import SCENES, visible_added_part
    from sked_ns.method.preservation import SketchDistanceField
    from sked_ns.sketches.sketch_set import sketch_view_at

    views = SCENES["crate"].sketch_set().views
    beta, resolution = 0.025, 64
    camera, mask = sketch_view_at(views[0], resolution)
    truth = visible_added_part(SCENES["crate"], views[0].camera_to_world[:3], float(camera.fx), resolution, resolution)
    # The visible part lies in the sketch; from this view the crate hides most of it.
    assert (truth["visible"] & ~mask).sum() <= 0.05 * truth["visible"].sum()
    assert (truth["visible"] & mask).sum() < 0.5 * mask.sum()
    field = SketchDistanceField(views)
    weight = field.preservation_weight(truth["points"].reshape(-1, 3), beta).reshape(mask.shape)
    exact = torch.where(truth["hit"], 1.0 - weight, torch.zeros_like(weight))
    nothing = torch.zeros(mask.shape)
    scores = edit_quality.view_fill("crate", views[0], field, beta, resolution, exact, nothing)
    assert scores["ios_region_perfect"] < 0.5 and scores["ios_visible"] > 0.97 and scores["ios_visible_base"] == 0.0
    # A third view sees the handle whole: there the two measures agree.
    whole = edit_quality.view_fill("crate", views[2], field, beta, resolution, nothing, nothing)
    assert whole["ios_region_perfect"] > 0.95 and whole["ios_visible"] == 0.0


def test_edit_quality_refuses_an_instant_ngp_base_of_a_scene_without_one(tmp_path):
    """Only the demo sphere's scenes have an instant-ngp base: another is refused in one line, nothing written."""
    output, work = tmp_path / "results.json", tmp_path / "work"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "edit_quality.py"), "--base", "instant-ngp", "--scenes",
                             "hat,vase", "--output", str(output), "--work", str(work)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "--base instant-ngp" in lines[0] and "hat,vase" in lines[0], result.stderr[-2000:]
    assert not output.exists() and not work.exists()


def test_silhouette_rim_splits_the_changed_regions_error_into_rim_and_interior():
    """A part drawn a pixel too small has all its error on the rim (fill 0 there), one drawn too large none inside the
    region but on the band around it; rim and interior add up to the region's mean squared error."""
    import numpy as np
    import silhouette_rim

    size = 32
    y, x = np.mgrid[:size, :size]
    disc = lambda radius: ((x - 15.5) ** 2 + (y - 15.5) ** 2 <= radius ** 2)  # noqa: E731
    base, part = np.zeros((size, size, 3), np.float32), np.array([1.0, 0.5, 0.0], np.float32)
    truth = np.where(disc(8)[..., None], part, base)
    exact = silhouette_rim.view_figures(truth, base, truth, disc(8))
    assert exact["rim_share"] == 0.0 and exact["interior_share"] == 0.0 and exact["rim_fill"] == pytest.approx(1.0)
    small = silhouette_rim.view_figures(np.where(disc(7)[..., None], part, base), base, truth, disc(8))
    assert small["interior_share"] == 0.0 and small["rim_share"] > 0.0 and small["rim_fill"] < 0.5
    mse = float(((np.where(disc(7)[..., None], part, base) - truth) ** 2).mean(-1)[disc(8)].mean())
    assert small["rim_share"] + small["interior_share"] == pytest.approx(mse, rel=1e-6)
    assert small["psnr_changed"] == pytest.approx(-10 * np.log10(mse), rel=1e-6)
    large = silhouette_rim.view_figures(np.where(disc(9)[..., None], part, base), base, truth, disc(8))
    assert large["rim_share"] == 0.0 and large["interior_share"] == 0.0 and large["band_error"] > 0.1


def test_silhouette_rim_refuses_a_sample_factor_below_one_before_reading_anything(tmp_path):
    """--final-samples 0 would render no field samples: one error line naming the flag, nothing read or written."""
    output = tmp_path / "rim.json"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "silhouette_rim.py"), "--work", str(tmp_path / "none"),
                             "--tags", "long-local-field", "--final-samples", "1", "0", "--output", str(output)],
                            capture_output=True, text=True, timeout=120)
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert result.returncode != 0 and len(lines) == 1 and "--final-samples 0" in lines[0], result.stderr[-2000:]
    assert not output.exists()


def test_silhouette_rim_multiplies_field_samples_only_where_an_edit_has_a_proposal_sampler():
    """An edit without a proposal sampler (instant-ngp's) renders as saved at factor 1 and is refused above it."""
    from types import SimpleNamespace

    import silhouette_rim

    sampler = SimpleNamespace(num_nerf_samples_per_ray=12)
    nerfacto, ngp = SimpleNamespace(model=SimpleNamespace(proposal_sampler=sampler)), SimpleNamespace(model=object())
    assert silhouette_rim.field_sampler(nerfacto, Path("edit"), [1, 4]) is sampler
    assert silhouette_rim.field_sampler(ngp, Path("edit"), [1]) is None
    with pytest.raises(SystemExit, match=r"^error: --final-samples 4: edit is not an edit of a nerfacto base"):
        silhouette_rim.field_sampler(ngp, Path("edit"), [1, 4])


def test_the_harness_names_each_call_of_a_step_and_restarts_per_step():
    """A step's n-th render is its n-th part (the last name after that), counted afresh after each reset; the
    wrapped method still returns its own result, and unwrapping restores it."""
    import contextlib

    import harness

    class Model:
        def render(self, value):
            return value * 2

    seen = []

    @contextlib.contextmanager
    def context(name):
        seen.append(name)
        yield

    model = Model()
    reset = harness.marked(model, "render", ["random_view", "sketch_view"], context)
    assert [model.render(v) for v in (1, 2, 3)] == [2, 4, 6]
    reset()
    model.render(4)
    assert seen == ["random_view", "sketch_view", "sketch_view", "random_view"]
    undo = harness.wrap(model, "render", contextlib.nullcontext)
    undo()
    assert model.render(5) == 10 and "render" in vars(model)  # the marked one again


def test_the_harness_times_only_the_calls_after_the_warm_up():
    import harness

    calls = []
    times = harness.timed_calls(lambda: calls.append(1), repeats=3, device="cpu", warmup=2)
    assert len(calls) == 5 and len(times) == 3 and all(t >= 0 for t in times)
    environment = harness.environment("cpu")
    assert {"python", "torch", "device", "machine", "torch_threads", "commit"} <= set(environment)


def test_the_memory_meter_counts_exactly_what_torch_allocates():
    from memory_meter import live_tensor_bytes, metered, part

    x = torch.randn(1000, 1000, requires_grad=True)  # 4 MB
    with metered() as peaks:
        with part("forward"):
            y = (x @ x).relu()  # the product, then its relu (saved for the backward pass): 8 MB at once
            loss = (y * 2).sum()
            del y
        with part("backward"):
            loss.backward()  # x.grad stays
    megabyte = 4_000_000
    assert peaks.parts["forward"] == pytest.approx(2 * megabyte, abs=1024)
    assert peaks.end_bytes == pytest.approx(megabyte, abs=1024)  # x.grad
    assert peaks.peak_bytes >= peaks.parts["forward"]
    assert peaks.parts_held_at_start["backward"] > 0
    assert live_tensor_bytes(x) == 2 * megabyte  # x and its gradient
    assert live_tensor_bytes({"a": [x, x.grad]}) == 2 * megabyte  # shared storages counted once


@pytest.mark.slow
def test_memory_benchmark_smoke_run(tmp_path):
    """Every part of the step is measured for each base kind, the model of the plan gets its inputs, and chunking
    cuts the NeRF side."""
    output = tmp_path / "memory.json"
    # Chunks small enough to be many at 16 px (a NeRF renders the sketch views at their masks' pixels only).
    result = subprocess.run([sys.executable, str(BENCHMARKS / "memory.py"), "--sd", "tiny", "--resolutions", "16",
                             "--silhouette-resolution", "16", "--base-steps", "5", "--field-chunk", "4096",
                             "--output", str(output)],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    data = json.loads(output.read_text())
    assert set(data["steps"]) == {"nerfacto@16", "instant-ngp@16", "splatfacto@16"}
    for key, entry in data["steps"].items():
        step = entry["chunked"]
        assert {"random_view_render_gb", "sketch_view_render_gb", "backward_gb", "optimiser_gb",
                "held_at_guidance_gb"} <= set(step), key
        assert entry["nerf_side_peak_gb"] > sum(entry["resident_gb"].values()) > 0
        assert entry["projected_fp16_total_gb"] <= entry["total_fp32_gb"]
        assert entry["settings"]["work"]["rays"] > 0 and entry["settings"]["base_weights_gb"] > 0
    for key in ("nerfacto@16", "instant-ngp@16"):
        assert data["steps"][key]["nerf_side_peak_unchunked_gb"] > data["steps"][key]["nerf_side_peak_gb"]
    sd = data["stable_diffusion"]
    assert sd["guidance_step_gb"] > 0 and sd["vae_encode_and_backward_gb"] > 0 and sd["unet_cfg_gb"] > 0
    assert "| nerfacto@16 |" in result.stdout


@pytest.mark.parametrize("script, flags", [
    ("step_census.py", ["--out", "{output}", "--workdir", "{work}"]),
    ("memory.py", ["--output", "{output}", "--workdir", "{work}", "--sd", "none"]),
    ("edit_quality.py", ["--output", "{output}", "--work", "{work}", "--quick"]),
])
@pytest.mark.parametrize("busy", ["output", "work"])
def test_a_benchmark_refuses_an_output_or_work_folder_another_one_writes(tmp_path, script, flags, busy):
    """Two benchmarks on one results file or one work folder would interleave their writes: the second is refused
    in one line before it measures or writes anything."""
    from lock_helpers import HOLD, WRITE, holding, killed

    output, work = tmp_path / "results.json", tmp_path / "work"
    output.write_text("{}")
    child = holding(output, WRITE) if busy == "output" else holding(work, HOLD)
    try:
        argv = [flag.format(output=output, work=work) for flag in flags]
        result = subprocess.run([sys.executable, str(BENCHMARKS / script), *argv], capture_output=True, text=True,
                                timeout=300)
    finally:
        killed(child)
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and str(output if busy == "output" else work) in lines[0], result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert output.read_text() == "{}"
    assert (sorted(p.name for p in work.iterdir()) == [".sked-writer.lock"]) if busy == "work" else not work.exists()
