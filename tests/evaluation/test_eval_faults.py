"""sked-eval when its machine or its inputs fail it: memory, threads or disk space running out is one `error:` line
saying what to do, and a checkpoint its still-training run replaces between the pick and the read is picked again."""

from __future__ import annotations

import errno
import shutil
import sys
import threading

import pytest
import torch
import yaml

from sked_ns.errors import SkedFileNotFoundError, SkedUserError


def step_file(run, step: int):
    return run / "nerfstudio_models" / f"step-{step:09d}.ckpt"


def save_step(run, step: int) -> None:
    torch.save({"step": step, "pipeline": {}}, step_file(run, step))


def trainer_saves(run, step: int) -> None:
    """What ns-train does at a save with save_only_latest_checkpoint: the new checkpoint, then the others removed."""
    save_step(run, step)
    for older in (run / "nerfstudio_models").glob("*.ckpt"):
        if older != step_file(run, step):
            older.unlink()


def fake_run(tmp_path, steps=(1, 2)):
    """A nerfacto run folder with checkpoints holding no weights: enough to pick and read them."""
    from nerfstudio.configs.method_configs import method_configs

    run = tmp_path / "run"
    (run / "nerfstudio_models").mkdir(parents=True)
    (run / "config.yml").write_text(yaml.dump(method_configs["nerfacto"]))
    for step in steps:
        save_step(run, step)
    return run


def test_a_checkpoint_replaced_between_its_pick_and_its_read_is_picked_again(tmp_path, monkeypatch):
    from sked_ns.engine.base_scene import resolve_base
    from sked_ns.evaluation.render import CHECKPOINT_TRIES, read_checkpoint

    run = fake_run(tmp_path)
    picked = resolve_base(run)
    assert picked.checkpoint == step_file(run, 2)
    trainer_saves(run, 3)
    checkpoint, state = read_checkpoint(picked, "sked-eval")
    assert checkpoint == step_file(run, 3) and state["step"] == 3

    named = resolve_base(step_file(run, 3))  # the user named this checkpoint: never swapped for another
    trainer_saves(run, 4)
    with pytest.raises(SkedFileNotFoundError, match=r"--load-dir \S+step-000000003.ckpt: removed before it could be "
                                                    r"read .*pass the run folder"):
        read_checkpoint(named, "--load-dir", pinned=True)

    reads = []

    def replaced_every_time(path, **kwargs):  # a trainer saving faster than a checkpoint is read
        reads.append(path)
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(path))

    monkeypatch.setattr(torch, "load", replaced_every_time)
    with pytest.raises(SkedFileNotFoundError, match=rf"sked-eval \S+run: its latest checkpoint was replaced "
                                                    rf"{CHECKPOINT_TRIES} times while being read"):
        read_checkpoint(resolve_base(run), "sked-eval")
    assert len(reads) == CHECKPOINT_TRIES


@pytest.mark.parametrize("error, what", [
    (MemoryError(), "memory"),
    (RuntimeError("can't start new thread"), "threads"),
    (RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory: you tried to "
                  "allocate 4294967296 bytes. Error code 12 (Cannot allocate memory)"), "memory"),
    (torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"), "GPU memory"),
    (ImportError("/x/_upfirdn_apply.so: failed to map segment from shared object"), "memory"),
    (OSError(errno.ENOSPC, "No space left on device"), "disk space"),
    (ImportError("libgomp.so.1: cannot allocate memory in static TLS block"), None),
    (RuntimeError("shape mismatch"), None),
    (OSError(errno.EACCES, "Permission denied"), None),
])
def test_what_ran_out_is_told_from_the_error(error, what):
    from sked_ns.evaluation.exhaustion import ran_out

    assert ran_out(error) == what


def sked_eval(monkeypatch, *argv):
    from sked_ns.evaluation.eval_cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["sked-eval", *map(str, argv)])
    entrypoint()


@pytest.mark.parametrize("error, message", [
    (RuntimeError("can't start new thread"), r"sked-eval \S+run: ran out of threads \(RuntimeError: can't start new "
                                             r"thread\)\. Free memory, or raise the process's limit \(ulimit -v\), or "
                                             r"lower --resolution.*ulimit -u"),
    (MemoryError("images"), r"sked-eval \S+run: ran out of memory \(MemoryError: images\)\. .*lower --resolution, "
                            r"--novel-resolution and --clip-resolution"),
    (torch.cuda.OutOfMemoryError("CUDA out of memory."), r"ran out of GPU memory .*or pass --device cpu\.$"),
])
def test_running_out_while_evaluating_is_one_line_that_says_what_to_do(tmp_path, monkeypatch, error, message):
    from sked_ns.evaluation import evaluate

    def runs_out(args):
        raise error

    monkeypatch.setattr(evaluate, "main", runs_out)
    with pytest.raises(SkedUserError, match=message) as raised:
        sked_eval(monkeypatch, tmp_path / "run", "--device", "cpu")
    assert "\n" not in str(raised.value)
    monkeypatch.setattr(evaluate, "main", lambda args: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # anything else keeps its traceback
        sked_eval(monkeypatch, tmp_path / "run", "--device", "cpu")


def test_a_full_disk_while_writing_the_results_names_the_file_and_leaves_no_partial_one(tmp_path, monkeypatch):
    from sked_ns.evaluation import evaluate

    outcome = {"metrics": {"edit_run": "run"}, "sheet": torch.zeros(8, 8, 3)}
    output, sheet = tmp_path / "m.json", tmp_path / "m.png"

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(evaluate, "publish_atomically", disk_full)
    with pytest.raises(SkedUserError, match=rf"--sheet {sheet}: writing it: ran out of disk space .*Free space there, "
                                            r"or pass --sheet on another disk; an earlier result is kept\."):
        evaluate.write_outputs(outcome, output, sheet)
    assert sorted(tmp_path.iterdir()) == [], "no partial sheet left beside"
    monkeypatch.undo()
    monkeypatch.setattr(evaluate, "write_text_atomically", disk_full)
    with pytest.raises(SkedUserError, match=rf"--output {output}: writing it: ran out of disk space"):
        evaluate.write_outputs(outcome, output, sheet)
    assert sorted(tmp_path.iterdir()) == [sheet]


def test_running_out_of_memory_while_a_run_loads_names_the_run(tmp_path, monkeypatch):
    from sked_ns.evaluation.render import load_pipeline

    run = fake_run(tmp_path)

    def no_memory(*args, **kwargs):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 1073741824 bytes.")

    monkeypatch.setattr(torch, "load", no_memory)
    with pytest.raises(SkedUserError, match=rf"--base {run}: loading the run: ran out of memory \(RuntimeError: "
                                            r"DefaultCPUAllocator.*\)\. Free memory, or raise the process's limit"):
        load_pipeline(run, flag="--base")


def test_a_run_loads_to_render_without_threads_and_from_the_checkpoint_its_trainer_saved_meanwhile(
        scene, tmp_path, monkeypatch):
    """Under a tight address-space limit no thread starts (each reserves its stack); rendering a run needs its
    datasets, not its training loaders' thread pool caching every photo. And its still-running trainer replaces the
    checkpoint picked while the pipeline is set up."""
    from sked_ns.engine import base_scene
    from sked_ns.engine.base_scene import checkpoint_step
    from sked_ns.evaluation.render import load_pipeline, render_camera

    run = tmp_path / "run"
    shutil.copytree(scene["base"], run)
    step = checkpoint_step(base_scene.resolve_base(run).checkpoint)
    pick = base_scene.resolve_base

    def then_the_trainer_saves(*args, **kwargs):
        picked = pick(*args, **kwargs)
        if picked.checkpoint == step_file(run, step):
            shutil.copy(picked.checkpoint, step_file(run, step + 1))
            picked.checkpoint.unlink()
        return picked

    def no_thread(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(base_scene, "resolve_base", then_the_trainer_saves)
    monkeypatch.setattr(threading.Thread, "start", no_thread)
    pipeline = load_pipeline(run)
    monkeypatch.undo()
    assert pipeline.sked_loaded_step == step and pipeline.sked_loaded_checkpoint == step_file(run, step + 1)
    camera = pipeline.datamanager.eval_dataset.cameras[0:1]
    camera.rescale_output_resolution(16 / int(camera.width))
    assert torch.isfinite(render_camera(pipeline.model, camera)["rgb"]).all()
