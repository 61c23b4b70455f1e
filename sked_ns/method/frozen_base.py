"""The frozen base: the scene as trained, which L_pres and the base renders compare against.

A plain dataclass, not a module: held by the edit model as an ordinary attribute, it stays out
of the module tree, so it is never optimised and never saved; the model's `_apply` moves it.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Dict, List, Optional

import torch
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError, SkedUserError


@dataclass
class FrozenBase:
    """Copies of the base's modules, in eval mode with gradients off."""

    field: torch.nn.Module
    """The base's radiance field."""
    proposal_networks: Optional[torch.nn.ModuleList] = None
    """nerfacto: the base's proposal density networks."""
    occupancy_grid: Optional[torch.nn.Module] = None
    """instant-ngp: the base's occupancy grid."""
    sampler: Optional[torch.nn.Module] = None
    """instant-ngp: the base's grid marched with the base's density."""

    @classmethod
    def copy_of(cls, **modules: torch.nn.Module) -> "FrozenBase":
        """Frozen deep copies of the edit model's modules (taken right after the base's weights are loaded)."""
        return cls(**{name: copy.deepcopy(module).eval().requires_grad_(False) for name, module in modules.items()})

    def with_sampler(self, sampler: torch.nn.Module) -> "FrozenBase":
        return replace(self, sampler=sampler)

    def modules(self) -> List[torch.nn.Module]:
        return [getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None]


KEPT_CONFIG = "base_config.yml"
"""The base run's config.yml, as an edit's copy of its base holds it beside the weights (engine/kept_base.py)."""


def kept_config(kept: Path) -> Optional[Path]:
    """The base's config beside a kept checkpoint, or None (an edit of an older sked_ns kept the checkpoint alone)."""
    path = Path(kept).parent / KEPT_CONFIG
    return path if path.exists() else None


def base_weights(options) -> Path:
    """The checkpoint an edit's frozen base is read from: the edit's own copy (`base_kept`, engine/kept_base.py), so
    that no later write to the base run changes the edit, checked against its digest; the base run's before that
    copy is made."""
    checkpoint = Path(options.base_checkpoint)
    kept, digest = getattr(options, "base_kept", None), getattr(options, "base_digest", None)
    if kept is not None and Path(kept).exists():
        check_digest(Path(kept), digest, checkpoint)
        return Path(kept)
    if kept is not None:  # its own copy gone: the base run's file may since have been rewritten
        raise SkedFileNotFoundError(
            f"{kept}: the edit's copy of its base checkpoint is missing; the edit is its changes to exactly that "
            f"base, so loading it needs that file. Put it back {replacement(checkpoint, digest)}.")
    if checkpoint.exists():
        return checkpoint
    raise SkedFileNotFoundError(
        f"{checkpoint}: the edit's base checkpoint is missing (its base run saved a newer one and removed it, or was "
        "moved); the edit is its changes to exactly that base, so loading it needs that file. Put it back there.")


def replacement(checkpoint: Path, digest: Optional[str]) -> str:
    """Where a missing or damaged copy of an edit's base can come from again."""
    if digest is None:
        return (f"from the folder this edit was copied from, or copy {checkpoint} there if that base run was not "
                "trained on since the edit started")
    return (f"from the folder this edit was copied from, or from .sked-bases/{digest}.ckpt in the output folder "
            "where the edit was made")


_DIGESTS: Dict[tuple, str] = {}
"""File digests by (path, inode, size, mtime): an edit is loaded more than once by one command."""


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    import hashlib

    stat = Path(path).stat()
    key = (str(Path(path).absolute()), stat.st_ino, stat.st_size, stat.st_mtime_ns)
    if key not in _DIGESTS:
        digest = hashlib.sha256()
        with open(path, "rb") as file:
            for block in iter(lambda: file.read(1 << 22), b""):
                digest.update(block)
        _DIGESTS[key] = digest.hexdigest()
    return _DIGESTS[key]


def check_digest(kept: Path, digest: Optional[str], checkpoint: Path) -> None:
    """The edit's copy of its base holds the bytes it held when the edit started (an edit made before digests has none)."""
    if digest is None or file_digest(kept) == digest:
        return
    size = kept.stat().st_size
    state = "empty" if size == 0 else f"{size} bytes, changed or cut short since the edit started"
    raise SkedUserError(f"{kept}: the edit's copy of its base checkpoint is damaged ({state}); the edit is its "
                        f"changes to exactly that base. Put the file back whole {replacement(checkpoint, digest)}.")


def read_model_state(checkpoint: Path) -> Dict[str, Tensor]:
    """The model's weights from a nerfstudio checkpoint, keys without the `_model.` prefix."""
    try:
        state = torch.load(checkpoint, map_location="cpu")
        pipeline = state["pipeline"]
    except Exception as error:
        reason = str(error) or type(error).__name__
        size = checkpoint.stat().st_size if checkpoint.exists() else 0
        raise SkedUserError(f"{checkpoint}: not a readable nerfstudio checkpoint ({'an empty file' if size == 0 else reason}"
                            f"); it was cut short or damaged. Copy it again whole from where it came from (for an "
                            "edit's base/ copy: the folder the edit was copied from).") from error
    prefix = "_model."
    model_state = {}
    for key, value in pipeline.items():
        key = key[len("module.") :] if key.startswith("module.") else key
        if key.startswith(prefix):
            model_state[key[len(prefix) :]] = value
    if not model_state:
        raise SkedUserError(f"{checkpoint}: holds no model weights (no '_model.' keys).")
    check_weights(model_state, checkpoint)
    return model_state


TRAINED_MAGNITUDE = 1e10
"""No weight or buffer of a trained field or splat comes near this (positions are in the data's normalised frame,
scales and densities are logs or pre-activations); past it, products in float32 and fp16 overflow."""


def check_weights(state: Dict[str, Tensor], checkpoint: Path) -> None:
    """Every floating tensor finite and of a magnitude training can give: a diverged or damaged base is refused,
    naming the tensor, before an edit trains on it (its renders would be one flat colour, its steps all skipped)."""
    for name, value in state.items():
        if not torch.is_tensor(value) or not value.is_floating_point() or value.numel() == 0:
            continue
        largest = float(value.detach().abs().amax())  # NaN and inf propagate through amax
        if largest <= TRAINED_MAGNITUDE:
            continue
        if not math.isfinite(largest):
            kind = "NaN" if bool(torch.isnan(value).any()) else "infinite"
            what = f"holds {kind} values in {name}"
        else:
            what = f"holds {largest:.3g} in {name}, far beyond what training gives (|w| < {TRAINED_MAGNITUDE:.0e})"
        raise SkedUserError(f"{checkpoint}: the base's weights are damaged or diverged: it {what}. Edit an earlier "
                            "checkpoint of that run (--load-step) or train the base again.")


def check_photo_count(state: Dict[str, Tensor], photos: int, checkpoint: Path) -> None:
    """A base with a per-photo appearance embedding (nerfacto) fits only its own photo count."""
    embedding = state.get("field.embedding_appearance.embedding.weight")
    if embedding is not None and embedding.shape[0] != photos:
        raise SkedUserError(f"{checkpoint}: the base was trained on {embedding.shape[0]} images but --data has "
                            f"{photos}. Pass the base's own data and dataparser settings.")


def uses_tcnn(state: Dict[str, Tensor], prefix: str = "field.") -> bool:
    """tiny-cuda-nn modules store one flat `params` tensor; the torch ones named layers."""
    return any(key.startswith(prefix) and key.endswith(".params") for key in state)


def base_implementation(checkpoint: Path, prefix: str = "field.") -> str:
    """The field implementation the base's weights are laid out for ("tcnn" or "torch"), whatever its config says:
    nerfstudio's "tcnn" falls back to torch where tinycudann is missing, so the layout is the truth. A tcnn layout
    needs tinycudann here."""
    import importlib.util

    if not uses_tcnn(read_model_state(checkpoint), prefix):
        return "torch"
    if importlib.util.find_spec("tinycudann") is None:
        raise SkedUserError(f"{checkpoint}: the base was trained with tiny-cuda-nn, whose weights only tinycudann can "
                            "load. Install tinycudann here (pip install git+https://github.com/NVlabs/tiny-cuda-nn/"
                            "#subdirectory=bindings/torch), or edit on the machine that trained the base.")
    return "tcnn"
