"""What a base weighs, read from its checkpoint: the memory plan's (memory_plan.py) unit of an edit's model."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Optional


def checkpoint_weight_bytes(checkpoint: Path) -> float:
    """Bytes of a base checkpoint's model weights (floating-point tensors); for an edit saved as its changes, of the
    scene it composes with its own base (a splat edit's kept Gaussians, a local NeRF edit's base)."""
    checkpoint = Path(checkpoint)
    return _weight_bytes(checkpoint.resolve(), checkpoint.stat().st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _weight_bytes(checkpoint: Path, modified: int) -> float:
    # `ns-train sked` resolves its config more than once per start: the checkpoint is read once.
    from sked_ns.method.frozen_base import read_model_state
    from sked_ns.models.nerf.edited_base import is_local_edit
    from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS, KEPT_IN_BASE

    state = read_model_state(checkpoint)
    own = float(sum(value.numel() * value.element_size() for value in state.values()
                    if hasattr(value, "is_floating_point") and value.is_floating_point()))
    if KEPT_IN_BASE in state:  # its kept Gaussians are its base's rows, at its own Gaussians' size
        rows = max(len(state["gauss_params.means"]), 1)
        per_gaussian = sum(state[f"gauss_params.{name}"].numel() * state[f"gauss_params.{name}"].element_size()
                           for name in GAUSSIAN_PARAMS) / rows
        return own + float(state[KEPT_IN_BASE].sum()) * per_gaussian
    base = _edit_base(checkpoint) if is_local_edit(state) else None  # the earlier edit holds its whole base
    return own + (checkpoint_weight_bytes(base) if base is not None else 0.0)


def _edit_base(checkpoint: Path) -> Optional[Path]:
    """The base checkpoint of the edit saved in `checkpoint` (its config beside it, or its run's), or None."""
    import yaml

    from sked_ns.method.frozen_base import base_weights, kept_config

    config = kept_config(checkpoint) or checkpoint.parent.parent / "config.yml"
    try:
        return base_weights(yaml.load(config.read_text(), Loader=yaml.Loader).pipeline.model)
    except Exception:  # unreadable or gone: the plan counts what it can read (loading the edit says what is wrong)
        return None
