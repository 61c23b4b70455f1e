"""Results and checkpoints that a kill cannot leave half-written (sked_ns/atomic.py)."""

from __future__ import annotations

import os

import pytest

from sked_ns import atomic


def test_a_write_that_dies_before_the_rename_leaves_the_previous_file_and_no_debris(tmp_path, monkeypatch):
    results = tmp_path / "results.json"
    results.write_text('{"runs": 1}')

    def killed(*args):
        raise KeyboardInterrupt  # as a kill between writing and renaming

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        atomic.write_text_atomically(results, '{"runs": 2}')
    assert results.read_text() == '{"runs": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


def test_a_finished_write_replaces_the_file_whole(tmp_path):
    results = tmp_path / "new" / "results.json"
    atomic.write_text_atomically(results, "first")
    atomic.write_text_atomically(results, "second")
    assert results.read_text() == "second"
    assert sorted(p.name for p in results.parent.iterdir()) == ["results.json"]
