"""One job, start to end, wherever it runs (a Slurm array task, `--local`, or `sked-batch task PLAN --job NAME`).

The edit: its `ns-train` command, or, when its run folder holds a checkpoint, the resume command (continues
the same edit from its latest checkpoint, into the same folder). Then `sked-eval` on it. Output goes to the
job's log; the markers say what happened (state.py).
"""

from __future__ import annotations

import contextlib
import datetime
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional

from sked_ns.batch.plan import Job
from sked_ns.batch.state import (
    finished,
    job_record,
    marker,
    owner_alive,
    progress,
    read_marker,
    remove_marker,
    slurm_states,
    this_owner,
    write_marker,
    writer,
)
from sked_ns.run_lock import WriterBusy, describe, is_this_process, process_start, writing


def now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


def executable(name: str) -> str:
    """`ns-train` / `sked-eval` of this environment (the venv's, whether or not it is activated)."""
    return shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name) or name


def claim(job: Job) -> Optional[str]:
    """Mark the job as run by this process; the reason it is not ours to run, or None."""
    running = read_marker(job, "running")
    if running is not None:
        owner = running.get("owner", {})
        ours = this_owner()
        same = all(owner.get(key) == ours.get(key) for key in ("slurm_job", "pid", "host"))
        ids = [owner[key] for key in ("slurm_job",) if key in owner]
        if not same and owner_alive(owner, slurm_states(ids) if ids else {}):
            return f"already running ({running.get('owner')})"
    working = writer(job, running)
    if working is not None and not is_this_process(working):  # never a second writer: it is waited for
        return f"already running: {describe(working)} writes {job.run_dir}"
    if read_marker(job, "done") is not None:
        return "already done"
    attempt = max(int((running or {}).get("attempt", 0)), int((read_marker(job, "failed") or {}).get("attempt", 0))) + 1
    write_marker(job, "running", {"owner": this_owner(), "since": now(), "attempt": attempt})
    remove_marker(job, "failed")
    return None


def run_stage(job: Job, command: List[str], env: Optional[Dict[str, str]]) -> int:
    """One command, its output appended to the job's log; its process in the running marker."""
    job.log.parent.mkdir(parents=True, exist_ok=True)
    with open(job.log, "a") as log:
        log.write(f"\n=== {now()}, {_where(this_owner())}\n$ {' '.join(_quoted(command))}\n")
        log.flush()
        resolved = [executable(command[0])] + command[1:]
        with subprocess.Popen(resolved, stdout=log, stderr=subprocess.STDOUT, env=env) as process:
            try:
                # A kill -9 of this runner leaves the command running: the next sked-batch finds it here.
                write_marker(job, "running", {**(read_marker(job, "running") or {}), "child": {
                    "pid": process.pid, "host": socket.gethostname(), "started": process_start(process.pid),
                    "command": command[0]}})
                return process.wait()
            except BaseException:  # as subprocess.run: an interrupted runner takes its command down with it
                process.kill()
                raise


def _quoted(command: List[str]) -> List[str]:
    import shlex

    return [shlex.quote(token) for token in command]


def fail(job: Job, stage: str, reason: str, code: int) -> int:
    running = read_marker(job, "running") or {}
    write_marker(job, "failed", {"stage": stage, "reason": reason, "exit_code": code, "log": str(job.log),
                                 "where": _where(running.get("owner", {})), "attempt": running.get("attempt", 1),
                                 "at": now()})
    remove_marker(job, "running")
    return code or 1


def _where(owner: dict) -> str:
    return f"Slurm {owner['slurm_task']}" if "slurm_task" in owner else f"pid {owner.get('pid')} on {owner.get('host')}"


def evaluated(job: Job) -> bool:
    """sked-eval's result is there and newer than the edit's last checkpoint."""
    result = job.run_dir / "sked_eval.json"
    checkpoints = list((job.run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    return result.is_file() and all(result.stat().st_mtime >= c.stat().st_mtime for c in checkpoints)


def run_job(job: Job, env: Optional[Dict[str, str]] = None) -> int:
    """Run (or resume, or only evaluate) the job here; 0 when it is done (or another runner has it)."""
    with contextlib.ExitStack() as runner:
        try:  # one runner per job: its markers have one writer
            runner.enter_context(writing(job.folder / "batch", "It runs the job."))
        except WriterBusy as busy:
            print(f"{job.name}: already running ({describe(busy.record)}); nothing to do")
            return 0
        return _run_claimed(job, env)


def _run_claimed(job: Job, env: Optional[Dict[str, str]]) -> int:
    reason = claim(job)
    if reason is not None:
        print(f"{job.name}: {reason}; nothing to do")
        return 0
    if not finished(job):
        step, _ = progress(job)
        if not step:  # a new edit: this is the command its run folder will hold
            write_marker(job, "job", job_record(job))
        command = job.resume_command() if step else job.train_command()
        print(f"{job.name}: {'resuming from step ' + str(step) if step else 'editing'}; log {job.log}", flush=True)
        code = run_stage(job, command, env)
        if code != 0:
            return fail(job, "edit", f"ns-train exited with {code}", code)
        if not finished(job):
            step, total = progress(job)
            return fail(job, "edit", f"ns-train ended after step {step} of {total} without its last checkpoint", 1)
    if job.eval_flags is not None and not evaluated(job):
        print(f"{job.name}: evaluating; log {job.log}", flush=True)
        code = run_stage(job, job.eval_command(), env)
        if code != 0:
            return fail(job, "eval", f"sked-eval exited with {code}", code)
    step, total = progress(job)
    write_marker(job, "done", {"steps": step, "total": total, "run": str(job.run_dir), "at": now(),
                               "eval": str(job.run_dir / "sked_eval.json") if job.eval_flags is not None else None})
    remove_marker(job, "running", "submitted")
    print(f"{job.name}: done ({step} steps, {job.run_dir})", flush=True)
    return 0


def job_env(device: Optional[str]) -> Dict[str, str]:
    """This process's environment, on one GPU when `device` is given."""
    env = dict(os.environ)
    if device is not None:
        env["CUDA_VISIBLE_DEVICES"] = device
    return env


__all__ = ["run_job", "job_env", "marker"]
