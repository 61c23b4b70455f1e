"""nerfacc's CUDA kernels on CUDA 13, where nerfacc 0.5.x's own build fails.

nerfstudio 1.1.5 pins nerfacc 0.5.2, which JIT-compiles its kernels on first use. Its scan
kernels call `cub::Equality`, which CUDA 13's CCCL 3 removed (found compiling nerfacc 0.5.2
with nvcc 13.0 against torch 2.11+cu130), so with today's torch wheels (CUDA 13) the build
fails and instant-ngp's occupancy-grid rendering cannot run. `ensure_kernels` leaves a working
nerfacc alone; otherwise it compiles a copy of nerfacc's own sources with the one-line
replacement CCCL 3 documents (`cuda::std::equal_to<>`), through torch's JIT like nerfacc
(cached under torch's extensions folder), and registers it as `nerfacc.csrc`, the prebuilt
module nerfacc looks for first. nerfacc's installed files are never modified.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Dict, List, Optional

import torch

NAME = "nerfacc_csrc_cccl3"
PATCHES: Dict[str, str] = {"cub::Equality()": "::cuda::std::equal_to<>()"}
"""Source replacements for CCCL 3 (CUDA 13); equal_to<> is what cub::Equality was."""
HEADER = "#include <cuda/std/functional>\n"

_status: Optional[str] = None


def nerfacc_sources() -> Path:
    import nerfacc

    return Path(nerfacc.__file__).parent / "cuda" / "csrc"


def patch_source(text: str) -> str:
    """nerfacc source text with the CCCL 3 replacements (and their header) applied."""
    if not any(old in text for old in PATCHES):
        return text
    for old, new in PATCHES.items():
        text = text.replace(old, new)
    return HEADER + text


def patched_copy(source: Path, target: Path) -> List[Path]:
    """Copy nerfacc's csrc folder to `target`, patched; returns the sources to compile."""
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(source, target)
    for path in list(target.glob("*.cu")) + list(target.glob("include/*.cuh")):
        path.write_text(patch_source(path.read_text()))
    return sorted(target.glob("*.cu")) + sorted(target.glob("*.cpp"))


def cuda_major() -> int:
    return int((torch.version.cuda or "0").split(".")[0])


def _cuda_include_paths() -> List[str]:
    """cuBLAS & co. headers of pip's CUDA packages, which a bare toolkit install may lack."""
    try:
        import nvidia

        return [str(p) for root in nvidia.__path__ for p in Path(root).glob("*/include") if (p / "cublas_v2.h").exists()]
    except ImportError:
        return []


def ensure_kernels() -> str:
    """Make nerfacc's CUDA kernels importable; returns how ('prebuilt', 'nerfacc', 'patched') or why not."""
    global _status
    if _status is not None:
        return _status
    if not torch.cuda.is_available():
        _status = "unavailable: no CUDA device"
        return _status
    try:
        from nerfacc import csrc  # noqa: F401  (a prebuilt or already registered extension)

        _status = "prebuilt"
        return _status
    except ImportError:
        pass
    if cuda_major() < 13:
        _status = "nerfacc"  # nerfacc's own JIT build works before CCCL 3
        return _status
    from torch.utils.cpp_extension import _get_build_directory, load

    build = Path(_get_build_directory(NAME, verbose=False))
    sources = patched_copy(nerfacc_sources(), build.parent / f"{NAME}_src")
    includes = [str(sources[0].parent / "include")] + _cuda_include_paths()
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
    print("nerfacc: compiling its CUDA kernels for CUDA 13 (once, about a minute; cached afterwards)", flush=True)
    module = load(name=NAME, sources=[str(s) for s in sources], extra_cflags=["-O3"],
                  extra_cuda_cflags=["-O3", "--expt-relaxed-constexpr"], extra_include_paths=includes)
    import nerfacc

    sys.modules["nerfacc.csrc"] = module
    nerfacc.csrc = module
    _status = "patched"
    return _status
