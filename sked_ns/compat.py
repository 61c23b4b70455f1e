"""Where the libraries SKED runs on differ between versions, in one place.

Each entry says which version it serves and how it tells them apart (by feature, not version string).

Let torch >= 2.6 load nerfstudio checkpoints.

torch 2.6 switched `torch.load` to `weights_only=True`; nerfstudio checkpoints hold numpy
scalars (scheduler learning rates), so `--load-dir`, `ns-export` and `ns-viewer` fail
with an UnpicklingError. Allow-listing the numpy scalar and dtype types keeps the safe
loader and makes those checkpoints load again.
"""

from __future__ import annotations

import inspect
import re
import warnings
from typing import Callable, Optional

import numpy as np
import torch


def numpy_safe_globals() -> list:
    """The numpy reconstruction functions and dtypes that checkpoints of numpy values need."""
    try:  # numpy >= 2 renamed numpy.core to numpy._core
        from numpy._core.multiarray import _reconstruct, scalar  # type: ignore[attr-defined]
    except ImportError:
        from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    types: list = [scalar, _reconstruct, np.dtype, np.ndarray]
    dtypes = getattr(np, "dtypes", None)  # numpy >= 1.25 pickles dtypes by their class
    if dtypes is not None:
        types += [getattr(dtypes, name) for name in dir(dtypes) if name.endswith("DType")]
    return types


def allow_numpy_in_checkpoints() -> None:
    """Register the numpy types with torch's weights-only unpickler (idempotent)."""
    add_safe_globals = getattr(torch.serialization, "add_safe_globals", None)
    if add_safe_globals is None:  # torch < 2.4 loads these without help
        return
    add_safe_globals(numpy_safe_globals())


# ---- nerfstudio: 1.1.5 (tested) and its main branch ----------------------------------------


def datamanager_is_module(datamanager) -> bool:
    """nerfstudio 1.1.5: a DataManager is a torch.nn.Module, which VanillaPipeline moves with `.to(device)`.

    nerfstudio main: a plain object that keeps its own `device` and has no `.to()`. Detected by type,
    so a pipeline never calls `.to()` on a datamanager that lacks it (SkedPipeline leaves the move to
    VanillaPipeline, which does what its own version needs).
    """
    return isinstance(datamanager, torch.nn.Module)


# 1.1.5's loop: `for step in range(self._start_step, self._start_step + num_iterations)`.
_LOOP_COUNTS_FROM_START = re.compile(r"range\(\s*self\._start_step\s*,\s*self\._start_step\s*\+")


def train_loop_adds_start_step(train: Optional[Callable] = None) -> bool:
    """nerfstudio 1.1.5: Trainer.train runs `max_num_iterations` more steps after a resume (True).

    nerfstudio main: it runs `range(self._start_step, self.config.max_num_iterations)`, so a resumed
    run already stops at its total (False). Detected from the source of `train` (default: nerfstudio's
    Trainer.train); where the source cannot be read, the tested 1.1.5 behaviour is assumed.
    """
    if train is None:
        from nerfstudio.engine.trainer import Trainer

        train = Trainer.train
    try:
        source = inspect.getsource(train)
    except (OSError, TypeError):  # no source shipped (zipped or compiled install)
        return True
    return _LOOP_COUNTS_FROM_START.search(source) is not None


def quiet_third_party_warnings() -> None:
    """nerfstudio 1.1.5 on torch 2.14 warns on every camera call; keep the demo's output readable."""
    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", message=".*non-tuple sequence for multidimensional indexing.*")
    warnings.filterwarnings("ignore", message=".*DataLoader will create.*")
    warnings.filterwarnings("ignore", message=".*Converting a tensor with requires_grad=True to a scalar.*")
