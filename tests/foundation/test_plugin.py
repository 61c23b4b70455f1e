"""The package registers `sked` with nerfstudio and its config carries the paper's defaults."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sked_ns.models.nerf.nerfacto import SkedNerfactoModelConfig
from sked_ns.session.methods import sked_method


def test_entry_point_registers_sked():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    assert "sked" in methods and "sketch" in descriptions["sked"].lower()
    assert isinstance(methods["sked"].pipeline.model, SkedNerfactoModelConfig)


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
    first = " ".join(result.stdout.split("options", 1)[0].split())  # the description, before the option tables
    assert all(kind in first for kind in ("nerfacto", "instant-ngp", "splatfacto")), first


def test_guidance_is_one_subcommand_per_component():
    """`pipeline.model.guidance:<name>` picks the component; its flags follow it (issue 11, item 4)."""
    import tyro

    from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig
    from sked_ns.guidance import StableDiffusionGuidanceConfig, guidance_components

    assert guidance_components() == {"stable-diffusion": StableDiffusionGuidanceConfig,
                                     "reference": ReferenceGuidanceConfig}
    config = sked_method.config

    def parse(*arguments):
        return tyro.cli(type(config), default=config, args=list(arguments)).pipeline.model.guidance

    assert isinstance(parse(), StableDiffusionGuidanceConfig) and parse().guidance_scale == 100.0
    assert parse("pipeline.model.guidance:stable-diffusion", "--pipeline.model.guidance.guidance-scale", "7.5",
                 ).guidance_scale == 7.5
    reference = parse("pipeline.model.guidance:reference", "--pipeline.model.guidance.target", "vase")
    assert isinstance(reference, ReferenceGuidanceConfig) and reference.target == "vase"


def test_a_registered_guidance_is_offered_and_a_broken_one_is_skipped(monkeypatch):
    """A new guidance is one module plus an entry point: nothing in sked_ns changes to offer it."""
    from dataclasses import dataclass

    import sked_ns.guidance as guidance_module
    from sked_ns.guidance import GuidanceConfig, guidance_config, guidance_name

    @dataclass
    class DeepFloydConfig(GuidanceConfig):
        stage: int = 1

    class Entry:
        def __init__(self, name, loaded):
            self.name, self.value, self.module, self._loaded = name, f"plugin:{name}", "plugin", loaded

        def load(self):
            if isinstance(self._loaded, Exception):
                raise self._loaded
            return self._loaded

    entries = [Entry("deepfloyd", DeepFloydConfig), Entry("broken", ImportError("no module named plugin")),
               Entry("not-a-config", dict)]
    monkeypatch.setattr(guidance_module, "entry_points", lambda group: entries)
    with pytest.warns(UserWarning) as caught:
        components = guidance_module.guidance_components()
    assert set(components) == {"stable-diffusion", "deepfloyd"}
    assert {"broken", "not-a-config"} <= {word.strip("'") for w in caught for word in str(w.message).split()}
    chosen = guidance_config("deepfloyd", stage=2)
    assert isinstance(chosen, DeepFloydConfig) and chosen.stage == 2 and guidance_name(chosen) == "deepfloyd"
    with pytest.raises(ValueError, match=r"unknown guidance 'if'.*installed.*sked_ns\.guidance"):
        guidance_config("if")


def test_a_plugin_imported_first_is_not_reported_broken():
    # Its module imports sked_ns.guidance, which looks the plugin up while the module is half-imported.
    code = ("from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig\n"
            "from sked_ns.guidance import guidance_components\nassert 'reference' in guidance_components()")
    result = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_the_method_never_imports_the_demo():
    """The import graph has no arrow from the method into sked_ns/demo (issue 11, item 5)."""
    import ast

    package = Path(__file__).resolve().parents[2] / "sked_ns"
    offenders = []
    for path in package.rglob("*.py"):
        if "demo" in path.relative_to(package).parts[:1]:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            offenders += [f"{path.relative_to(package)}: {name}" for name in names
                          if name == "sked_ns.demo" or name.startswith("sked_ns.demo.")]
    assert not offenders, offenders


def test_importing_the_plugin_changes_only_what_the_development_guide_lists():
    """Every ns-* process imports sked_ns: its hook, its finder and numpy's types in torch's safe list, nothing else
    (docs/development.md, What the plugin changes outside SKED)."""
    import json
    import subprocess
    import sys

    code = """if True:
        import json, sys, torch
        hook, meta = sys.excepthook, list(sys.meta_path)
        safe = {repr(t) for t in torch.serialization.get_safe_globals()}
        import sked_ns
        from sked_ns.moved import MovedModuleFinder
        finder = [f for f in sys.meta_path if f not in meta]
        added = sorted(f"{t.__module__}.{t.__name__}" for t in torch.serialization.get_safe_globals()
                       if repr(t) not in safe)
        import sked_ns.session.methods  # what ns-train loads for its method list (not ns-train sked here)
        from tyro._errors import _parse_error_hook
        print(json.dumps({
            "finders": [type(f).__name__ for f in finder],
            "answers_others": [n for n in ("json", "nerfstudio.models.nerfacto", "sked_ns.errors")
                               if MovedModuleFinder().find_spec(n) is not None],
            "hook": sys.excepthook.__module__ + "." + sys.excepthook.__name__,
            "chains_to": sked_ns.errors._previous_excepthook is hook,
            "tyro_hook": _parse_error_hook.get() is not None,
            "added": added,
        }))"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    changed = json.loads(result.stdout.strip().splitlines()[-1])
    assert changed["finders"] == ["MovedModuleFinder"] and changed["answers_others"] == []
    assert changed["hook"] == "sked_ns.errors.excepthook" and changed["chains_to"]
    assert not changed["tyro_hook"], "the one-line parse errors are for ns-train sked alone"
    assert changed["added"] and all(name.startswith("numpy") for name in changed["added"]), changed["added"]
