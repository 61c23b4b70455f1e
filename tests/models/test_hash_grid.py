"""The fast torch hash grid against nerfstudio's own: the same outputs bit for bit, the same gradients up to the
order of the table's scatter-add (one over all corners, not eight), no host copies."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding

from sked_ns.models.nerf.hash_grid import FastHashEncoding, use_fast_hash_grids

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from dispatch_census import DispatchCensus, module_tensors  # noqa: E402


def _pair(**kwargs):
    torch.manual_seed(0)
    reference = HashEncoding(implementation="torch", **kwargs)
    with torch.no_grad():
        reference.hash_table.uniform_(-1, 1)  # nerfstudio's 1e-3 init hides interpolation errors
    fast = copy.deepcopy(reference)
    assert use_fast_hash_grids(fast) == 1
    return reference, fast


@pytest.mark.parametrize("kwargs", [dict(), dict(num_levels=4, min_res=2, max_res=64, log2_hashmap_size=10),
                                    dict(num_levels=1, min_res=16, max_res=16, features_per_level=4)])
def test_same_outputs_and_gradients(kwargs):
    reference, fast = _pair(**kwargs)
    points = torch.rand(3000, 3)
    # grid corners, the cube's faces and edges: where ceil == floor and lerps degenerate
    points[:64] = torch.randint(0, 3, (64, 3)).float() / 2
    points = points.reshape(30, 100, 3)
    out_reference, out_fast = reference(points), fast(points)
    assert out_fast.shape == out_reference.shape
    assert torch.equal(out_fast, out_reference)
    weights = torch.randn_like(out_reference)
    (out_reference * weights).sum().backward()
    (out_fast * weights).sum().backward()
    # A table entry sums the gradients of every sample whose corner hashes to it, in another order: float32 rounding
    # of sums of up to a few thousand terms of this size.
    scale = reference.hash_table.grad.abs().max()
    torch.testing.assert_close(fast.hash_table.grad, reference.hash_table.grad, rtol=1e-5, atol=1e-6 * float(scale))
    touched = reference.hash_table.grad != 0
    assert torch.equal(fast.hash_table.grad != 0, touched)


def test_state_dict_keeps_nerfstudio_layout():
    reference, fast = _pair(num_levels=4, log2_hashmap_size=8)
    assert list(fast.state_dict()) == list(reference.state_dict()) == ["hash_table"]
    copied = copy.deepcopy(fast)  # the frozen base is a deep copy
    points = torch.rand(5, 3)
    assert isinstance(copied, FastHashEncoding)
    assert torch.equal(copied(points), reference(points))


def test_no_host_copies_or_syncs_where_nerfstudio_has_them():
    reference, fast = _pair()
    points = torch.rand(100, 3)
    counts = {}
    for name, module in (("reference", reference), ("fast", fast)):
        census = DispatchCensus(module_tensors(module) + [points])
        with census:
            module(points)
        counts[name] = census.census
    assert counts["reference"].syncs >= 9, "the census no longer sees nerfstudio's host copies"
    assert counts["fast"].syncs == 0, counts["fast"].sync_lines
    assert counts["fast"].compute_ops < counts["reference"].compute_ops / 2


def test_tcnn_and_already_fast_grids_are_left_alone():
    _, fast = _pair(num_levels=2, log2_hashmap_size=6)
    assert use_fast_hash_grids(fast, None) == 0
