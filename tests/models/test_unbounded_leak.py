"""benchmarks/unbounded_leak.py: every floater candidate is one change, a patch that exists or model flags."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import unbounded_leak  # noqa: E402


@pytest.mark.parametrize("name", sorted(unbounded_leak.CANDIDATES))
def test_each_candidate_is_one_patch_or_flags(name):
    patch, flags = unbounded_leak.CANDIDATES[name]
    assert bool(patch) != bool(flags) or (name == "default" and not patch and not flags)  # one change each
    assert not patch or callable(getattr(unbounded_leak, patch))
    assert all(flag.startswith(("--pipeline.", "--optimizers.", "--max-num-iterations")) for flag in flags[::2])

