"""The methods nerfstudio registers (`ns-train sked`, `sked-fast`, `sked-quality`): the presets' edits, run by the
session trainer so that an edit without --sketches is drawn in its viewer."""

from __future__ import annotations

import sys

from sked_ns.engine.parse_errors import install_for_sked_train, sked_train_method
from sked_ns.engine.presets import PRESETS, method_from_preset
from sked_ns.errors import show_warnings_as_lines
from sked_ns.session.trainer import SessionTrainerConfig

SESSION_METHODS = {name: method_from_preset(name, SessionTrainerConfig) for name in PRESETS}
"""Each preset's registry entry; tyro rebuilds a config from its class, so the class says which trainer runs it."""
sked_method, sked_fast, sked_quality = (SESSION_METHODS[name] for name in ("sked", "sked-fast", "sked-quality"))

install_for_sked_train(SESSION_METHODS)  # `ns-train sked*` alone: its mistyped flags as one `error:` line
if sked_train_method(sys.argv, SESSION_METHODS):  # and its warnings as one `warning:` line each
    show_warnings_as_lines()
