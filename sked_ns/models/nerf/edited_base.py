"""A finished local edit as the base of the next one (progressive editing).

A local edit saves only its residual (local_field.py): its checkpoint holds no field to copy. The next edit's frozen
base is then the earlier edit itself, rebuilt from its run's config.yml (which reads its own base copy, and so on
down to a plain base) and seen through the interfaces a frozen base offers: a field (`forward`, `density_fn`) and,
on nerfacto, proposal densities. What it renders is the earlier edit's render, kept samples held as it held them.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Dict, Optional

import torch
import yaml
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError
from sked_ns.method.frozen_base import kept_config


def is_local_edit(state: Dict[str, Tensor]) -> bool:
    """Whether a checkpoint's model state is a local edit's (its residual, no field)."""
    return any(key.startswith("local_field.") for key in state) and not any(key.startswith("field.") for key in state)


def is_saved_residual(state: Dict[str, Tensor], prefix: str = "") -> bool:
    """Whether a model state holds a LocalResidual (its MLP head), not a LocalField."""
    return any(key.startswith(prefix + "local_field.head.") for key in state)


def earlier_edit(checkpoint: Path, state: Dict[str, Tensor], **model_kwargs) -> torch.nn.Module:
    """The local edit saved as `state`, from `checkpoint` (the next edit's copy of its step-*.ckpt, or the run's own
    file), frozen."""
    # The edit's own copy of its base holds that run's config beside its weights; before it, the run's own.
    config_path = kept_config(checkpoint) or Path(checkpoint).parent.parent / "config.yml"
    if not config_path.exists():
        raise SkedFileNotFoundError(f"{config_path}: the base is an edit saved as its changes alone, which its run's "
                                    "config.yml rebuilds; put the edit's run folder back where it was.")
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    model = config.pipeline.model.setup(**model_kwargs)
    model.load_state_dict(state)
    from nerfstudio.viewer.viewer_elements import ViewerElement

    for name, value in list(vars(model).items()):  # the viewer's controls are the new edit's, not its base's
        if isinstance(value, ViewerElement):
            setattr(model, name, SimpleNamespace(value=value.value))
    return model.eval().requires_grad_(False)


class EditedField(torch.nn.Module):
    """An earlier edit's field outputs (its base's moved by its residual, its kept samples its base's)."""

    def __init__(self, edit: torch.nn.Module) -> None:
        super().__init__()
        self.edit = edit

    def forward(self, ray_samples, compute_normals: bool = False) -> Dict:
        evaluate = (lambda field, samples: field(samples)) if not compute_normals else (  # noqa: E731
            lambda field, samples: field(samples, compute_normals=True))
        with torch.no_grad():
            return self.edit._held_outputs(ray_samples, evaluate)[0]

    def density_fn(self, positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        return self.edit.field_density(positions, times)


class EditedProposal(torch.nn.Module):
    """An earlier nerfacto edit's proposal density `index` (its base's network moved by its residual)."""

    def __init__(self, edit: torch.nn.Module, index: int) -> None:
        super().__init__()
        self.edit, self.index = edit, index

    def density_fn(self, positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        with torch.no_grad():
            return self.edit.density_fns[self.index](positions, times)
