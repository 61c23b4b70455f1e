"""The package registers `sked` with nerfstudio and its config carries the paper's defaults."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from sked_ns.sked_config import sked_method
from sked_ns.sked_model import SkedModelConfig


def test_entry_point_registers_sked():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    assert "sked" in methods and "sketch" in descriptions["sked"].lower()
    assert isinstance(methods["sked"].pipeline.model, SkedModelConfig)


def test_defaults_follow_the_paper():
    model = sked_method.config.pipeline.model
    assert (model.beta, model.lambda_sil, model.lambda_sp, model.lambda_colour) == (0.025, 1.0, 5e-4, 5.0)
    assert sked_method.config.max_num_iterations == 10_000


def test_ns_train_sked_help():
    # The ns-train installed beside this interpreter, whether or not the venv is activated.
    ns_train = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
    assert ns_train, "ns-train is not installed: is nerfstudio installed in this environment?"
    result = subprocess.run([ns_train, "sked", "--help"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "sketch-guided" in result.stdout and "--pipeline.model.beta" in result.stdout
