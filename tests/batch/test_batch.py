"""`sked-batch`: plans, job states from files, the local runner and a real single-node Slurm.

The end-to-end tests run the user's commands (`python -m sked_ns.batch`, what `sked-batch` is) on plans of two
tiny reference-guided CPU edits of the demo base; the Slurm one starts slurmctld and slurmd in a temporary folder
(tests/slurm_cluster.py), cancels an edit mid-run with scancel and checks that resubmitting resumes it.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from lock_helpers import WRITE, holding, killed
from PIL import Image
from slurm_cluster import SlurmCluster, why_not

from sked_ns import run_lock
from sked_ns.batch import state
from sked_ns.batch.cli import to_run
from sked_ns.batch.plan_file import load_plan
from sked_ns.batch.report import ROW_HEIGHT, write_report
from sked_ns.batch.runners import run_local, sbatch_script, slurm_options
from sked_ns.batch.task import run_job
from sked_ns.errors import SkedUserError

TINY_FLAGS = ("--machine.device-type cpu --mixed-precision False --pipeline.model.guidance-resolution 16 "
              "--pipeline.model.silhouette-resolution 16 --steps-per-eval-image 1000000 pipeline.model.guidance:reference")
"""A tiny CPU edit: reference guidance (no Stable Diffusion), 16 px renders."""


def write_plan(folder: Path, scene, edits, **top) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    plan = {"name": "tiny", **top,
            "defaults": {"base": str(scene["base"]), "data": str(scene["data"]), "sketches": str(scene["sketches"]),
                         "flags": TINY_FLAGS, "eval": False, **top.pop("defaults", {})},
            "edits": edits}
    plan.update(top)
    path = folder / "plan.yml"
    path.write_text(yaml.safe_dump(plan, sort_keys=False))
    return path


def sked_batch(*args, env=None, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sked_ns.batch", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=timeout)


def status_rows(output: str) -> dict:
    """`sked-batch status` table -> {job: (state, steps)}."""
    lines = output.splitlines()
    header = max(i for i, line in enumerate(lines) if line.split()[:2] == ["job", "state"])
    rows = {}
    for line in lines[header + 1:]:
        cells = line.split()
        if len(cells) < 3 or cells[1] not in state.STATES or not re.match(r"^(\d+/(\d+|\?)|-)$", cells[2]):
            break  # the counts line
        rows[cells[0]] = (cells[1], cells[2])
    return rows


def wait_for(predicate, timeout: float, what: str, logs=(), poll: float = 1.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if predicate():
            return
        time.sleep(poll)
    tails = "\n".join(f"--- {log}\n{Path(log).read_text()[-2000:]}" for log in logs if Path(log).exists())
    pytest.fail(f"timed out after {timeout} s waiting for {what}\n{tails}")


# ---- plans ------------------------------------------------------------------------------------


@pytest.fixture
def fake_scene(tmp_path):
    """Paths that pass the plan's checks (a run folder, data, a sketch set), for plans that run nothing."""
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "config.yml").write_text("method_name: nerfacto\n")
    (tmp_path / "data").mkdir()
    (tmp_path / "sketches").mkdir()
    (tmp_path / "sketches" / "sketches.json").write_text("{}")
    return {"base": tmp_path / "base", "data": tmp_path / "data", "sketches": tmp_path / "sketches"}


def test_a_plan_expands_to_the_commands_a_user_would_type(fake_scene, tmp_path):
    path = write_plan(tmp_path / "p", fake_scene, [
        {"name": "hat", "prompts": ["a red chef hat", "A blue cap!"], "seeds": [0, 7], "preset": "sked-fast",
         "flags": "--pipeline.model.beta 0.05 pipeline.model.guidance:stable-diffusion "
                  "--pipeline.model.guidance.guidance-scale 50"},
        {"name": "carve", "dataparser": "instant-ngp-data", "flags": ["--max-num-iterations", 20, "--vis", "viewer"]},
    ], defaults={"flags": TINY_FLAGS + " --pipeline.model.guidance.seed 3 --steps-per-save 5"})
    plan = load_plan(path)
    assert [job.name for job in plan.jobs] == ["hat-a-red-chef-hat-s0", "hat-a-red-chef-hat-s7", "hat-a-blue-cap-s0",
                                               "hat-a-blue-cap-s7", "carve"]
    assert plan.output == (tmp_path / "p" / "outputs" / "tiny").resolve()  # relative to the plan's folder
    hat = plan.job("hat-a-blue-cap-s7")
    command = hat.train_command()
    assert command[:2] == ["ns-train", "sked-fast"] and command[-3:] == ["nerfstudio-data", "--data", str(fake_scene["data"])]
    assert command[command.index("--prompt") + 1] == "A blue cap!" and command[command.index("--machine.seed") + 1] == "7"
    where = command[command.index("--output-dir"):command.index("--output-dir") + 6]
    assert where == ["--output-dir", str(plan.output), "--experiment-name", hat.name, "--timestamp", "run"]
    assert hat.run_dir == plan.output / hat.name / "sked-fast" / "run"
    # Plain flags (defaults', then the edit's) before every subcommand; the edit's guidance replaces the default one.
    assert command.index("--steps-per-eval-image") < command.index("--pipeline.model.beta"), "defaults', then the edit's"
    subcommands = [t for t in command if ":" in t and not t.startswith("-")]
    assert subcommands == ["pipeline.model.guidance:stable-diffusion"], command
    assert command.index("--pipeline.model.beta") < command.index(subcommands[0]) < command.index(
        "--pipeline.model.guidance.guidance-scale") < command.index("nerfstudio-data")
    carve = plan.job("carve").train_command()
    assert "--prompt" not in carve and "--machine.seed" not in carve
    # A plain flag written after a subcommand in the plan goes before it; the subcommand's own flags stay with it.
    assert carve.index("--steps-per-save") < carve.index("--max-num-iterations") < carve.index(
        "pipeline.model.guidance:reference") < carve.index("--pipeline.model.guidance.seed") < carve.index("instant-ngp-data")
    assert "--pipeline.model.guidance.seed" not in command, "the edit's guidance replaced the default one, with its flags"
    assert carve[carve.index("--vis") + 1] == "viewer" and carve[carve.index("--viewer.quit-on-train-completion") + 1] == "True"
    assert plan.job("carve").resume_command() == [
        "ns-train", "sked", "--load-dir", str(plan.job("carve").run_dir), "--output-dir", str(plan.output),
        "--experiment-name", "carve", "--timestamp", "run"]


@pytest.mark.parametrize("edit, message", [
    ({"name": "a", "colour": "red"}, r"edits\[0\] \(a\): unknown field\(s\) colour"),
    ({"name": "a", "base": None}, r"edits\[0\] \(a\): no base"),
    ({"name": "a", "base": "missing"}, r"edits\[0\] \(a\)\.base: .*missing: no config\.yml"),
    ({"name": "a", "sketches": "."}, r"edits\[0\] \(a\)\.sketches: .*no sketches\.json"),
    ({"name": "a", "prompts": ["a hat", ""]}, r"edits\[0\] \(a\)\.prompts: '' is not a non-empty text"),
    ({"name": "a", "seeds": [1, -2]}, r"edits\[0\] \(a\)\.seeds: -2 is not a whole number >= 0"),
    ({"name": "a", "seed": 1, "seeds": [2]}, r"give seeds \(a list\) or seed \(one\), not both"),
    ({"name": "a", "preset": "nerfacto"}, r"edits\[0\] \(a\)\.preset: 'nerfacto': one of sked, sked-fast"),
    ({"name": "a", "flags": "--prompt 'a hat'"}, r"edits\[0\] \(a\)\.flags: --prompt is not for the flags: the plan sets "
                                                 r"it from prompts"),
    ({"name": "a", "flags": "--output-dir=/x"}, r"--output-dir is not for the flags"),
    ({"name": "a b"}, r"edits\[0\] \(a b\)\.name: 'a b': letters, digits"),
    ({"name": "a", "seeds": [1, 2, 1]}, r"edits\[0\] \(a\)\.seeds: 1 is listed twice"),
    ({"name": "a", "prompts": ["a hat", "A hat!"]}, r"edits\[0\] \(a\)\.prompts: 'a hat' and 'A hat!' make the same job "
                                                   r"name"),
    # sked-eval's flags are read as sked-eval reads them when the plan is, not after hours of editing.
    ({"name": "a", "eval": "--resolution 0"}, r"edits\[0\] \(a\)\.eval: '--resolution 0': .*--resolution: 0: must be "
                                              r"at least 1"),
    ({"name": "a", "eval": "--reslution 64"}, r"edits\[0\] \(a\)\.eval: .*unrecognized arguments: --reslution"),
    ({"name": "a", "eval": "--cameras nowhere.json"}, r"edits\[0\] \(a\)\.eval: .*--cameras nowhere.json: no such camera"),
    ({"name": "a", "eval": "--output m.json"}, r"edits\[0\] \(a\)\.eval: .*--output is not for a plan's eval flags"),
])
def test_plan_mistakes_name_the_file_entry_and_field(fake_scene, tmp_path, edit, message):
    path = write_plan(tmp_path, fake_scene, [edit])
    with pytest.raises(SkedUserError, match=message) as refused:
        load_plan(path)
    assert str(path) in str(refused.value)


@pytest.mark.parametrize("slurm, message", [
    ({"time": 14400}, r"slurm\.time: 14400: write the time as a quoted string"),  # YAML's reading of 4:00:00
    ({"time": "4 hours"}, r"slurm\.time: '4 hours': Slurm's time format"),
    ({"max_parallel": 0}, r"slurm\.max_parallel: 0: a whole number >= 1"),
    ({"mem": "lots"}, r"slurm\.mem: 'lots': memory per edit"),
])
def test_slurm_settings_are_checked_with_the_plan(fake_scene, tmp_path, slurm, message):
    with pytest.raises(SkedUserError, match=message):
        load_plan(write_plan(tmp_path, fake_scene, [{"name": "a"}], slurm=slurm))


def test_a_sweep_is_counted_from_its_lists_and_a_huge_one_warned(fake_scene, tmp_path, capsys):
    """10^5 jobs: known and dry-run without 10^5 job objects (memory, not time, is what is checked)."""
    import tracemalloc

    from sked_ns.batch.cli import main
    from sked_ns.errors import SkedWarning

    path = write_plan(tmp_path, fake_scene, [{"name": "e", "prompts": [f"prompt {i}" for i in range(1000)],
                                              "seeds": list(range(100))}])
    tracemalloc.start()
    try:
        plan = load_plan(path)
        assert len(plan.jobs) == 100_000 and plan.jobs[-1].name == "e-prompt-999-s99"
        assert plan.job("e-prompt-500-s7").prompt == "prompt 500"
        with pytest.warns(SkedWarning, match=r"100000 jobs \(edits\[0\] \(e\): 1000 prompt\(s\) x 100 seed\(s\)\): "
                                             r"100000 ns-train edits of 1000000000 iterations"), \
                pytest.raises(SystemExit) as ended:
            main([str(path), "--local", "--dry-run"])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert ended.value.code == 0
    assert peak < 20e6, f"{peak / 1e6:.0f} MB: the jobs were made, not counted"
    out = capsys.readouterr().out.splitlines()
    assert len(out) < 120 and out[-1].startswith("... and 99950 more edits like these"), out[-3:]
    assert "99950 more, 100000 in all (100000 pending)" in "\n".join(out)
    assert not plan.output.exists(), "a dry run writes nothing"


def test_submitting_checks_the_output_and_the_command_line_first(fake_scene, tmp_path, monkeypatch):
    from sked_ns.batch.cli import main
    from sked_ns.errors import SkedWarning

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    path = write_plan(tmp_path / "p", fake_scene, [{"name": "e"}], output=str(blocker / "out"))
    for command in ([str(path), "--local"], [str(path), "--slurm", "--dry-run"], ["report", str(path)],
                    ["task", str(path), "--job", "e"]):
        with pytest.raises(SkedUserError, match=rf"plan\.yml: output: {blocker}/out: {blocker} is a file"):
            main(command)
    path = write_plan(tmp_path / "q", fake_scene, [{"name": "e"}])
    output = load_plan(path).output
    for flags, message in ((["--slurm", "--time", "4h"], r"--time 4h: Slurm's time format"),
                           (["--slurm", "--max-parallel", "0"], r"--max-parallel 0: a whole number >= 1"),
                           (["--local", "--devices", "0,,1"], r"--devices 0,,1: GPUs separated by commas"),
                           (["--local", "--devices", "0"], r"--devices 0: no GPU is visible here")):
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
        with pytest.raises(SkedUserError, match=message):
            main([str(path), *flags])
    with pytest.warns(SkedWarning, match=r"--devices 0: for --local only"), pytest.raises(SystemExit):
        main([str(path), "--slurm", "--dry-run", "--devices", "0"])
    with pytest.warns(SkedWarning, match=r"--partition, --time: for --slurm only"), pytest.raises(SystemExit):
        main([str(path), "--local", "--dry-run", "--partition", "gpu", "--time", "1:00:00"])
    assert not output.exists(), "refused or dry runs: nothing written (the Slurm dry run made <output>/slurm)"


def test_an_unwritable_output_is_one_error_line(fake_scene, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    path = write_plan(tmp_path / "p", fake_scene, [{"name": "e"}], output=str(blocker / "out"))
    result = sked_batch(path, "--local", timeout=300)
    assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert result.stderr.strip().splitlines()[-1].startswith(f"error: {path}: output: {blocker}/out: "), result.stderr


def test_an_unreadable_plan_is_named(tmp_path):
    plan = tmp_path / "plan.yml"
    plan.write_bytes(b"\xff\xfe binary \x00")
    with pytest.raises(SkedUserError, match=r"plan\.yml: cannot read the plan"):
        load_plan(plan)


def test_two_edits_making_the_same_job_are_refused(fake_scene, tmp_path):
    path = write_plan(tmp_path, fake_scene, [{"name": "a", "prompt": "a hat"}, {"name": "a", "prompt": "A hat."}])
    with pytest.raises(SkedUserError, match=r"edits\[1\] \(a\): job 'a-a-hat' is also made by edits\[0\] \(a\)"):
        load_plan(path)
    (tmp_path / "empty.toml").write_text('name = "x"\n')
    with pytest.raises(SkedUserError, match=r"empty\.toml: edits: a list of edits"):
        load_plan(tmp_path / "empty.toml")


# ---- states, runners, report (no edit runs) --------------------------------------------------


def fake_checkpoints(job, steps, total):
    models = job.run_dir / "nerfstudio_models"
    models.mkdir(parents=True, exist_ok=True)
    (job.run_dir / "config.yml").write_text(f"method_name: sked\nmax_num_iterations: {total}\n")
    for step in steps:
        (models / f"step-{step:09d}.ckpt").write_bytes(b"x")


def test_states_come_from_the_job_folder(fake_scene, tmp_path):
    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1, 2, 3, 4]}]))
    pending, interrupted, failed, done, running = plan.jobs
    fake_checkpoints(interrupted, [4, 9], total=20)
    state.write_marker(interrupted, "job", state.job_record(interrupted))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    state.write_marker(interrupted, "running", {"owner": {"pid": dead.pid, "host": os.uname().nodename}})
    state.write_marker(failed, "failed", {"stage": "edit", "reason": "ns-train exited with 2", "where": "pid 1"})
    fake_checkpoints(done, [19], total=20)
    state.write_marker(done, "done", {})
    state.write_marker(running, "running", {"owner": state.this_owner()})
    statuses = state.plan_status(plan.jobs)
    assert [(s.state, s.step, s.total) for s in statuses] == [
        ("pending", 0, None), ("interrupted", 10, 20), ("failed", 0, None), ("done", 20, 20), ("running", 0, None)]
    table = state.status_table(statuses)
    assert "resumes from step 10" in table and "edit: ns-train exited with 2" in table
    assert str(failed.log) in table and "1 pending, 1 interrupted" not in table  # counts in STATES order
    assert table.splitlines()[-1] == "1 done, 1 running, 1 failed, 1 interrupted, 1 pending (of 5)"
    # A later plan asking another edit of a job that has a checkpoint is "changed" (its folder holds the earlier edit).
    changed_plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1, 2, 3, 4],
                                                                "flags": "--pipeline.model.beta 0.1"}]))
    assert state.job_status(changed_plan.jobs[1], {}).state == "changed"
    with pytest.raises(SkedUserError, match=r"e-s1: its train command changed since it ran .*give the edit another name, "
                                            r"or remove \S+/e-s1 to run it anew"):
        to_run(changed_plan, None)
    assert [s.job.name for s in to_run(plan, None)] == ["e-s0", "e-s1", "e-s2"], "pending, interrupted, failed"
    assert state.job_status(changed_plan.jobs[2], {}).state == "failed", "nothing saved yet: runs with the new command"


def test_a_failed_stage_is_recorded_with_its_log_and_rerun(fake_scene, tmp_path, monkeypatch):
    import sked_ns.batch.task as task

    job = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e"}])).jobs[0]
    monkeypatch.setattr(task, "executable", lambda name: "false")  # ns-train fails at once
    assert run_job(job) == 1
    failed = state.read_marker(job, "failed")
    assert (failed["stage"], failed["exit_code"], failed["log"]) == ("edit", 1, str(job.log))
    assert "$ ns-train sked --load-dir" in job.log.read_text() and state.read_marker(job, "running") is None
    calls = []

    def fake_ns_train(job_, command, env):  # the rerun: a new edit that reaches its total
        calls.append(command)
        fake_checkpoints(job_, [5], total=6)
        return 0

    monkeypatch.setattr(task, "run_stage", fake_ns_train)
    assert run_job(job) == 0 and calls == [job.train_command()]
    assert state.job_status(job, {}).state == "done" and state.read_marker(job, "done")["steps"] == 6
    assert state.read_marker(job, "failed") is None and state.read_marker(job, "running") is None


def test_interrupted_jobs_resume_and_gpus_run_one_edit_each(fake_scene, tmp_path, monkeypatch):
    import sked_ns.batch.runners as runners
    import sked_ns.batch.task as task

    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1, 2]}]))
    fake_checkpoints(plan.jobs[0], [3], total=8)
    seen = {}

    def fake_stage(job, command, env):
        seen[job.name] = (command, env.get("CUDA_VISIBLE_DEVICES"))
        fake_checkpoints(job, [7], total=8)
        return 0

    monkeypatch.setattr(task, "run_stage", fake_stage)
    monkeypatch.setattr(runners, "run_job", task.run_job)
    assert run_local(plan.jobs, devices=["3", "5"]) == {job.name: 0 for job in plan.jobs}
    assert seen["e-s0"][0] == plan.jobs[0].resume_command(), "a checkpoint: resumed, not started again"
    assert seen["e-s1"][0] == plan.jobs[1].train_command()
    assert {device for _, device in seen.values()} == {"3", "5"}, "one edit per GPU"


def test_a_job_whose_runner_was_killed_is_waited_for_never_run_twice(fake_scene, tmp_path, monkeypatch):
    """kill -9 of sked-batch leaves the ns-train it started running: the next sked-batch reports that process and
    starts no second writer into its run folder; once it has finished the edit, the job is done, not failed."""
    import sked_ns.batch.task as task

    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1]}]))
    job, by_hand = plan.jobs
    fake_checkpoints(job, [4], total=10)
    runner = subprocess.Popen([sys.executable, "-c", "pass"])
    runner.wait()  # killed
    edit = holding(job.run_dir)  # its ns-train, which holds the run folder as ns-train does
    host = socket.gethostname()
    state.write_marker(job, "running", {"owner": {"pid": runner.pid, "host": host}, "attempt": 1, "child": {
        "pid": edit.pid, "host": host, "started": run_lock.process_start(edit.pid), "command": "ns-train"}})
    status = state.job_status(job, {})
    assert (status.state, status.where) == ("running", f"pid {edit.pid} on {host}"), status
    assert f"its runner (pid {runner.pid} on {host}) has ended" in status.note
    started = []
    monkeypatch.setattr(task, "run_stage", lambda job_, command, env: started.append(command) or 0)
    assert run_job(job) == 0 and started == [], "a second ns-train into the same run folder"
    assert state.read_marker(job, "failed") is None and state.read_marker(job, "running")["child"]["pid"] == edit.pid
    fake_checkpoints(job, [9], total=10)  # the orphan finishes the edit and ends
    killed(edit)
    assert "ran to its end" in state.job_status(job, {}).note
    assert run_job(job) == 0 and started == [], "nothing left to edit"
    assert state.job_status(job, {}).state == "done" and state.read_marker(job, "failed") is None
    # An `ns-train` resumed by hand into a job's run folder (no marker names it) runs the job too.
    typed = holding(by_hand.run_dir)
    try:
        assert state.job_status(by_hand, {}).where == f"pid {typed.pid} on {host}"
        assert to_run(plan, None) == [], "done, and running"
        assert run_job(by_hand) == 0 and started == []
    finally:
        killed(typed)


def test_one_runner_per_job(fake_scene, tmp_path, monkeypatch):
    """Two sked-batch runs of one plan: a job the other has taken (before its marker is written) is left to it."""
    import sked_ns.batch.task as task

    job = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e"}])).jobs[0]
    other = holding(job.folder / "batch", WRITE)  # another sked-batch running the job
    started = []
    monkeypatch.setattr(task, "run_stage", lambda job_, command, env: started.append(command) or 0)
    try:
        assert run_job(job) == 0 and started == []
        assert state.read_marker(job, "running") is None, "the markers are the other runner's to write"
    finally:
        killed(other)
    monkeypatch.undo()
    monkeypatch.setattr(task, "executable", lambda name: sys.executable)
    state.write_marker(job, "running", {"owner": state.this_owner()})
    # The runner records the command it starts (what a kill -9 of the runner leaves behind).
    code = task.run_stage(job, ["ns-train", "-c", "import os; print('pid', os.getpid())"], None)
    child = state.read_marker(job, "running")["child"]
    assert code == 0 and f"pid {child['pid']}\n" in job.log.read_text()
    assert child["command"] == "ns-train" and child["started"] is not None


def test_the_sbatch_script_maps_array_tasks_to_jobs(fake_scene, tmp_path):
    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1]}],
                                slurm={"partition": "gpu", "time": "4:00:00", "max_parallel": 8}))
    options = slurm_options(plan, {"account": "lab", "gpus": None, "sbatch_args": ["--qos=high"]})
    script = sbatch_script(plan, plan.jobs, options)
    for line in ("#SBATCH --array=0-1%8", "#SBATCH --partition=gpu", "#SBATCH --time=4:00:00", "#SBATCH --account=lab",
                 "#SBATCH --gpus=1", "#SBATCH --qos=high", "JOBS=(e-s0 e-s1)", f"#SBATCH --output={plan.output}/slurm/%A_%a.out"):
        assert line in script, script
    assert re.search(r'exec \S*python\S* -m sked_ns\.batch task \S+plan\.yml --job "\$\{JOBS\[\$SLURM_ARRAY_TASK_ID\]\}"',
                     script)
    assert "--gpus" not in sbatch_script(plan, plan.jobs, slurm_options(plan, {"gpus": 0}))


def test_two_submissions_in_one_second_keep_their_own_scripts(fake_scene, tmp_path, monkeypatch):
    import sked_ns.batch.runners as runners

    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": [0, 1]}]))
    arrays = iter(["101", "102"])
    monkeypatch.setattr(runners, "sbatch", lambda arguments: next(arrays))
    monkeypatch.setattr(runners.time, "strftime", lambda form, *args: "20260101-000000")  # the same second
    options = slurm_options(plan, {"gpus": 0})
    options.report_job = False
    for job in plan.jobs:  # scripts that launch a submission per job
        runners.submit_slurm(plan, [job], options)
    for job in plan.jobs:
        script = Path(state.read_marker(job, "submitted")["script"]).read_text()
        assert f"JOBS=({job.name})" in script, f"{job.name}'s array runs another job"


def test_the_report_has_a_row_and_a_sheet_row_per_job(fake_scene, tmp_path):
    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "prompt": "a hat", "seeds": [0, 1]}]))
    done, failed = plan.jobs
    fake_checkpoints(done, [3], total=4)
    state.write_marker(done, "done", {})
    views = [{"w": 32, "h": 32}, {"w": 32, "h": 16}]  # rows of sked-eval's sheet: 24 and 12 px at --resolution 24
    (fake_scene["sketches"] / "sketches.json").write_text(json.dumps({"views": views}))
    (done.run_dir / "sked_eval.json").write_text(json.dumps({
        "resolution": 24, "sketches": str(fake_scene["sketches"]), "views": [{}, {}],
        "mean": {"ios": 0.9, "psnr_outside": 31.0}, "clip_similarity": "unavailable: no prompt",
        "novel_views": {"mean": {"psnr_keep": 40.0}}}))
    Image.new("RGB", (72, 24 + 12 + 24), (255, 0, 0)).save(done.run_dir / "sked_eval.png")
    state.write_marker(failed, "failed", {"stage": "eval", "reason": "sked-eval exited with 1"})
    paths = write_report(plan)
    rows = list(csv.DictReader(paths["csv"].open()))
    assert [(r["job"], r["status"], r["prompt"], r["seed"]) for r in rows] == [
        ("e-a-hat-s0", "done", "a hat", "0"), ("e-a-hat-s1", "failed", "a hat", "1")]
    assert (rows[0]["ios"], rows[0]["novel_psnr_keep"], rows[1]["ios"]) == ("0.9", "40.0", "")
    assert "clip_similarity" not in rows[0], "a reason is not a number"
    assert json.loads(paths["json"].read_text())["jobs"][0]["psnr_outside"] == 31.0
    sheet = Image.open(paths["sheet"])
    assert sheet.height == 2 * ROW_HEIGHT
    # The done job's row holds its two sketch-view strips (red), the failed one's only its label.
    assert sheet.getpixel((sheet.width - 1, ROW_HEIGHT // 2)) == (255, 0, 0)
    assert sheet.getpixel((sheet.width - 1, ROW_HEIGHT + ROW_HEIGHT // 2)) != (255, 0, 0)


def test_reports_are_written_one_at_a_time(fake_scene, tmp_path):
    """The Slurm report job and a `sked-batch report` at once: the second waits, the three files are one table's."""
    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e"}]))
    other = holding(plan.output / "results.csv", WRITE)  # another report being written
    second = threading.Thread(target=write_report, args=(plan,))
    second.start()
    second.join(timeout=10)
    try:
        assert second.is_alive() and not (plan.output / "results.csv").exists(), "written beside another report"
    finally:
        killed(other)
    second.join()
    assert [p.name for p in sorted(plan.output.iterdir()) if p.is_file()] == ["contact_sheet.png", "results.csv",
                                                                            "results.json"]


def test_a_sweep_s_contact_sheet_stops_at_a_size_that_opens(fake_scene, tmp_path, monkeypatch):
    import sked_ns.batch.report as report

    monkeypatch.setattr(report, "SHEET_ROWS", 3)
    plan = load_plan(write_plan(tmp_path, fake_scene, [{"name": "e", "seeds": list(range(5))}]))
    paths = write_report(plan)
    assert Image.open(paths["sheet"]).height == 4 * ROW_HEIGHT, "three jobs and a line saying two more"
    assert len(list(csv.DictReader(paths["csv"].open()))) == 5


# ---- real edits ---------------------------------------------------------------------------------


def test_local_batch_runs_evaluates_reports_and_skips_what_is_done(scene, tmp_path):
    """`sked-batch PLAN --local`: two tiny edits one after another, sked-eval on the first, one table."""
    path = write_plan(tmp_path, scene, [
        {"name": "hat", "seed": 0, "eval": "--resolution 24 --cameras none"},
        {"name": "plain", "seed": 1},
    ], defaults={"flags": TINY_FLAGS + " --max-num-iterations 3 --steps-per-save 2"})
    result = sked_batch(path, "--local")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    rows = status_rows(result.stdout)
    assert rows == {"hat-s0": ("done", "3/3"), "plain-s1": ("done", "3/3")}, result.stdout
    plan = load_plan(path)
    assert (plan.job("hat-s0").run_dir / "nerfstudio_models" / "step-000000002.ckpt").is_file()
    table = list(csv.DictReader((plan.output / "results.csv").open()))
    assert [(r["job"], r["status"], r["seed"]) for r in table] == [("hat-s0", "done", "0"), ("plain-s1", "done", "1")]
    assert 0 <= float(table[0]["ios"]) <= 1 and float(table[0]["psnr_outside"]) > 15
    assert table[1]["ios"] == "", "not evaluated (eval: false)"
    assert Image.open(plan.output / "contact_sheet.png").height == 2 * ROW_HEIGHT
    again = sked_batch(path, "--local")  # idempotent: nothing left to run
    assert again.returncode == 0 and "nothing to run" in again.stdout, again.stdout + again.stderr
    assert status_rows(again.stdout) == rows


def test_the_edit_of_a_killed_runner_is_reported_not_started_again(scene, tmp_path):
    """kill -9 of `sked-batch --local` leaves its ns-train editing: status names it, a new run leaves it alone."""
    path = write_plan(tmp_path, scene, [{"name": "long", "seed": 0}],
                      defaults={"flags": TINY_FLAGS + " --max-num-iterations 2000 --steps-per-save 1000"})
    job = load_plan(path).jobs[0]
    runner = subprocess.Popen([sys.executable, "-m", "sked_ns.batch", str(path), "--local"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    wait_for(lambda: run_lock.holder(job.run_dir), 600, "its ns-train to take the run folder", [job.log], poll=0.2)
    edit = run_lock.holder(job.run_dir)
    runner.kill()  # kill -9: no chance to stop its ns-train
    runner.wait()
    try:
        assert run_lock.alive(edit), "the edit goes on without its runner"
        status = sked_batch("status", path)
        assert status_rows(status.stdout)["long-s0"][0] == "running", status.stdout
        assert f"pid {edit['pid']} on {socket.gethostname()}" in status.stdout
        again = sked_batch(path, "--local")
        assert again.returncode == 0 and "nothing to run" in again.stdout, again.stdout + again.stderr
        assert job.log.read_text().count("$ ns-train") == 1, "a second ns-train into the same run folder"
        assert run_lock.alive(edit) and state.read_marker(job, "failed") is None
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(edit["pid"], signal.SIGKILL)


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    reason = why_not()
    if reason:
        pytest.skip(reason)
    # CPUs=2: the two tiny edits of the plan run at once, one core each.
    with SlurmCluster(tmp_path_factory.mktemp("slurm"), cpus=2) as cluster:
        yield cluster


def test_slurm_array_runs_the_plan_and_resubmitting_resumes_a_cancelled_edit(scene, slurm, tmp_path):
    # A folder name sbatch's #SBATCH reading would split or cut at a comment unless escaped.
    path = write_plan(tmp_path / "plans #1 with space", scene, [
        {"name": "short", "seed": 0, "flags": "--max-num-iterations 3 --steps-per-save 2"},
        {"name": "long", "seed": 0, "flags": "--max-num-iterations 40 --steps-per-save 3"},  # long enough to cancel
    ])
    plan = load_plan(path)
    short, long = plan.job("short-s0"), plan.job("long-s0")
    env = slurm.env
    submitted = sked_batch(path, "--slurm", "--gpus", "0", env=env)
    assert submitted.returncode == 0, submitted.stdout + submitted.stderr
    array = re.search(r"submitted Slurm job array (\d+) \(2 task", submitted.stdout).group(1)
    assert (plan.output / "slurm").glob("submit-*.sbatch")
    checkpoints = long.run_dir / "nerfstudio_models"
    wait_for(lambda: state.read_marker(long, "running") or state.read_marker(long, "failed"), 600,
             "the long edit to start", [long.log])
    running = status_rows(sked_batch("status", path, env=env).stdout)
    assert running["long-s0"][0] == "running", running
    # Cancel as soon as a checkpoint exists (nothing slow in between: a tiny edit's steps are fast on an idle machine).
    wait_for(lambda: list(checkpoints.glob("step-*.ckpt")) or state.read_marker(long, "failed"), 600,
             "the long edit's first checkpoint", [long.log], poll=0.1)
    cancelled = subprocess.run(["scancel", f"{array}_1"], env=env, capture_output=True, text=True)
    assert cancelled.returncode == 0, cancelled.stderr
    wait_for(lambda: not subprocess.run(["squeue", "-h", "-j", array], env=env, capture_output=True, text=True).stdout.strip(),
             600, "the array to end", [short.log, long.log])
    rows = status_rows(sked_batch("status", path, env=env).stdout)
    assert rows["short-s0"] == ("done", "3/3"), rows
    assert rows["long-s0"][0] == "interrupted", rows
    saved = max(int(p.stem.split("-")[1]) for p in checkpoints.glob("step-*.ckpt"))
    assert 0 < saved < 39

    again = sked_batch(path, "--slurm", "--gpus", "0", env=env)  # only the interrupted edit goes again
    assert again.returncode == 0, again.stdout + again.stderr
    assert "long-s0: interrupted (resumes from step" in again.stdout and "short-s0" not in again.stdout, again.stdout
    assert "(1 task(s))" in again.stdout
    wait_for(lambda: not subprocess.run(["squeue", "-h"], env=env, capture_output=True, text=True).stdout.strip(), 600,
             "the resumed edit and the report job after it", [long.log])
    rows = status_rows(sked_batch("status", path, env=env).stdout)
    assert rows == {"short-s0": ("done", "3/3"), "long-s0": ("done", "40/40")}, rows
    assert (checkpoints / "step-000000039.ckpt").is_file(), "the resumed edit reached the same total"
    log = " ".join(long.log.read_text().split())  # rich wraps long lines
    assert f"Resuming the SKED edit {long.run_dir} from step-{saved:09d}.ckpt to 40 iterations" in log
    table = list(csv.DictReader((plan.output / "results.csv").open()))  # written by the report job
    assert [(r["job"], r["status"], r["steps"]) for r in table] == [("short-s0", "done", "3"), ("long-s0", "done", "40")]


def test_a_dry_run_prints_command_lines_a_shell_runs_as_planned(tmp_path, capsys):
    """A sketches path with a space and a prompt with a shell metacharacter: each printed line, run through bash,
    gives the job's own arguments and runs nothing else."""
    from sked_ns.batch.cli import main

    folder = tmp_path / "with space"
    scene = {"base": folder / "base", "data": folder / "data", "sketches": folder / "my sketches"}
    for path in scene.values():
        path.mkdir(parents=True)
    (scene["base"] / "config.yml").write_text("method_name: nerfacto\n")
    (scene["sketches"] / "sketches.json").write_text("{}")
    prompt = "a hat; echo INJECTED $(echo TWICE) 'quoted'"
    path = write_plan(tmp_path / "p", scene, [{"name": "e", "prompts": [prompt]}])
    with pytest.raises(SystemExit) as ended:
        main([str(path), "--local", "--dry-run"])
    assert ended.value.code == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "--prompt" in line]
    assert len(lines) == 1
    expected = list(load_plan(path).jobs[0].train_command())
    shown = subprocess.run(["bash", "-c", f"set -- {lines[0]}; printf '%s\\0' \"$@\""], capture_output=True,
                           text=True, check=True).stdout
    assert shown.split("\0")[:-1] == expected
    assert prompt in expected and str(scene["sketches"]) in expected


@pytest.mark.parametrize("argv, message", [([], r"sked-batch: the following arguments are required: plan"),
                                           (["p.yml"], r"sked-batch: one of the arguments --local --slurm is required"),
                                           (["status"], r"sked-batch status: the following arguments are required"),
                                           (["p.yml", "--local", "--bogus"], r"unrecognized arguments: --bogus")])
def test_a_bad_command_line_is_one_error_line_without_argparse_s_usage(argv, message, capsys):
    from sked_ns.batch.cli import main

    with pytest.raises(SkedUserError, match=message + r".*\(see sked-batch.*--help\)\."):
        main(argv)
    assert "usage:" not in capsys.readouterr().err


def sbatch_arguments(line: str) -> list:
    """A plain reading of an #SBATCH line as Slurm 22.05's sbatch reads it (src/sbatch/opt.c, get_argument): whitespace
    splits, '...' and "..." group, a backslash escapes the next character but an escaped space still ends the
    argument (fixed in later Slurm), an unescaped # outside quotes ends the line."""
    text, arguments, position = line[len("#SBATCH"):], [], 0
    while True:
        while position < len(text) and text[position].isspace():
            position += 1
        if position >= len(text):
            return arguments
        argument, quote, escaped = [], None, False
        while position < len(text) and (quote is not None or not text[position].isspace()):
            character = text[position]
            if escaped:
                escaped = False
            elif character == "\\":
                escaped, position = True, position + 1
                continue
            elif quote is not None:
                if character == quote:
                    quote, position = None, position + 1
                    continue
            elif character in "\"'":
                quote, position = character, position + 1
                continue
            elif character == "#":
                return arguments + (["".join(argument)] if argument else [])
            argument.append(character)
            position += 1
        arguments.append("".join(argument))


@pytest.mark.parametrize("value", ["plain", "with space", "a#b # c", 'say "hi"', "it's", "back\\slash", "tab\there",
                                   "%A_%a"])
def test_an_sbatch_line_gives_back_each_argument_whole(value):
    from sked_ns.batch.runners import sbatch_word

    assert sbatch_arguments(f"#SBATCH {sbatch_word('--comment=' + value)} --array=0-1") == [f"--comment={value}",
                                                                                           "--array=0-1"]


def test_an_sbatch_line_refuses_a_line_break():
    from sked_ns.batch.runners import sbatch_word

    with pytest.raises(SkedUserError, match="cannot hold a line break"):
        sbatch_word("--output=/a\nb")

