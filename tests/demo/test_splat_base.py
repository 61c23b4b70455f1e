"""The CPU-fitted splat base is a run `ns-train splatfacto` would have written, and nerfstudio's own tools read it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.demo.splat_base import SplatFit, fit_demo_splat_base, last_fit
from sked_ns.method.options import without_lpips

FIT = SplatFit(steps=40, num_gaussians=300, warmup_length=20, refine_every=10, sh_degree_interval=20,
               seed_opacity=0.5)  # opaque seeds: a visible gain in 40 steps
GAUSSIAN_GROUPS = {"means", "scales", "quats", "features_dc", "features_rest", "opacities"}
# What the fit types on `ns-train splatfacto`'s command line; nothing else may differ from splatfacto's config.
TYPED = {"output_dir", "experiment_name", "timestamp", "machine.device_type", "vis", "max_num_iterations",
         "steps_per_save", "pipeline.datamanager.data", "pipeline.datamanager.dataparser.data",
         "optimizers.means.scheduler.max_steps"} | {
    f"pipeline.model.{name}" for name in ("background_color", "num_random", "random_scale", "refine_every",
                                          "warmup_length", "sh_degree_interval", "num_downscales",
                                          "resolution_schedule", "stop_split_at", "reset_alpha_every")}


@pytest.fixture(scope="module")
def splat_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("splat")
    data = folder / "data"
    demo_scene.write_demo_dataset(data, num_views=10, size=32)
    run = fit_demo_splat_base(data, folder / "outputs", FIT)
    checkpoint = torch.load(next((run / "nerfstudio_models").glob("*.ckpt")), map_location="cpu", weights_only=False)
    return {"run": run, "data": data, "checkpoint": checkpoint, "fit": dict(last_fit), "folder": folder}


def _flat(value, prefix=""):
    if isinstance(value, dict):
        return {key: leaf for name, item in value.items() for key, leaf in _flat(item, f"{prefix}{name}.").items()}
    return {prefix[:-1]: value}


def test_run_folder_is_a_splatfacto_run(splat_run):
    from nerfstudio.configs.method_configs import method_configs
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
    from nerfstudio.models.splatfacto import SplatfactoModelConfig

    run = splat_run["run"]
    assert run == splat_run["folder"] / "outputs" / "demo-base-splat" / "splatfacto" / "base"
    assert (run / "dataparser_transforms.json").is_file()
    assert [path.name for path in (run / "nerfstudio_models").iterdir()] == [f"step-{FIT.steps - 1:09d}.ckpt"]
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)  # nerfstudio's own loader
    assert config.method_name == "splatfacto"
    assert isinstance(config.pipeline.model, SplatfactoModelConfig)
    assert isinstance(config.pipeline.datamanager, FullImageDatamanagerConfig)
    assert config.pipeline.datamanager.dataparser.load_3D_points
    assert config.pipeline.datamanager.dataparser.data == splat_run["data"]
    saved = _flat(dataclasses.asdict(config))
    reference = _flat(dataclasses.asdict(method_configs["splatfacto"]))
    assert saved.keys() == reference.keys()
    assert {key for key in saved if saved[key] != reference[key]} <= TYPED


def test_checkpoint_holds_what_the_trainer_saves(splat_run):
    from nerfstudio.configs.method_configs import method_configs

    checkpoint = splat_run["checkpoint"]
    assert checkpoint.keys() == {"step", "pipeline", "optimizers", "schedulers", "scalers"}
    assert checkpoint["step"] == FIT.steps - 1
    # A splatfacto pipeline built by nerfstudio itself on the same data holds the same keys and shapes.
    config = method_configs["splatfacto"]
    config.pipeline.datamanager.data = splat_run["data"]
    with without_lpips():
        fresh = config.pipeline.setup(device="cpu", test_mode="val").state_dict()
    state = checkpoint["pipeline"]
    assert state.keys() == fresh.keys()
    assert all(state[key].shape[1:] == fresh[key].shape[1:] for key in state)
    count = len(state["_model.gauss_params.means"])
    assert state["_model.gauss_params.features_rest"].shape == (count, 15, 3)  # SH degree 3, as splatfacto stores
    assert count != FIT.num_gaussians  # the densification strategy ran
    assert checkpoint["optimizers"].keys() == GAUSSIAN_GROUPS
    assert checkpoint["schedulers"].keys() == {"means"}
    assert checkpoint["scalers"] == {}  # splatfacto trains without mixed precision: a disabled grad scaler


def test_ns_train_splatfacto_resumes_it(splat_run, tmp_path):
    """`ns-train splatfacto --load-dir RUN` restores pipeline, optimizers, schedulers and scaler from it."""
    config = yaml.load((splat_run["run"] / "config.yml").read_text(), Loader=yaml.Loader)
    config.load_dir = splat_run["run"] / "nerfstudio_models"
    config.output_dir = tmp_path  # the trainer's logs go elsewhere: the base run stays as it was
    with without_lpips():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
    assert trainer._start_step == FIT.steps
    for name in GAUSSIAN_GROUPS:
        saved = splat_run["checkpoint"]["pipeline"][f"_model.gauss_params.{name}"]
        assert torch.equal(trainer.pipeline.model.gauss_params[name].detach(), saved)
        restored = trainer.optimizers.optimizers[name].state_dict()["state"][0]["exp_avg"]
        assert torch.equal(restored, splat_run["checkpoint"]["optimizers"][name]["state"][0]["exp_avg"])


def test_ns_export_gaussian_splat_reads_it(splat_run, tmp_path):
    from nerfstudio.scripts.exporter import ExportGaussianSplat

    with without_lpips():
        ExportGaussianSplat(load_config=splat_run["run"] / "config.yml", output_dir=tmp_path).main()
    raw = (tmp_path / "splat.ply").read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    names = [line.split()[-1] for line in lines if line.startswith("property")]
    table = np.frombuffer(body, dtype=np.float32).reshape(count, len(names))
    state = splat_run["checkpoint"]["pipeline"]
    visible = state["_model.gauss_params.opacities"][:, 0] >= -5.5373  # the exporter drops opacity < 1/255
    means = state["_model.gauss_params.means"][visible].numpy()
    assert count == len(means) > 0
    np.testing.assert_array_equal(table[:, [names.index(axis) for axis in "xyz"]], means)
    assert sum(name.startswith("f_rest_") for name in names) == 45


def test_eval_setup_loads_the_fitted_weights(splat_run):
    from nerfstudio.models.splatfacto import SplatfactoModel
    from nerfstudio.utils.eval_utils import eval_setup

    with without_lpips():
        _, pipeline, checkpoint, step = eval_setup(splat_run["run"] / "config.yml", test_mode="inference")
    assert isinstance(pipeline.model, SplatfactoModel) and step == FIT.steps - 1
    for key, value in splat_run["checkpoint"]["pipeline"].items():
        assert torch.equal(pipeline.state_dict()[key], value), key


def test_the_fit_learns_the_photos(splat_run):
    fit = splat_run["fit"]
    assert fit["train_psnr"] > fit["seed_psnr"] + 1.0, fit
    assert np.isfinite(fit["eval_psnr"]), fit


def test_edit_quality_rows_name_their_base():
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import edit_quality

    summary = {"psnr_keep_gt_base": 20.0, "psnr_keep_gt": 19.5, "psnr_keep_drop": 0.5, "leak": 0.01, "ios": 0.9,
               "ios_min": 0.8, "psnr_target_changed_base": 5.0, "psnr_target_changed": 20.0}
    rows = [{"scene": "crate", "set": "held-out", "protocol": "cpu-100", "variant": "default", "seconds": 1.0,
             "summary": summary},  # recorded before splat bases: nerfacto
            {"scene": "crate", "base": "splatfacto", "set": "held-out", "protocol": "cpu-100", "variant": "default",
             "seconds": 1.0, "summary": summary}]
    lines = edit_quality.table({"runs": rows}).splitlines()
    assert lines[0].startswith("| scene | base |")
    assert lines[2].startswith("| crate | nerfacto |") and lines[3].startswith("| crate | splatfacto |")
    # Their files under --work differ, so a splat run never reuses a nerfacto edit.
    assert edit_quality._run_tag("splatfacto", "cpu-100", "default") != edit_quality._run_tag("nerfacto", "cpu-100", "default")


def test_the_48_px_protocols_run_only_when_asked_and_differ_only_in_render_size():
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import edit_quality

    assert edit_quality.DEFAULT_PROTOCOLS == ("cpu-100", "long")  # the README's 24 px rows; 48 px reported apart
    for small, large in (("cpu-100", "cpu-100-48"), ("long", "long-48")):
        assert {**edit_quality.PROTOCOLS[small], "resolution": 48} == edit_quality.PROTOCOLS[large]
    paths = {key: Path("/nowhere") / key for key in ("data", "target", "sketches")}
    arguments = edit_quality.edit_arguments(Path("/base"), paths, "hat", edit_quality.PROTOCOLS["cpu-100-48"], Path("/out"))
    for flag in ("--pipeline.model.guidance-resolution", "--pipeline.model.silhouette-resolution"):
        assert arguments[arguments.index(flag) + 1] == "48"


def test_the_preset_sample_protocols_are_their_short_protocol_at_the_presets_samples_per_ray():
    import sys

    from sked_ns.engine.presets import read_preset

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import edit_quality

    for protocol, preset in (("long-1x", "sked"), ("long-0.5x", "sked-fast"), ("cpu-100-0.5x", "sked-fast")):
        scale = read_preset(preset)["model"]["samples_per_ray_scale"]
        short = edit_quality.PROTOCOLS[protocol.rsplit("-", 1)[0]]
        assert edit_quality.PROTOCOLS[protocol] == {**short, "samples_per_ray_scale": scale}
        assert protocol not in edit_quality.DEFAULT_PROTOCOLS
        paths = {key: Path("/nowhere") / key for key in ("data", "target", "sketches")}
        arguments = edit_quality.edit_arguments(Path("/base"), paths, "hat", edit_quality.PROTOCOLS[protocol], Path("/out"))
        assert float(arguments[arguments.index("--pipeline.model.samples-per-ray-scale") + 1]) == scale


@pytest.mark.slow
def test_sked_demo_edits_a_splat_base_and_sked_eval_scores_it(tmp_path):
    """`sked-demo --base splatfacto`: the real `ns-train sked` edit of a CPU-fitted splatfacto run, before/after renders
    of the edit's frozen base, novel views; then `sked-eval` on that edit."""
    from sked_ns.demo.run import run

    quick = SplatFit(steps=20, num_gaussians=300, warmup_length=10, refine_every=10, seed_opacity=0.5)
    summary = run(tmp_path / "demo", size=32, iterations=6, base="splatfacto", splat_fit=quick)
    assert summary["base"] == "splatfacto"
    assert "/splatfacto/" in str(next((tmp_path / "demo" / "base").glob("*/splatfacto/*/config.yml")))
    for view in summary["views"]:
        assert view["ios_edit"] > view["ios_base"]  # the seeds grew into the sketches
        # and the rest is the base's: 3,000 seeds 24.2 dB in one view after six iterations (still a faint haze), 250: 25.6
        assert view["psnr_outside"] > 23
    assert summary["novel_views"]["mean"]["psnr_keep"] > 30
    from sked_ns.evaluation.evaluate import evaluate

    scores = evaluate(Path(summary["edit_run"]), resolution=32, novel_resolution=32, clip_views=2, clip_resolution=16)["metrics"]
    assert scores["mean"]["psnr_outside"] > 23 and scores["novel_views"]["mean"]["psnr_keep"] > 30  # 24.5 (above)
    assert scores["mean"]["ios"] > scores["mean"]["ios_base"]
