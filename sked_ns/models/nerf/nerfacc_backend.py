"""A stand-in for nerfacc's kernel backend, so every nerfacc kernel call gets working kernels.

nerfacc 0.5.2 imports `nerfacc.cuda._backend` (which JIT-builds its kernels with its own, failing
build) on the first kernel call only. Placed in sys.modules by SKED's instant-ngp model, this stand-in is
what that call finds: its `_C` comes from `sked_ns.models.nerf.nerfacc_kernels.ensure_kernels`. Kept apart
from nerfacc_kernels so that `python -m sked_ns.models.nerf.nerfacc_kernels` runs a module not yet imported.
"""

from __future__ import annotations

import sys
import types

BACKEND = "nerfacc.cuda._backend"


class LazyBackend(types.ModuleType):
    """Stands in for nerfacc.cuda._backend: its `_C` is built by `ensure_kernels` on first use."""

    def __getattr__(self, name: str):
        if name != "_C":
            raise AttributeError(name)
        from sked_ns.models.nerf.nerfacc_kernels import ensure_kernels

        status = ensure_kernels()
        if status.startswith("unavailable"):
            raise RuntimeError("nerfacc's kernels run on CUDA only: torch sees no CUDA device here.")
        if status == "nerfacc":  # nerfacc's own build works here: hand over to its backend module
            del sys.modules[BACKEND]
            from nerfacc.cuda._backend import _C

            return _C
        return sys.modules["nerfacc.csrc"]


def install_lazy_backend() -> None:
    """Route nerfacc's kernel calls (nerfacc.cuda's lazy functions) through `ensure_kernels`;
    nothing is compiled or imported until the first call."""
    if BACKEND not in sys.modules:
        sys.modules[BACKEND] = LazyBackend(BACKEND)
