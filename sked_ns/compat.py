"""Where the libraries SKED runs on differ between versions, in one place.

Each entry says which version it serves and how it tells them apart (by feature, not version string).

Let torch >= 2.6 load nerfstudio checkpoints.

torch 2.6 switched `torch.load` to `weights_only=True`; nerfstudio checkpoints hold numpy
scalars (scheduler learning rates), so `--load-dir`, `ns-export` and `ns-viewer` fail
with an UnpicklingError. Allow-listing the numpy scalar and dtype types keeps the safe
loader and makes those checkpoints load again.
"""

from __future__ import annotations

import warnings

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


def quiet_third_party_warnings() -> None:
    """nerfstudio 1.1.5 on torch 2.14 warns on every camera call; keep the demo's output readable."""
    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", message=".*non-tuple sequence for multidimensional indexing.*")
    warnings.filterwarnings("ignore", message=".*DataLoader will create.*")
    warnings.filterwarnings("ignore", message=".*Converting a tensor with requires_grad=True to a scalar.*")
