"""Progress lines: how far, how long, what is left."""

from __future__ import annotations

import io

import pytest

from sked_ns.progress import Progress


def test_a_line_says_how_far_how_long_and_what_is_left():
    progress = Progress("sked-eval", "novel view", 4)
    assert progress.line(1, 10.0) == "sked-eval: novel view 1/4 (10 s, about 30 s left)"
    assert progress.line(4, 200.0) == "sked-eval: novel view 4/4 (3 min)"
    assert progress.line(2, 7200.0, ": a done") == "sked-eval: novel view 2/4 (2.0 h, about 2.0 h left): a done"


def test_each_step_is_one_line_on_its_stream():
    stream = io.StringIO()
    progress = Progress("sked-batch", "edits", 2, stream=stream)
    progress.step(": first done")
    progress.step()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and lines[0].startswith("sked-batch: edits 1/2 (") and lines[0].endswith(": first done")
    assert lines[1].startswith("sked-batch: edits 2/2 (") and "left" not in lines[1]


def test_many_small_items_say_how_far_at_most_every_so_often_and_at_the_end(monkeypatch):
    import sked_ns.progress as progress_module

    clock = iter(float(t) for t in [0, 0, 1, 2, 12, 13, 14])  # start, then one reading per step
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: next(clock))
    stream = io.StringIO()
    progress = Progress("demo base", "fitting step", 6, stream=stream, every_seconds=10.0)
    for _ in range(6):
        progress.step()
    assert [line.split(" (")[0] for line in stream.getvalue().splitlines()] == [
        "demo base: fitting step 1/6", "demo base: fitting step 4/6", "demo base: fitting step 6/6"]


def test_a_heartbeat_says_what_it_is_doing_how_long_and_when_it_is_done():
    import time

    from sked_ns.progress import Heartbeat

    said = []
    with Heartbeat("nerfacc", "building its kernels", every_seconds=0.05, expected="once", say=said.append):
        time.sleep(0.3)
    assert said[0] == "building its kernels (once)..." and said[-1].startswith("done building its kernels (")
    assert len(said) >= 4 and all(line.startswith("still building its kernels (") for line in said[1:-1])
    stream = io.StringIO()
    with pytest.raises(RuntimeError), Heartbeat("x", "failing", stream=stream, every_seconds=10):
        raise RuntimeError("stop")
    assert stream.getvalue() == "x: failing...\n"  # no "done" for work that failed
