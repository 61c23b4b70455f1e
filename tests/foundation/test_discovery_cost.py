"""Method discovery, which every `ns-*` command runs, costs little where SKED is not used: no model, metric,
diffusion or plotting library, at most MODULE_BUDGET modules beyond nerfstudio's own discovery, and no process-wide
hook beyond the ones docs/development.md lists. Each side is a fresh process (benchmarks/plugin_cost.py's probe),
the stock one with the plugin's entry points filtered out of nerfstudio's lookup."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import plugin_cost  # noqa: E402  (benchmarks/: the probe the benchmark reports with)


@pytest.fixture(scope="module")
def states():
    return plugin_cost.discovery_state(plugin=False), plugin_cost.discovery_state(plugin=True)


@pytest.fixture(scope="module")
def found(states):
    stock, plugin = states
    return plugin_cost.changes(stock, plugin)


def test_the_probe_tells_the_plugin_apart(states):
    stock, plugin = states
    assert {"sked", "sked-fast", "sked-quality"} <= set(plugin["methods"])
    assert not any(name.startswith("sked") for name in stock["methods"])


def test_discovery_imports_no_model_metric_or_plotting_library(found):
    heavy = plugin_cost.heavy_imports(found["modules"]["added"])
    assert not heavy, f"method discovery imports {heavy}: import them where a model, evaluation or viewer is built"


def test_discovery_imports_few_modules_beyond_nerfstudio_s_own(found):
    added = found["modules"]["added"]
    assert len(added) <= plugin_cost.MODULE_BUDGET, (len(added), added)


def test_discovery_adds_no_hook_beyond_the_documented_ones(states, found):
    stock, plugin = states
    assert plugin_cost.undocumented(found) == {}
    assert found["meta_path"]["added"] == plugin_cost.DOCUMENTED["meta_path"]
    assert plugin["excepthook"] == "sked_ns.errors.excepthook" and stock["excepthook"] != plugin["excepthook"]


def test_the_probe_sees_what_a_heavy_import_brings(states):
    """torchmetrics (what the method's options once imported) brings its libraries and their hooks: the probe
    reports them, so the tests above fail where the plugin imports it."""
    stock, _ = states
    found = plugin_cost.changes(stock, plugin_cost.discovery_state(plugin=True, also_import=["torchmetrics"]))
    assert {"torchmetrics", "transformers"} <= set(plugin_cost.heavy_imports(found["modules"]["added"]))
    assert len(found["modules"]["added"]) > plugin_cost.MODULE_BUDGET
    assert {"logging", "warnings_filters"} <= set(plugin_cost.undocumented(found))
