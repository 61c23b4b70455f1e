"""nerfacc's CUDA kernels, built so they compile with the torch and CUDA this project installs.

nerfstudio 1.1.5 pins nerfacc 0.5.2, which JIT-compiles its kernels on first use. Two things
break that build today (found compiling nerfacc 0.5.2 with nvcc 13.0 against torch 2.14):
- torch's headers require C++20, where libstdc++'s <math.h> declares `lerp` globally and
  nerfacc's include/utils_math.cuh defines its own global `float lerp(float, float, float)`:
  grid.cu and pdf.cu stop with "conflicts with a previous declaration";
- CUDA 13's CCCL 3 removed `cub::Equality`, which scan.cu calls.
`ensure_kernels` leaves a prebuilt nerfacc alone; otherwise it compiles a patched copy of
nerfacc's own sources (lerp renamed, `cuda::std::equal_to<>` for cub::Equality) through torch's
JIT, and registers it as `nerfacc.csrc`, the prebuilt module nerfacc looks for first. The copy
is written once per content, in a folder named by its hash, so later processes reuse the
compiled extension. `install_lazy_backend` (run when a SKED instant-ngp model is built, so also under
`ns-render` / `ns-viewer` of such an edit) routes the process's nerfacc kernel calls through `ensure_kernels`
(nerfacc_backend.py); a stock `ns-train instant-ngp` never sees it. nerfacc's installed files are never modified.

Check that the kernels compile and link on a machine without a GPU:
    python -m sked_ns.models.nerf.nerfacc_kernels --compile-only
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path
from typing import Dict, List, Optional

import torch

from sked_ns.progress import Heartbeat

NAME = "nerfacc_csrc_sked"
PATCHES: Dict[str, str] = {"cub::Equality()": "::cuda::std::equal_to<>()"}
"""Source replacements for CCCL 3 (CUDA 13); equal_to<> is what cub::Equality was."""
HEADER = "#include <cuda/std/functional>\n"
RENAMES: Dict[str, str] = {"lerp": "nerfacc_lerp"}
"""Global functions of nerfacc that clash with C++20's <cmath> (which <math.h> exports globally)."""
EXTRA_CUDA_CFLAGS = ["-O3", "--expt-relaxed-constexpr"]
COMPILE_ONLY_ARCH = "9.0"
"""The GPU architecture `--compile-only` builds for when TORCH_CUDA_ARCH_LIST is unset (no GPU to ask)."""

_status: Optional[str] = None


def nerfacc_sources() -> Path:
    import nerfacc

    return Path(nerfacc.__file__).parent / "cuda" / "csrc"


def patch_source(text: str) -> str:
    """nerfacc source text with the C++20 renames and the CCCL 3 replacements (and their header)."""
    for old, new in RENAMES.items():
        # Whole identifiers only, never a qualified std::lerp / at::lerp or a member .lerp.
        text = re.sub(rf"(?<![\w:.]){old}\b", new, text)
    if not any(old in text for old in PATCHES):
        return text
    for old, new in PATCHES.items():
        text = text.replace(old, new)
    return HEADER + text


def patched_copy(source: Path, target: Path) -> List[Path]:
    """Copy nerfacc's csrc folder to `target` (new), patched; returns the sources to compile."""
    shutil.copytree(source, target)
    for path in list(target.glob("*.cu")) + list(target.glob("include/*.cuh")):
        path.write_text(patch_source(path.read_text()))
    return compiled_sources(target)


def compiled_sources(tree: Path) -> List[Path]:
    return sorted(tree.glob("*.cu")) + sorted(tree.glob("*.cpp"))


def source_digest(source: Path) -> str:
    """Hash of nerfacc's sources and of the patches: names the patched tree and its build."""
    digest = hashlib.sha256(repr((PATCHES, HEADER, RENAMES)).encode())
    for path in sorted(p for p in source.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        digest.update(str(path.relative_to(source)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


def patched_tree(source: Path, root: Path) -> Path:
    """The patched copy of `source` under `root`, written once per content and never rewritten.

    Written to a temporary folder and renamed into place (atomic), so concurrent processes
    never see a half-written tree and never delete sources another one is compiling.
    """
    target = root / f"{NAME}_{source_digest(source)}_src"
    if target.is_dir():
        return target
    root.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=root))
    try:
        patched_copy(source, scratch / "csrc")
        try:
            os.rename(scratch / "csrc", target)
        except OSError:
            if not target.is_dir():  # another process's rename won the race otherwise
                raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return target


def cuda_major() -> int:
    return int((torch.version.cuda or "0").split(".")[0])


def torch_needs_cxx20() -> bool:
    """Whether torch's headers demand C++20 (where nerfacc's global lerp clashes with <cmath>)."""
    header = Path(torch.__file__).parent / "include" / "torch" / "csrc" / "api" / "include" / "torch" / "all.h"
    return header.is_file() and "202002L" in header.read_text()


def needs_patched_build() -> bool:
    return cuda_major() >= 13 or torch_needs_cxx20()


def require_nvcc() -> Path:
    """nvcc of the toolkit torch builds with, or an error saying what to install.

    When CUDA_HOME holds an nvcc without the toolkit's headers (a wrapper script, e.g. in
    /usr/local/bin, makes torch guess CUDA_HOME=/usr/local), torch's CUDA_HOME is pointed at the
    toolkit that nvcc runs, so the host compiler and the linker find the same toolkit as nvcc.
    """
    from torch.utils import cpp_extension

    home = cpp_extension.CUDA_HOME
    nvcc = Path(home) / "bin" / "nvcc" if home else None
    if nvcc is None or not nvcc.exists():
        raise RuntimeError(
            f"nerfacc's CUDA kernels are compiled on first use and need the CUDA toolkit's compiler nvcc, "
            f"which was not found (CUDA_HOME={home or 'unset'}, no nvcc on PATH). Install the CUDA toolkit "
            f"{torch.version.cuda or ''} matching torch, then put its bin/ on PATH or set CUDA_HOME to it."
        )
    if not (Path(home) / "include" / "cuda_runtime.h").exists():
        toolkit = _toolkit_of(nvcc)
        if toolkit is None:
            raise RuntimeError(f"CUDA_HOME={home} has an nvcc but not the CUDA toolkit's include/cuda_runtime.h: "
                               "set CUDA_HOME to the CUDA toolkit's folder (e.g. /usr/local/cuda).")
        cpp_extension.CUDA_HOME = str(toolkit)  # torch reads it when it writes the build's paths
        nvcc = toolkit / "bin" / "nvcc"
    return nvcc


def _toolkit_of(nvcc: Path) -> Optional[Path]:
    """The toolkit folder an nvcc (maybe a wrapper script) really runs from: its `--dryrun` says TOP=."""
    with tempfile.TemporaryDirectory() as folder:
        unit = Path(folder) / "empty.cu"
        unit.write_text("")
        try:
            dry = subprocess.run([str(nvcc), "--dryrun", "-c", str(unit), "-o", str(unit.with_suffix(".o"))],
                                 capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            return None
    tops = re.findall(r"^#\$ TOP=(.+)$", dry.stdout + dry.stderr, flags=re.MULTILINE)
    toolkit = Path(tops[0].strip()).resolve() if tops else None
    return toolkit if toolkit and (toolkit / "include" / "cuda_runtime.h").exists() else None


def _extra_header_dirs(toolkit_include: Path) -> List[str]:
    """Include folders of pip's CUDA packages that hold headers the toolkit lacks (e.g. cuBLAS)."""
    try:
        import nvidia
    except ImportError:
        return []
    return [
        str(folder) for root in nvidia.__path__ for folder in sorted(Path(root).glob("*/include"))
        if any(not (toolkit_include / header.name).exists() for header in folder.glob("*.h"))
    ]


def build_arguments(tree: Path) -> dict:
    """torch.utils.cpp_extension arguments for the patched tree (shared by the JIT build and --compile-only)."""
    nvcc = require_nvcc()
    # -isystem after torch's own (the toolkit's) includes: pip's headers only fill what the toolkit lacks.
    after_toolkit = [f"-isystem {folder}" for folder in _extra_header_dirs(nvcc.parent.parent / "include")]
    return dict(sources=[str(s) for s in compiled_sources(tree)], extra_cflags=["-O3", *after_toolkit],
                extra_cuda_cflags=[*EXTRA_CUDA_CFLAGS, *after_toolkit], extra_ldflags=[], extra_include_paths=[])


def _register(module) -> None:
    import nerfacc

    sys.modules["nerfacc.csrc"] = module
    nerfacc.csrc = module


def build_patched() -> types.ModuleType:
    """Compile (or reuse the cached build of) the patched kernels and load them."""
    from torch.utils.cpp_extension import _get_build_directory, load

    source = nerfacc_sources()
    name = f"{NAME}_{source_digest(source)}"
    root = Path(_get_build_directory(name, verbose=False)).parent
    arguments = build_arguments(patched_tree(source, root))
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
    with Heartbeat("nerfacc", "building its CUDA kernels", expected="once, a few minutes; cached afterwards"):
        return load(name=name, **arguments)


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
    require_nvcc()
    if not needs_patched_build():
        _status = "nerfacc"  # nerfacc's own JIT build works with C++17 and CUDA < 13
        return _status
    _register(build_patched())
    _status = "patched"
    return _status


def compile_only(build_directory: Path) -> Path:
    """Compile and link the patched kernels into `build_directory` without importing them (no GPU needed)."""
    from torch.utils.cpp_extension import _write_ninja_file_and_build_library

    source = nerfacc_sources()
    build_directory.mkdir(parents=True, exist_ok=True)
    tree = patched_tree(source, build_directory)
    os.environ.setdefault("TORCH_CUDA_ARCH_LIST", COMPILE_ONLY_ARCH)
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
    name = f"{NAME}_{source_digest(source)}"
    jobs = os.environ["MAX_JOBS"]
    with Heartbeat("nerfacc_kernels", f"compiling and linking the patched kernels ({jobs} parallel jobs)",
                   expected="several minutes without a cache"):
        _write_ninja_file_and_build_library(
            name=name, **build_arguments(tree), extra_sycl_cflags=[], build_directory=str(build_directory),
            verbose=False, with_cuda=True, with_sycl=False,
        )
    return build_directory / f"{name}.so"


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--compile-only", action="store_true", required=True,
                        help="compile and link the patched kernels without a GPU (they are not loaded)")
    parser.add_argument("--build-dir", type=Path, default=None, help="where to build (default: a temporary folder)")
    args = parser.parse_args(argv)
    build = args.build_dir or Path(tempfile.mkdtemp(prefix="nerfacc_kernels_"))
    start = time.monotonic()
    library = compile_only(build)
    print(f"nerfacc kernels compiled and linked: {library} ({time.monotonic() - start:.0f} s, "
          f"arch {os.environ['TORCH_CUDA_ARCH_LIST']}, nvcc {require_nvcc()})")
    return 0 if library.exists() else 1


if __name__ == "__main__":
    sys.exit(main())
