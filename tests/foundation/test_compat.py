"""Checkpoints holding numpy scalars load under torch >= 2.6 once the plugin is imported."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

LOAD = "import torch, sys; {imports}; ckpt = torch.load(sys.argv[1], map_location='cpu'); print(ckpt['step'])"


def _nerfstudio_style_checkpoint(path):
    """What nerfstudio's trainer saves: step, pipeline, optimizers, schedulers, scaler."""
    parameter = torch.nn.Parameter(torch.randn(4))
    optimizer = torch.optim.Adam([parameter], lr=np.float64(1e-2))
    scheduler = ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=100).setup().get_scheduler(optimizer, 1e-2)
    parameter.sum().backward()
    optimizer.step()
    scheduler.step()
    torch.save(
        {
            "step": 7,
            "pipeline": {"_model.field.weight": parameter.detach()},
            "optimizers": {"fields": optimizer.state_dict()},
            "schedulers": {"fields": scheduler.state_dict()},
            "scalers": {"scale": np.float32(65536.0), "growth": np.int64(2000), "history": np.array([1.0, 2.0])},
        },
        path,
    )


def _load_in_fresh_python(path, imports):
    return subprocess.run(
        [sys.executable, "-c", LOAD.format(imports=imports), str(path)], capture_output=True, text=True, timeout=120
    )


@pytest.mark.skipif(tuple(int(x) for x in torch.__version__.split(".")[:2]) < (2, 6), reason="torch < 2.6 loads these")
def test_checkpoint_with_numpy_scalars_round_trips(tmp_path):
    path = tmp_path / "step-000000007.ckpt"
    _nerfstudio_style_checkpoint(path)
    without = _load_in_fresh_python(path, "pass")
    assert without.returncode != 0 and "Weights only load failed" in without.stderr  # the bug is real
    loaded = _load_in_fresh_python(path, "import sked_ns")
    assert loaded.returncode == 0, loaded.stderr
    assert loaded.stdout.strip() == "7"


def test_loaded_values_are_intact(tmp_path):
    import sked_ns  # noqa: F401

    path = tmp_path / "ckpt.pt"
    torch.save({"lr": np.float64(0.125), "array": np.arange(3.0), "step": np.int64(5)}, path)
    loaded = torch.load(path)
    assert loaded["lr"] == 0.125 and loaded["step"] == 5
    np.testing.assert_array_equal(loaded["array"], [0.0, 1.0, 2.0])


def test_the_old_sketches_module_s_names_still_import():
    import subprocess
    import sys

    # A fresh process: what a script written for the one-module sked_ns.sketches does first.
    code = ("from sked_ns.sketches import load_sketch_set, SketchSet\n"
            "from sked_ns.sketches import sketch_set\n"
            "assert load_sketch_set is sketch_set.load_sketch_set and SketchSet is sketch_set.SketchSet\n"
            "import sked_ns.sketches as package\n"
            "try:\n    package.no_such_name\nexcept AttributeError:\n    print('ok')\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.stdout.strip() == "ok", result.stderr[-2000:]
    from pathlib import Path

    import sked_ns.sketches as package

    here = {path.stem for path in Path(package.__file__).parent.glob("*.py")} - {"__init__"}
    assert package._SUBMODULES == here, "sketches/__init__.py's _SUBMODULES lists the package's modules"
