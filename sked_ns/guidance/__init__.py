"""Guidance: what pulls the sketched region towards the target.

A guidance is a component: a config (`GuidanceConfig`, chosen on the command line as the tyro
subcommand `pipeline.model.guidance:<name>`) whose `setup()` builds a `Guidance` that turns a
rendered view into named losses. Stable Diffusion is built in; any package adds its own under
the entry-point group `sked_ns.guidance` (as `sked_ns.demo` adds reference guidance), so a new
guidance touches only its own module. Guidance objects are plain Python objects, not
submodules: their weights never enter a checkpoint.
"""

from __future__ import annotations

import sys
import warnings
from importlib.metadata import entry_points
from typing import Dict, Optional, Type, Union

import tyro
from typing_extensions import Annotated

from sked_ns.errors import refuse, warn_option
from sked_ns.guidance.base import Guidance, GuidanceConfig, RenderedView
from sked_ns.guidance.stable_diffusion import StableDiffusionGuidance, StableDiffusionGuidanceConfig

ENTRY_POINT_GROUP = "sked_ns.guidance"
BUILT_IN: Dict[str, Type[GuidanceConfig]] = {"stable-diffusion": StableDiffusionGuidanceConfig}


def guidance_components() -> Dict[str, Type[GuidanceConfig]]:
    """Every guidance by its subcommand name: the built-in ones, then the registered ones."""
    components = dict(BUILT_IN)
    for entry in entry_points(group=ENTRY_POINT_GROUP):
        if _being_imported(entry.module):
            continue  # the plugin's own module imports this package first: it is not broken, just not done yet
        try:
            component = entry.load()
        except Exception as error:  # a broken plugin must not stop the others
            warnings.warn(f"guidance '{entry.name}' ({entry.value}) could not be loaded: {error}")
            continue
        if not (isinstance(component, type) and issubclass(component, GuidanceConfig)):
            warnings.warn(f"guidance '{entry.name}' ({entry.value}) is not a GuidanceConfig subclass; ignored.")
            continue
        components.setdefault(entry.name, component)
    return components


def _being_imported(module_name: str) -> bool:
    module = sys.modules.get(module_name)
    spec = getattr(module, "__spec__", None)
    return module is not None and bool(getattr(spec, "_initializing", False))


def guidance_config(name: str, **settings) -> GuidanceConfig:
    """The named guidance's config, e.g. `guidance_config("reference", target="vase")`."""
    components = guidance_components()
    if name not in components:
        raise ValueError(f"unknown guidance '{name}'; installed: {sorted(components)} "
                         f"(a package adds one under the entry-point group '{ENTRY_POINT_GROUP}').")
    return components[name](**settings)


def guidance_name(config: GuidanceConfig) -> str:
    """The subcommand name of a guidance config (its class's registered name)."""
    for name, component in guidance_components().items():
        if type(config) is component:
            return name
    return type(config).__name__


def check_guidance(config: GuidanceConfig, prompt: Optional[str]) -> None:
    """The prompt against the guidance, then the guidance's own settings; before any data is read."""
    if prompt is not None and not config.uses_prompt:
        warn_option(f"--prompt {prompt!r} is ignored: pipeline.model.guidance:{guidance_name(config)} does not use a prompt.")
    elif prompt is not None and not prompt.strip():
        # An unset shell variable must not delete content: carving is asked for by leaving the prompt out.
        refuse([f"--prompt {prompt!r} is empty. To carve the sketched region away, leave out --prompt; otherwise "
                "say what should be there."])
    config.check()


def _subcommands():
    # One tyro subcommand per component: `pipeline.model.guidance:reference --pipeline.model.guidance.target vase`.
    options = tuple(Annotated[component, tyro.conf.subcommand(name)] for name, component in guidance_components().items())
    return options[0] if len(options) == 1 else Union[options]  # type: ignore[valid-type]


GuidanceChoice = _subcommands()
"""The type of `SkedOptions.guidance`: one subcommand per installed guidance."""

__all__ = [
    "ENTRY_POINT_GROUP",
    "Guidance",
    "GuidanceChoice",
    "GuidanceConfig",
    "RenderedView",
    "check_guidance",
    "StableDiffusionGuidance",
    "StableDiffusionGuidanceConfig",
    "guidance_components",
    "guidance_config",
    "guidance_name",
]
