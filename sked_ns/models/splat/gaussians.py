"""Gaussians as SKED reads and compares them: the base's from its checkpoint, their colours, and L_pres per Gaussian."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import torch
import yaml
from nerfstudio.models.splatfacto import num_sh_bases
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.method.frozen_base import base_weights, read_model_state

GAUSSIAN_PARAMS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
"""splatfacto's per-Gaussian parameters, in its checkpoint as `gauss_params.<name>`."""
KEPT_IN_BASE = "kept_in_base"
"""A splat edit's saved (N_base,) bool: which of its base's Gaussians it keeps (read from the base, not saved)."""
BASE_CONFIG = "base_config.yml"
"""The name an edit's copy of its base gives the base's config.yml (engine/kept_base.py's CONFIG)."""
SH_C0 = 0.28209479177387814
"""The degree-0 SH basis: an SH coefficient difference times this is a colour difference."""

class GaussianSet(torch.nn.Module):
    """Per-Gaussian tensors held as buffers: moved by `.to()`, never optimised; saved with the model unless `saved` is
    False (a set read again from elsewhere whenever the model is built)."""

    def __init__(self, tensors: Dict[str, Tensor], saved: bool = True):
        super().__init__()
        for name, value in tensors.items():
            self.register_buffer(name, value, persistent=saved)

    def save_with_model(self, saved: bool) -> None:
        for name, value in self.tensors().items():
            self.register_buffer(name, value, persistent=saved)

    def __getitem__(self, name: str) -> Tensor:
        return getattr(self, name)

    def tensors(self) -> Dict[str, Tensor]:
        return dict(self.named_buffers())

    def assign(self, tensors: Dict[str, Tensor]) -> None:
        for name, value in tensors.items():
            setattr(self, name, value)  # a registered buffer's name: replaces the buffer


def base_gaussians(state: Dict[str, Tensor], checkpoint: Path, sh_degree: int) -> Dict[str, Tensor]:
    """The base scene's Gaussians from a model state: a splatfacto run's `gauss_params`, or an earlier SKED splat
    edit's kept and editable sets together (progressive editing), its kept set read from its own base when the edit
    saved only what it changed."""
    missing = [name for name in GAUSSIAN_PARAMS if f"gauss_params.{name}" not in state]
    if missing:
        raise SkedUserError(f"{checkpoint}: holds no splatfacto Gaussians (no gauss_params.{missing[0]}). "
                            "Point --load-dir at a splatfacto run.")
    gaussians = {name: state[f"gauss_params.{name}"].float() for name in GAUSSIAN_PARAMS}
    if "kept.means" in state:  # an edit saved whole (earlier versions): its kept Gaussians are in it
        gaussians = {name: torch.cat([state[f"kept.{name}"].float(), gaussians[name]]) for name in GAUSSIAN_PARAMS}
    elif KEPT_IN_BASE in state:  # an edit saved as its changes: its kept Gaussians are its base's
        kept = kept_gaussians(edit_base_scene(checkpoint, sh_degree), state[KEPT_IN_BASE], checkpoint)
        gaussians = {name: torch.cat([kept[name], gaussians[name]]) for name in GAUSSIAN_PARAMS}
    count = len(gaussians["means"])
    rest = num_sh_bases(sh_degree) - 1
    shapes = {"means": (count, 3), "scales": (count, 3), "quats": (count, 4), "features_dc": (count, 3),
              "features_rest": (count, rest, 3), "opacities": (count, 1)}
    wrong = [f"{name} {tuple(value.shape)} (expected {shapes[name]})" for name, value in gaussians.items()
             if tuple(value.shape) != shapes[name]]
    if wrong:
        raise SkedUserError(f"{checkpoint}: the base's Gaussians do not fit its config (SH degree {sh_degree}): "
                            f"{', '.join(wrong)}.")
    return gaussians


def kept_gaussians(base: Dict[str, Tensor], kept_in_base: Tensor, checkpoint: Path) -> Dict[str, Tensor]:
    """The base's Gaussians an edit keeps, in the base's order (copies: they are the edit's own tensors)."""
    count = len(base["means"])
    if kept_in_base.dtype != torch.bool or tuple(kept_in_base.shape) != (count,):
        raise SkedUserError(f"{checkpoint}: the edit's kept set ({KEPT_IN_BASE} {tuple(kept_in_base.shape)}) does not "
                            f"fit its base's {count} Gaussians: its base copy is not the one it was made from. Put "
                            "that copy back in the edit's base folder.")
    rows = kept_in_base.to(base["means"].device)
    return {name: value[rows].clone() for name, value in base.items()}


def edit_base_scene(checkpoint: Path, sh_degree: int) -> Dict[str, Tensor]:
    """The whole scene an edit saved in `checkpoint` was made from: its base's Gaussians (composed in turn, when that
    base is itself such an edit). The edit's config lies beside its checkpoint: its run's config.yml, or, for the
    copy a later edit keeps of it, that copy's base config."""
    checkpoint = Path(checkpoint)
    configs = [checkpoint.parent / BASE_CONFIG, checkpoint.parent.parent / "config.yml"]
    found = next((path for path in configs if path.exists()), None)
    if found is None:
        raise SkedFileNotFoundError(f"{checkpoint}: an edit saved as its changes to its base, and neither "
                                    f"{configs[0]} nor {configs[1]} is there to say which base; put the edit's "
                                    "config.yml back beside it.")
    try:
        model = yaml.load(found.read_text(), Loader=yaml.Loader).pipeline.model
    except Exception as error:  # yaml of nerfstudio configs imports arbitrary modules
        raise SkedUserError(f"{found}: cannot read this nerfstudio config ({error}).") from error
    weights = base_weights(model)
    return base_gaussians(read_model_state(weights), weights, sh_degree)


def gaussian_colours(gaussians: Dict[str, Tensor], camera_centre: Tensor, sh_degree: int) -> Tensor:
    """(N, 3) colours towards one camera: splatfacto's SH (gsplat's, clamp_min(rgb + 0.5, 0)) or sigmoid colours."""
    if sh_degree == 0:
        return torch.sigmoid(gaussians["features_dc"])
    from gsplat.cuda._torch_impl import _spherical_harmonics  # the torch twin of gsplat's kernel: any device

    coefficients = torch.cat([gaussians["features_dc"][:, None], gaussians["features_rest"]], dim=1)
    rgb = _spherical_harmonics(sh_degree, gaussians["means"] - camera_centre, coefficients)
    return torch.clamp_min(rgb + 0.5, 0.0)


def splat_preservation_loss(params: Dict[str, Tensor], reference: Dict[str, Tensor], weight: Tensor,
                            lambda_colour: float, sh_degree: int) -> Tensor:
    """L_pres for Gaussians: mean_i w_i [ (o_i - o_i^base)^2 + lambda_c ||c_i - c_i^base||^2 + |mu_i - mu_i^base|^2 /
    s_i^base^2 + ||log s_i - log s_i^base||^2 + 1 - <q_i, q_i^base>^2 ] over the Gaussians with a base value
    (weight 0 elsewhere). Opacity and colour as rendered (activated), position in units of the base Gaussian's size."""
    f = lambda name: params[name].float()  # noqa: E731
    r = lambda name: reference[name].float()  # noqa: E731
    opacity = (torch.sigmoid(f("opacities")) - torch.sigmoid(r("opacities"))).pow(2).sum(dim=-1)
    if sh_degree == 0:
        colour = (torch.sigmoid(f("features_dc")) - torch.sigmoid(r("features_dc"))).pow(2).sum(dim=-1)
    else:
        colour = SH_C0**2 * ((f("features_dc") - r("features_dc")).pow(2).sum(dim=-1)
                             + (f("features_rest") - r("features_rest")).pow(2).sum(dim=(-2, -1)))
    size = torch.exp(r("scales")).mean(dim=-1).clamp_min(1e-4)  # a degenerate base Gaussian must not blow it up
    position = (f("means") - r("means")).pow(2).sum(dim=-1) / size.pow(2)
    scale = (f("scales") - r("scales")).pow(2).sum(dim=-1)
    alignment = (torch.nn.functional.normalize(f("quats"), dim=-1, eps=1e-12)
                 * torch.nn.functional.normalize(r("quats"), dim=-1, eps=1e-12)).sum(dim=-1)
    rotation = (1.0 - alignment.pow(2)).clamp_min(0.0)  # rounding must not make it negative
    per_gaussian = weight.float() * (opacity + lambda_colour * colour + position + scale + rotation)
    count = (weight > 0).sum().clamp_min(1)
    return per_gaussian.sum() / count
