"""The methods nerfstudio registers (`ns-train sked`, `sked-fast`, `sked-quality`): the presets' edits, run by the
session trainer so that an edit without --sketches is drawn in its viewer."""

from __future__ import annotations

import copy

from nerfstudio.plugins.types import MethodSpecification

from sked_ns.engine.presets import PRESET_METHODS
from sked_ns.session.trainer import SessionTrainer


def with_sessions(method: MethodSpecification) -> MethodSpecification:
    config = copy.deepcopy(method.config)
    config._target = SessionTrainer
    return MethodSpecification(config=config, description=method.description)


sked_method = with_sessions(PRESET_METHODS["sked"])
sked_fast = with_sessions(PRESET_METHODS["sked-fast"])
sked_quality = with_sessions(PRESET_METHODS["sked-quality"])
