"""nerfacc's kernels on CUDA 13: the source patch, and nothing happens without CUDA."""

from __future__ import annotations

import torch

from sked_ns import nerfacc_kernels


def test_patch_replaces_what_cccl3_removed_and_adds_its_header():
    source = "x = cub::DeviceScan::ExclusiveSumByKey(a, b, cub::Equality(), s);\n"
    patched = nerfacc_kernels.patch_source(source)
    assert "cub::Equality" not in patched and "::cuda::std::equal_to<>()" in patched
    assert patched.startswith(nerfacc_kernels.HEADER)
    assert nerfacc_kernels.patch_source("int y;\n") == "int y;\n"  # untouched files stay as they are


def test_patched_copy_of_the_installed_nerfacc(tmp_path):
    source = nerfacc_kernels.nerfacc_sources()
    assert "cub::Equality()" in (source / "scan.cu").read_text(), "nerfacc changed: revisit the patch"
    sources = nerfacc_kernels.patched_copy(source, tmp_path / "csrc")
    assert {p.name for p in sources} == {p.name for p in source.iterdir() if p.suffix in (".cu", ".cpp")}
    for path in tmp_path.rglob("*.cu*"):
        assert "cub::Equality" not in path.read_text(), path
    assert (tmp_path / "csrc" / "include" / "utils_scan.cuh").exists()
    assert "cub::Equality()" in (source / "scan.cu").read_text(), "the installed nerfacc is never modified"


def test_without_cuda_nothing_is_built(monkeypatch):
    monkeypatch.setattr(nerfacc_kernels, "_status", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert nerfacc_kernels.ensure_kernels().startswith("unavailable")
