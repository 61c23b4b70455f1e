"""nerfacc's kernels: the source patch, the cached patched tree, the build's flags and errors,
and the lazy backend every nerfacc kernel call goes through (faked CUDA: no GPU needed)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from sked_ns.models.nerf import nerfacc_backend, nerfacc_kernels

GLOBAL_LERP = re.compile(r"(?<![\w:.])lerp\s*\(")


def test_patch_replaces_what_cccl3_removed_and_adds_its_header():
    source = "x = cub::DeviceScan::ExclusiveSumByKey(a, b, cub::Equality(), s);\n"
    patched = nerfacc_kernels.patch_source(source)
    assert "cub::Equality" not in patched and "::cuda::std::equal_to<>()" in patched
    assert patched.startswith(nerfacc_kernels.HEADER)
    assert nerfacc_kernels.patch_source("int y;\n") == "int y;\n"  # untouched files stay as they are


def test_patch_renames_the_global_lerp_only():
    source = "inline __device__ float lerp(float a, float b, float t);\ny = lerp(a, b, t) + std::lerp(a, b, t) + v.lerp(w) + slerp(q);\n"
    patched = nerfacc_kernels.patch_source(source)
    assert patched == (
        "inline __device__ float nerfacc_lerp(float a, float b, float t);\n"
        "y = nerfacc_lerp(a, b, t) + std::lerp(a, b, t) + v.lerp(w) + slerp(q);\n"
    )


def test_patched_copy_of_the_installed_nerfacc(tmp_path):
    source = nerfacc_kernels.nerfacc_sources()
    assert "cub::Equality()" in (source / "scan.cu").read_text(), "nerfacc changed: revisit the patch"
    assert GLOBAL_LERP.search((source / "include" / "utils_math.cuh").read_text()), "nerfacc changed: revisit the patch"
    sources = nerfacc_kernels.patched_copy(source, tmp_path / "csrc")
    assert {p.name for p in sources} == {p.name for p in source.iterdir() if p.suffix in (".cu", ".cpp")}
    for path in (tmp_path / "csrc").rglob("*"):
        if path.is_file():
            text = path.read_text()
            assert "cub::Equality" not in text and not GLOBAL_LERP.search(text), path
    assert "nerfacc_lerp(" in (tmp_path / "csrc" / "include" / "utils_math.cuh").read_text()
    assert "cub::Equality()" in (source / "scan.cu").read_text(), "the installed nerfacc is never modified"


def _compile_with_cxx20_math(include: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    """One translation unit: libstdc++'s <math.h> (C++20 exports std::lerp globally) then nerfacc's math header."""
    unit = tmp_path / "unit.cu"
    unit.write_text(f'#include <math.h>\n#include "{include / "utils_math.cuh"}"\n')
    return subprocess.run(["nvcc", "-std=c++20", "-c", str(unit), "-o", str(tmp_path / "unit.o")],
                          capture_output=True, text=True)


@pytest.mark.skipif(shutil.which("nvcc") is None, reason="needs nvcc (compiles, runs nothing)")
def test_patched_math_header_compiles_under_cxx20(tmp_path):
    source = nerfacc_kernels.nerfacc_sources()
    original = _compile_with_cxx20_math(source / "include", tmp_path)
    assert original.returncode != 0 and "lerp" in original.stderr, "the check no longer sees nerfacc's clash"
    tree = nerfacc_kernels.patched_tree(source, tmp_path / "cache")
    patched = _compile_with_cxx20_math(tree / "include", tmp_path)
    assert patched.returncode == 0, patched.stderr


def test_patched_tree_is_written_once_per_content(tmp_path):
    source = tmp_path / "csrc"
    shutil.copytree(nerfacc_kernels.nerfacc_sources(), source)
    tree = nerfacc_kernels.patched_tree(source, tmp_path / "cache")
    built = tree / "grid.cuda.o"  # stands for anything a build left beside the sources
    built.write_text("")
    mtime = (tree / "grid.cu").stat().st_mtime_ns
    again = nerfacc_kernels.patched_tree(source, tmp_path / "cache")
    assert again == tree and built.exists(), "the tree is reused, not rewritten"
    assert (tree / "grid.cu").stat().st_mtime_ns == mtime, "sources untouched, so ninja rebuilds nothing"
    (source / "grid.cu").write_text((source / "grid.cu").read_text() + "// changed\n")
    changed = nerfacc_kernels.patched_tree(source, tmp_path / "cache")
    assert changed != tree and changed.name.startswith(nerfacc_kernels.NAME)
    assert [p.name for p in (tmp_path / "cache").iterdir() if p.name.startswith(".")] == [], "no scratch left"


def test_patched_tree_when_another_process_wins_the_race(tmp_path, monkeypatch):
    source = nerfacc_kernels.nerfacc_sources()
    target = tmp_path / f"{nerfacc_kernels.NAME}_{nerfacc_kernels.source_digest(source)}_src"
    write = nerfacc_kernels.patched_copy

    def racing_copy(source, scratch):
        write(source, target)  # the other process finishes first
        (target / "theirs").write_text("")
        return write(source, scratch)

    monkeypatch.setattr(nerfacc_kernels, "patched_copy", racing_copy)
    assert nerfacc_kernels.patched_tree(source, tmp_path) == target
    assert (target / "theirs").exists(), "their tree is kept"
    assert sorted(p.name for p in tmp_path.iterdir()) == [target.name]


def _fake_toolkit(tmp_path: Path, headers) -> Path:
    home = tmp_path / "cuda"
    (home / "bin").mkdir(parents=True)
    (home / "bin" / "nvcc").write_text("")
    (home / "include").mkdir()
    for name in headers:
        (home / "include" / name).write_text("")
    return home


def test_a_wrapper_nvcc_leads_to_its_toolkit(tmp_path, monkeypatch):
    """nvcc in /usr/local/bin as a script makes torch guess CUDA_HOME=/usr/local, which has no CUDA headers."""
    from torch.utils import cpp_extension

    toolkit = _fake_toolkit(tmp_path / "real", ["cuda_runtime.h"])
    wrapper = tmp_path / "local"
    (wrapper / "bin").mkdir(parents=True)
    (wrapper / "bin" / "nvcc").write_text(f'#!/bin/sh\necho "#$ TOP={toolkit}/bin/.." >&2\n')
    (wrapper / "bin" / "nvcc").chmod(0o755)
    monkeypatch.setattr(cpp_extension, "CUDA_HOME", str(wrapper))
    assert nerfacc_kernels.require_nvcc() == toolkit / "bin" / "nvcc"
    assert cpp_extension.CUDA_HOME == str(toolkit), "torch's include and library paths follow"
    (wrapper / "bin" / "nvcc").write_text("#!/bin/sh\n")
    monkeypatch.setattr(cpp_extension, "CUDA_HOME", str(wrapper))
    with pytest.raises(RuntimeError, match=r"CUDA_HOME=.*cuda_runtime\.h"):
        nerfacc_kernels.require_nvcc()


def _pip_header_folders():
    import nvidia

    return [folder for root in nvidia.__path__ for folder in Path(root).glob("*/include") if (folder / "cublas_v2.h").exists()]


def test_pip_headers_only_fill_what_the_toolkit_lacks_after_it(tmp_path, monkeypatch):
    from torch.utils import cpp_extension

    folders = _pip_header_folders()
    if not folders:
        pytest.skip("no pip CUDA headers installed")
    monkeypatch.setattr(cpp_extension, "CUDA_HOME", str(_fake_toolkit(tmp_path, ["cuda_runtime.h"])))
    arguments = nerfacc_kernels.build_arguments(tmp_path)
    assert arguments["extra_include_paths"] == [], "nothing ahead of the toolkit's headers (-I)"
    for flags in (arguments["extra_cflags"], arguments["extra_cuda_cflags"]):
        assert f"-isystem {folders[0]}" in flags, "searched after the toolkit's -isystem"
    import nvidia

    every_header = {p.name for root in nvidia.__path__ for p in Path(root).glob("*/include/*.h")}
    complete = _fake_toolkit(tmp_path / "complete", every_header)
    monkeypatch.setattr(cpp_extension, "CUDA_HOME", str(complete))
    assert not any("-isystem" in flag for flag in nerfacc_kernels.build_arguments(tmp_path)["extra_cuda_cflags"])


@pytest.fixture
def fake_cuda(monkeypatch):
    """CUDA 'available', no prebuilt nerfacc.csrc, a fresh status; restored afterwards."""
    import nerfacc

    monkeypatch.setattr(nerfacc_kernels, "_status", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setitem(sys.modules, "nerfacc.csrc", None)  # `from nerfacc import csrc` raises ImportError
    had_csrc = hasattr(nerfacc, "csrc")
    monkeypatch.delattr(nerfacc, "csrc", raising=False)
    yield monkeypatch
    if not had_csrc and hasattr(nerfacc, "csrc"):  # registered by the test's fake build
        delattr(nerfacc, "csrc")


def test_without_cuda_nothing_is_built(monkeypatch):
    monkeypatch.setattr(nerfacc_kernels, "_status", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert nerfacc_kernels.ensure_kernels().startswith("unavailable")


@pytest.mark.parametrize("cuda", ["12.8", "13.0"])
def test_without_nvcc_the_error_says_what_to_install(fake_cuda, cuda):
    from torch.utils import cpp_extension

    fake_cuda.setattr(cpp_extension, "CUDA_HOME", None)
    fake_cuda.setattr(torch.version, "cuda", cuda)
    with pytest.raises(RuntimeError, match=r"nvcc.*CUDA_HOME"):
        nerfacc_kernels.ensure_kernels()


def test_cxx20_torch_gets_the_patched_build_below_cuda_13_too(monkeypatch):
    assert nerfacc_kernels.torch_needs_cxx20(), "the torch this project installs (2.14) requires C++20"
    monkeypatch.setattr(torch.version, "cuda", "12.8")
    assert nerfacc_kernels.needs_patched_build()
    monkeypatch.setattr(nerfacc_kernels, "torch_needs_cxx20", lambda: False)
    assert not nerfacc_kernels.needs_patched_build(), "C++17 and CUDA 12: nerfacc's own build works"
    monkeypatch.setattr(torch.version, "cuda", "13.0")
    assert nerfacc_kernels.needs_patched_build()


def test_every_nerfacc_kernel_call_gets_the_patched_build(fake_cuda, tmp_path):
    """nerfacc's own lazy functions (stock nerfstudio models use them) load the patched kernels."""
    import nerfacc.cuda
    from torch.utils import cpp_extension

    fake_cuda.setattr(cpp_extension, "CUDA_HOME", str(_fake_toolkit(tmp_path, ["cuda_runtime.h"])))
    built = types.SimpleNamespace(traverse_grids=lambda *args: ("traversed", args))
    calls = []
    fake_cuda.setattr(nerfacc_kernels, "build_patched", lambda: calls.append(1) or built)
    fake_cuda.delitem(sys.modules, nerfacc_backend.BACKEND, raising=False)
    nerfacc_backend.install_lazy_backend()
    backend = sys.modules[nerfacc_backend.BACKEND]
    assert isinstance(backend, nerfacc_backend.LazyBackend), "installed, nothing built yet"
    assert nerfacc.cuda.traverse_grids(1, 2) == ("traversed", (1, 2))
    assert nerfacc.cuda.traverse_grids(3) == ("traversed", (3,))
    assert calls == [1], "built once per process"
    assert sys.modules["nerfacc.csrc"] is built


def test_a_nerfacc_kernel_call_without_cuda_is_explained(monkeypatch):
    import nerfacc.cuda

    monkeypatch.setattr(nerfacc_kernels, "_status", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.delitem(sys.modules, nerfacc_backend.BACKEND, raising=False)
    nerfacc_backend.install_lazy_backend()
    with pytest.raises(RuntimeError, match="CUDA only"):
        nerfacc.cuda.traverse_grids()


def test_the_plugin_leaves_stock_nerfacc_alone():
    """Every ns-* command imports the plugin (method registry); a stock `ns-train instant-ngp` must still get
    nerfacc's own backend, untouched."""
    probe = ("import sys; from nerfstudio.configs.method_configs import all_methods; "
             "assert 'sked' in all_methods and 'instant-ngp' in all_methods; import sked_ns.models.nerf.ngp; "
             "print('nerfacc.cuda._backend' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split()[-1] == "False"


def test_a_sked_ngp_model_installs_the_nerfacc_stand_in_itself(monkeypatch):
    """ns-render / ns-viewer of a SKED instant-ngp edit build its model: that is where the stand-in goes in."""
    from sked_ns.models.nerf.ngp import SkedNGPModel

    class Built(Exception):
        pass

    def stop(self):
        raise Built

    monkeypatch.delitem(sys.modules, nerfacc_backend.BACKEND, raising=False)
    model = SkedNGPModel.__new__(SkedNGPModel)
    object.__setattr__(model, "config", types.SimpleNamespace(beta=1.0))
    monkeypatch.setattr(SkedNGPModel, "_scaled_config", stop)
    with pytest.raises(Built):
        model.populate_modules()
    assert isinstance(sys.modules[nerfacc_backend.BACKEND], nerfacc_backend.LazyBackend)
