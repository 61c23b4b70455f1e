"""Runs written by sked_ns 0.3 (the flat layout) keep loading, rendering and resuming: their config.yml files name
classes by the old module paths (tests/data/v0.3-runs, made before anything moved)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

FIXTURES = Path(__file__).resolve().parents[1] / "data" / "v0.3-runs"
WRITTEN_IN = ("/", "tmp", "sked-v0.3-fixtures")
EDITS = {"nerfacto": "edits/nerfacto/edit/sked/run", "instant-ngp": "edits/instant-ngp/edit/sked/run",
         "splatfacto": "edits/splatfacto/edit/sked/run", "resumed": "edits/resumed/edit/sked/resumed",
         "progressive": "edits/progressive/edit/sked/run"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """A copy of the fixtures with every path under the folder they were written in moved to the copy (yaml writes
    a path as the list of its parts)."""
    root = tmp_path_factory.mktemp("v0.3") / "runs"
    shutil.copytree(FIXTURES, root)
    for config in root.rglob("config.yml"):
        text = config.read_text()

        def moved(match):
            indent = match.group(1)
            return "".join(f"{indent}- {part}\n" for part in root.parts)

        text = re.sub(r"^([ \t]*)- /\n\1- tmp\n\1- sked-v0\.3-fixtures\n", moved, text, flags=re.M)
        assert "sked-v0.3-fixtures" not in text, config
        config.write_text(text)
    return root


def test_the_fixtures_name_the_old_module_paths():
    text = (FIXTURES / EDITS["nerfacto"] / "config.yml").read_text()
    assert "sked_ns.trainer.SkedTrainerConfig" in text and "sked_ns.nerfacto_model.SkedNerfactoModelConfig" in text


@pytest.mark.parametrize("kind", list(EDITS))
def test_a_v0_3_config_loads_as_todays_classes(runs, kind):
    from sked_ns.engine.base_scene import resolve_base
    from sked_ns.engine.trainer import SkedTrainerConfig
    from sked_ns.method.options import SkedOptions

    config = yaml.load((runs / EDITS[kind] / "config.yml").read_text(), Loader=yaml.Loader)
    assert type(config) is SkedTrainerConfig
    assert isinstance(config.pipeline.model, SkedOptions)
    assert type(config.pipeline.model).__module__.startswith(("sked_ns.models.nerf.", "sked_ns.models.splat."))
    assert resolve_base(runs / EDITS[kind]).family == "sked"


@pytest.mark.parametrize("kind", ["nerfacto", "instant-ngp", "splatfacto", "progressive"])
def test_a_v0_3_edit_renders(runs, kind):
    from nerfstudio.cameras.cameras import Cameras

    from sked_ns.evaluation.render import load_pipeline, render_camera

    pipeline = load_pipeline(runs / EDITS[kind])
    camera = Cameras(camera_to_worlds=torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, -2.4], [0, 1, 0, 0]])[None],
                     fx=40.0, fy=40.0, cx=16.0, cy=16.0, width=32, height=32)
    image = render_camera(pipeline.model, camera)
    assert image["rgb"].shape == (32, 32, 3) and torch.isfinite(image["rgb"]).all()
    assert image["accumulation"].max() > 0.05, "the sphere is in view"


def test_nerfstudio_opens_a_v0_3_edit_as_ns_render_does(runs):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, checkpoint, step = eval_setup(runs / EDITS["nerfacto"] / "config.yml", test_mode="inference")
    assert step == 1 and type(pipeline.model).__module__ == "sked_ns.models.nerf.nerfacto"


def test_a_v0_3_resumed_edit_is_named_for_what_nerfstudio_cannot_open(runs):
    """0.3 saved a resume's start step as load_step, which ns-render then asks for: SKED's reader says so."""
    from sked_ns.engine.base_scene import resolve_base

    with pytest.warns(UserWarning, match="load_step 1 is the step its resume started from"):
        assert resolve_base(runs / EDITS["resumed"]).checkpoint.name == "step-000000002.ckpt"


@pytest.mark.slow
def test_a_v0_3_edit_resumes(runs):
    """`ns-train sked --load-dir <v0.3 edit>` continues it (its saved settings, one more iteration)."""
    run = runs / EDITS["nerfacto"]
    result = subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.train", "sked", "--load-dir", str(run), "--max-num-iterations", "3",
         "--vis", "tensorboard", "--machine.device-type", "cpu"],
        capture_output=True, text=True, timeout=900, cwd=runs,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    # A resume writes a new run folder beside the interrupted one (ns-train's timestamp), from its checkpoint on.
    resumed = [path.parents[1] for path in (run.parent).glob("*/nerfstudio_models/step-000000002.ckpt")]
    assert len(resumed) == 1 and resumed[0] != run, sorted(str(p.relative_to(runs)) for p in runs.rglob("*.ckpt"))
    saved = yaml.load((resumed[0] / "config.yml").read_text(), Loader=yaml.Loader)
    assert saved.max_num_iterations == 3 and saved.load_dir is None
