"""The methods nerfstudio registers (`ns-train sked`, `sked-fast`, `sked-quality`): the presets' edits, run by the
session trainer so that an edit without --sketches is drawn in its viewer."""

from __future__ import annotations

import copy
from dataclasses import fields

from nerfstudio.plugins.types import MethodSpecification

from sked_ns.engine.parse_errors import install_for_sked_train
from sked_ns.engine.presets import PRESET_METHODS
from sked_ns.session.trainer import SessionTrainerConfig


def with_sessions(method: MethodSpecification) -> MethodSpecification:
    """The preset's config as a SessionTrainerConfig (tyro rebuilds a config from its class, so the class says
    which trainer runs it)."""
    settings = {item.name: copy.deepcopy(getattr(method.config, item.name)) for item in fields(method.config)
                if item.init and item.name != "_target"}
    return MethodSpecification(config=SessionTrainerConfig(**settings), description=method.description)


sked_method = with_sessions(PRESET_METHODS["sked"])
sked_fast = with_sessions(PRESET_METHODS["sked-fast"])
sked_quality = with_sessions(PRESET_METHODS["sked-quality"])

install_for_sked_train(PRESET_METHODS)  # `ns-train sked*` alone: its mistyped flags as one `error:` line
