"""Presets (configs/*.yml) become ns-train methods, also from a normal (non-editable) install."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

from sked_ns.engine.presets import PRESETS, read_preset
from sked_ns.engine.trainer import resolve_edit

ROOT = Path(__file__).resolve().parents[2]


def test_every_preset_is_a_registered_method_with_its_settings():
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    for name in PRESETS:
        preset = read_preset(name)
        config = methods[name]
        assert config.max_num_iterations == preset["iterations"]
        for optimizer in config.optimizers.values():
            assert optimizer["scheduler"].max_steps == preset["iterations"], "lr decays over the whole edit"
        for key, value in preset["model"].items():
            assert getattr(config.pipeline.model, key) == value, (name, key)
    fast, default, quality = (read_preset(name) for name in ("sked-fast", "sked", "sked-quality"))
    assert fast["iterations"] < default["iterations"] < quality["iterations"]
    assert default["iterations"] == 10_000 and default["model"]["guidance_resolution"] == 128  # the paper's


def test_every_optimizer_is_adam_with_the_authors_betas_also_after_config_yml():
    import yaml
    from nerfstudio.engine.optimizers import Optimizers

    from sked_ns.engine.presets import sked_trainer_config

    for name in PRESETS:
        config = sked_trainer_config(read_preset(name), name)
        config = yaml.load(yaml.dump(config), Loader=yaml.Loader)  # as ns-train writes and reloads config.yml
        groups = {group: [torch.nn.Parameter(torch.zeros(2))] for group in config.optimizers}
        for group, optimizer in Optimizers(config.optimizers, groups).optimizers.items():
            assert isinstance(optimizer, torch.optim.Adam), (name, group)
            assert optimizer.param_groups[0]["betas"] == (0.9, 0.99), (name, group)
            assert optimizer.param_groups[0]["eps"] == 1e-15, (name, group)


def test_a_preset_with_an_unknown_key_names_the_file_and_key(tmp_path):
    (tmp_path / "broken.yml").write_text("description: x\niterations: 10\nmodel:\n  guidance_resolutoin: 64\n")
    with pytest.raises(ValueError, match=r"broken\.yml.*model\.guidance_resolutoin"):
        read_preset("broken", tmp_path)
    (tmp_path / "empty.yml").write_text("")
    with pytest.raises(ValueError, match=r"empty\.yml.*iterations"):
        read_preset("empty", tmp_path)


def test_presets_ship_in_the_wheel(tmp_path):
    """A non-editable install has configs/ as sked_ns.configs and the three entry points."""
    source = tmp_path / "src"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".venv", ".git", "demo_output", "tests", "*.egg-info", "build"))
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "dist"), str(source)],
        capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("sked_ns-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        entry_points = next(archive.read(n).decode() for n in names if n.endswith("entry_points.txt"))
    for name in PRESETS:
        assert f"sked_ns/configs/{name}.yml" in names
        assert f"{name} = sked_ns.session.methods:" in entry_points
    modules = {str(path.relative_to(ROOT)) for path in (ROOT / "sked_ns").rglob("*.py")}
    assert modules - set(names) == set(), "every module of every layer ships (pyproject's package list)"


def test_samples_per_ray_scale_changes_the_model_not_the_saved_config(scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=2)
    config.pipeline.model.samples_per_ray_scale = 0.5
    resolve_edit(config)
    base_samples = config.pipeline.model.num_nerf_samples_per_ray
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    assert model.config.num_nerf_samples_per_ray == round(base_samples * 0.5)
    assert config.pipeline.model.num_nerf_samples_per_ray == base_samples, "config.yml keeps the base's count"
    assert model.proposal_sampler.num_nerf_samples_per_ray == round(base_samples * 0.5)


def test_samples_per_ray_scale_shortens_the_ngp_step(ngp_scene, tmp_path):
    from sked_ns.engine.edit_run import edit_config

    config = edit_config(ngp_scene["base"], ngp_scene["data"], ngp_scene["sketches"], tmp_path, iterations=2)
    config.pipeline.model.samples_per_ray_scale = 2.0
    resolve_edit(config)
    model = config.pipeline.setup(device="cpu", test_mode="val").model
    assert model.config.render_step_size == pytest.approx(0.005)
    assert config.pipeline.model.render_step_size == 0.01
    config.pipeline.model.samples_per_ray_scale = 0.0
    with pytest.raises(ValueError, match="samples_per_ray_scale"):
        config.pipeline.setup(device="cpu", test_mode="val")


@pytest.mark.parametrize("ablation, dropped", [
    ("no-preserve", {"preservation_loss"}), ("no-silhouette", {"silhouette_loss"}),
    ("text-only", {"preservation_loss", "silhouette_loss"}),
])
def test_ablation_switches_drop_their_losses(scene, tmp_path, ablation, dropped):
    from sked_ns.engine.edit_run import edit_config

    config = edit_config(scene["base"], scene["data"], scene["sketches"], tmp_path, iterations=2)
    config.pipeline.model.ablation = ablation
    resolve_edit(config)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    pipeline.train()
    _, losses, _ = pipeline.get_train_loss_dict(step=0)
    for name in ("preservation_loss", "silhouette_loss"):
        if name in dropped:
            assert losses[name] == 0
        else:
            assert losses[name] > 0
    assert torch.isfinite(sum(losses.values()))


def test_learning_rate_decay_spans_the_edit_the_user_asked_for(scene, tmp_path):
    """`ns-train sked --max-num-iterations 300`: the rates still reach 0.1x at the end, not at step 10,000."""
    from sked_ns.engine.presets import edit_preset

    config = edit_preset()
    config.load_dir, config.sketches, config.max_num_iterations = scene["base"], scene["sketches"], 300
    config.data, config.machine.device_type = scene["data"], "cpu"
    resolve_edit(config)
    assert {optimizer["scheduler"].max_steps for optimizer in config.optimizers.values()} == {300}


HASH = r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b"
DB_FIGURE = r"\b\d+(\.\d+)?\s*dB\b"


def test_the_checks_for_stale_help_can_fail():
    import re

    assert re.search(HASH, "the commit 428301a added it") and re.search(DB_FIGURE, "17.8 dB at 250 seeds")
    assert not re.search(HASH, "--pipeline.model.lambda-pres 5.0 dB-free") and not re.search(DB_FIGURE, "a 4x4 patch")


@pytest.mark.parametrize("method", PRESETS)
def test_ns_train_sked_help_says_what_and_why_not_figures(method):
    """--help texts come from docstrings: benchmark figures, commit hashes and issue numbers there go stale."""
    import re

    result = subprocess.run([sys.executable, "-m", "nerfstudio.scripts.train", method, "--help"], capture_output=True,
                            text=True, timeout=300, env={**__import__("os").environ, "COLUMNS": "200"})
    assert result.returncode == 0, result.stderr[-2000:]
    text = result.stdout
    assert "--pipeline.model.lambda-pres" in text and "--pipeline.model.num-seeds" in text
    flat = " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())
    assert "Required: the scene to edit" in flat and "Leave it out to carve the region away" in flat
    # The base's architecture is copied from its config.yml: typed, it would be overwritten, so it is not offered.
    assert "--pipeline.model.hidden-dim" not in text and "--pipeline.model.num-nerf-samples-per-ray" not in text
    # SKED's own fields carry SKED's help, not nerfstudio's text for a field of the same name; what it sets is hidden.
    assert "text to NeRF models" not in flat and "we recommend SO3xR3" not in flat, "nerfstudio's help on SKED's fields"
    assert "--pipeline.model.camera-optimizer" not in text and "--pipeline.model.base-kept" not in text
    if method == "sked":  # the help's first lines say what an edit needs
        head = " ".join(text.split("╭")[0].split())
        assert all(flag in head for flag in ("--load-dir", "--sketches", "--prompt", "--data")), head
    assert re.findall(HASH, text) == []
    assert [m.group(0) for m in re.finditer(DB_FIGURE, text)] == []
    assert re.findall(r"\bissue \d+|\(#\d+\)", text) == []
