"""One writer per run folder and per output file (sked_ns/run_lock.py).

A second `ns-train sked` into a run folder another live edit writes is refused before it writes anything; the
lock of a killed edit does not block; a checkpoint that cannot be written names another writer when there is one.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import types
from pathlib import Path

import pytest
import torch
from lock_helpers import HOLD, WRITE, holding, killed  # noqa: E402,F401  (tests/, shared with sked-batch's tests)

from sked_ns import run_lock
from sked_ns.engine.base_scene import dataparser_name, resolve_base
from sked_ns.engine.edit_run import edit_config
from sked_ns.errors import SkedUserError


def tiny_edit(scene, output: Path, prompt: str):
    config = edit_config(scene["base"], scene["data"], scene["sketches"], output, prompt=prompt, iterations=2,
                         guidance_resolution=16, silhouette_resolution=16)
    config.timestamp = "same-second"  # what two edits started in the same second share
    return config


FIRST_EDIT = """import sys, time
from pathlib import Path
from sked_ns.engine.edit_run import edit_config
base, data, sketches, output = map(Path, sys.argv[1:5])
config = edit_config(base, data, sketches, output, prompt="the first", iterations=2, guidance_resolution=16,
                     silhouette_resolution=16)
config.timestamp = "same-second"
config.save_config()  # ns-train's first write; the run goes on
print("held", flush=True)
time.sleep(900)
"""


def test_a_second_edit_into_a_run_folder_being_written_is_refused(scene, tmp_path):
    output = tmp_path / "out"
    first = holding(scene["base"], FIRST_EDIT, str(scene["data"]), str(scene["sketches"]), str(output))
    try:
        run_dir = tiny_edit(scene, output, "x").get_base_dir()
        saved = (run_dir / "config.yml").read_bytes()
        assert b"the first" in saved
        base = resolve_base(scene["base"])
        ns_train = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")
        second = subprocess.run(
            [ns_train, "sked", "--load-dir", str(scene["base"]), "--sketches", str(scene["sketches"]),
             "--prompt", "the second", "--output-dir", str(output), "--experiment-name", "edit", "--timestamp",
             "same-second", "--machine.device-type", "cpu", "--vis", "tensorboard", "--max-num-iterations", "2",
             "--pipeline.model.guidance-resolution", "16", "--pipeline.model.silhouette-resolution", "16",
             "pipeline.model.guidance:reference",
             dataparser_name(base.config.pipeline.datamanager.dataparser), "--data", str(scene["data"])],
            capture_output=True, text=True, timeout=600)
        assert second.returncode != 0
        errors = [line for line in second.stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and "Traceback" not in second.stderr, second.stderr[-3000:]
        assert f"{run_dir}: another process is writing to it (pid {first.pid} on {socket.gethostname()}" in errors[0]
        assert "--timestamp" in errors[0] and "--output-dir" in errors[0], errors[0]
        assert (run_dir / "config.yml").read_bytes() == saved, "the first edit's config.yml was replaced"
    finally:
        killed(first)
    # The killed edit's lock does not block: its folder can be written again (a resume, or a new edit).
    again = tiny_edit(scene, output, "the third")
    try:
        again.save_config()
        assert b"the third" in (run_dir / "config.yml").read_bytes()
    finally:
        run_lock.release(run_dir)


def test_resuming_into_a_run_folder_being_written_is_refused(tmp_path, monkeypatch):
    """`ns-train sked --load-dir RUN --timestamp <its own>` (what sked-batch resumes with) while RUN still runs."""
    import yaml

    import sked_ns.engine.trainer

    monkeypatch.setattr(sked_ns.engine.trainer, "check_edit_inputs", lambda config: None)  # a fake run: no data, no sketches
    from test_resume import fake_run, saved_edit

    from sked_ns.engine.edit_run import resume_config

    saved = saved_edit()
    saved.output_dir, saved.experiment_name, saved.timestamp, saved.max_num_iterations = tmp_path, "scene", "run", 60
    run = fake_run(tmp_path / "scene" / "sked" / "run", [10])
    (run / "config.yml").write_text(yaml.dump(saved))
    before = (run / "config.yml").read_bytes()
    (tmp_path / "data").mkdir()
    config = resume_config(run, tmp_path)
    config.timestamp, config.data = "run", tmp_path / "data"
    writing = holding(run)
    try:
        with pytest.raises(run_lock.WriterBusy, match=rf"{run}: another process is writing to it \(pid {writing.pid} "):
            config.save_config()
    finally:
        killed(writing)
    assert (run / "config.yml").read_bytes() == before


def test_a_lock_is_the_live_process_s_and_ends_with_it(tmp_path):
    folder = tmp_path / "run"
    child = holding(folder)
    assert run_lock.holder(folder)["pid"] == child.pid
    with pytest.raises(run_lock.WriterBusy, match=rf"{folder}: another process is writing to it \(pid {child.pid} on "
                                                  rf"{socket.gethostname()} since .*\)\. Pick another\."):
        run_lock.hold(folder, "Pick another.")
    killed(child)  # kill -9: no chance to clean up
    assert run_lock.holder(folder) is None
    run_lock.hold(folder, "")
    run_lock.hold(folder, "")  # this process again: nothing to do
    assert run_lock.holder(folder)["pid"] == os.getpid()
    run_lock.release(folder)
    assert run_lock.holder(folder) is None, "released while the process goes on"


def test_a_forked_worker_does_not_keep_its_parent_s_lock(tmp_path):
    """A data loader forks workers: the lock stays the edit's, and ends with it."""
    folder = tmp_path / "run"
    parent = holding(folder, "import os, sys, time; from sked_ns.run_lock import hold; hold(sys.argv[1], '')\n"
                             "pid = os.fork()\nif pid == 0: time.sleep(900)\n"
                             "print(pid, 'held', flush=True); time.sleep(900)")
    worker = int(parent.said[0])
    try:
        killed(parent)  # the edit dies; its worker lives on a while
        run_lock.hold(folder, "")
        run_lock.release(folder)
    finally:
        os.kill(worker, signal.SIGKILL)


def test_two_writers_of_one_file_at_once_are_one_too_many(tmp_path):
    target = tmp_path / "sked_eval.json"
    entered, go_on, refused = threading.Event(), threading.Event(), []

    def first():
        with run_lock.writing(target, ""):
            entered.set()
            go_on.wait(30)

    thread = threading.Thread(target=first)
    thread.start()
    entered.wait(30)
    try:
        with pytest.raises(run_lock.WriterBusy, match="another task of this process is writing to it"):
            with run_lock.writing(target, ""):
                refused.append(False)
    finally:
        go_on.set()
        thread.join()
    with run_lock.writing(target, ""):  # the first has finished
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "the lock file goes with its writer"


def test_a_checkpoint_another_writer_broke_says_so(tmp_path, monkeypatch):
    from test_resume import checkpointing_trainer

    run = tmp_path / "run"
    trainer = checkpointing_trainer(run)
    run_lock.hold(run, "")
    try:
        def failed_write(*args, **kwargs):
            raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")

        monkeypatch.setattr(torch, "save", failed_write)
        with pytest.raises(SkedUserError, match="check the free space"):
            trainer.save_checkpoint(5)  # this edit alone in its folder: the disk
        # Another edit on a node whose file system did not keep it out has written its record over ours.
        other = {"pid": 4242, "host": "node-b", "since": "2026-01-01T00:00:00+00:00", "command": "ns-train sked ..."}
        (run / run_lock.LOCK_NAME).write_text(json.dumps(other))
        with pytest.raises(SkedUserError) as refused:
            trainer.save_checkpoint(10)
        message = str(refused.value)
        assert f"another process is writing to {run} too (pid 4242 on node-b" in message, message
        assert "free space" not in message
    finally:
        run_lock.release(run)


# ---- every file a command writes has one writer ----------------------------------------------------


def test_sked_eval_leaves_outputs_another_sked_eval_writes(tmp_path, monkeypatch):
    from sked_ns.evaluation import eval_cli, evaluate

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("method_name: sked\n")
    other = holding(run / "sked_eval.json", WRITE)
    monkeypatch.setattr(evaluate, "evaluate", lambda *args: pytest.fail("evaluated while another sked-eval writes"))
    # The inputs pass (tests/evaluation/test_evaluate.py checks them): only the outputs' writer is under test here.
    monkeypatch.setattr(evaluate, "edit_scene", lambda run: types.SimpleNamespace(model_config=None, run_dir=run))
    monkeypatch.setattr(evaluate, "checked_sketches", lambda *args: (None, None))
    monkeypatch.setattr(evaluate, "check_sketch_masks", lambda *args: None)
    monkeypatch.setattr(sys, "argv", ["sked-eval", str(run / "config.yml"), "--device", "cpu"])
    try:
        with pytest.raises(run_lock.WriterBusy, match=rf"sked_eval\.json: another process is writing to it \(pid "
                                                      rf"{other.pid} .*pass another --output"):
            eval_cli.entrypoint()
    finally:
        killed(other)
    assert not (run / "sked_eval.json").exists()


def test_a_sketch_set_has_one_writer(tmp_path, rng):
    from conftest import random_view

    from sked_ns.sketches.sketch_set import SketchSet, load_sketch_set, save_sketch_set

    sketches = SketchSet(views=[random_view(rng, 32, 24), random_view(rng, 32, 24)])
    other = holding(tmp_path / "hat", WRITE)  # another sked-sketch saving there
    try:
        with pytest.raises(run_lock.WriterBusy, match=rf"hat: another process is writing to it \(pid {other.pid} "):
            save_sketch_set(sketches, tmp_path / "hat", overwrite=True)
        assert not (tmp_path / "hat").exists()
    finally:
        killed(other)
    save_sketch_set(sketches, tmp_path / "hat")
    assert len(load_sketch_set(tmp_path / "hat").views) == 2


@pytest.mark.slow
def test_a_demo_leaves_the_output_folder_another_demo_writes(tmp_path, monkeypatch):
    from sked_ns.demo import run as demo

    output = tmp_path / "demo"
    other = holding(output, "import sys, time; from pathlib import Path; from sked_ns.demo.run import MARKER; "
                            "from sked_ns.run_lock import hold; Path(sys.argv[1]).mkdir(); "
                            "(Path(sys.argv[1]) / MARKER).touch(); hold(sys.argv[1], ''); print('held', flush=True); "
                            "time.sleep(900)")  # what sked-demo does first
    monkeypatch.setattr(demo.demo_scene, "write_demo_dataset", lambda *args: pytest.fail("wrote beside another demo"))
    try:
        with pytest.raises(run_lock.WriterBusy, match=rf"demo: another process is writing to it \(pid {other.pid} "
                                                      r".*choose another --output"):
            demo.run(output)
    finally:
        killed(other)
