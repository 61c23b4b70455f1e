"""What happened to a job, read from files in its folder (no database, no scheduler of our own).

`<job>/batch/` holds `job.json` (the commands the plan made), `running.json` (who runs it: a Slurm job
id or a pid and host), `failed.json` (the stage, exit code and log), `done.json`, and `submitted.json`
(the Slurm array task it was queued as). The run's checkpoints say how far it got. A running marker whose
owner is gone (scancel, a time limit, a node failure, Ctrl-C) means *interrupted*: it resumes.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Optional

from sked_ns.atomic import write_text_atomically
from sked_ns.batch.plan import Job
from sked_ns.run_lock import alive, holder, process_start

STATES = ("done", "running", "queued", "failed", "interrupted", "pending", "changed")
TO_RUN = ("pending", "failed", "interrupted")
"""What a submission (local or Slurm) runs; done, running and queued jobs are left alone."""
SLURM_ALIVE = {"PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "REQUEUED", "RESIZING", "SIGNALING",
               "STAGE_OUT", "REQUEUE_HOLD", "REQUEUE_FED", "RESV_DEL_HOLD"}
STEP_FILE = re.compile(r"^step-(\d+)\.ckpt$")
TOTAL_LINE = re.compile(r"^max_num_iterations: (\d+)$", re.MULTILINE)


def marker(job: Job, name: str) -> Path:
    return job.folder / "batch" / f"{name}.json"


def read_marker(job: Job, name: str) -> Optional[dict]:
    try:
        return json.loads(marker(job, name).read_text())
    except (OSError, ValueError):
        return None


def write_marker(job: Job, name: str, content: dict) -> None:
    write_text_atomically(marker(job, name), json.dumps(content, indent=2))


def remove_marker(job: Job, *names: str) -> None:
    for name in names:
        marker(job, name).unlink(missing_ok=True)


def job_record(job: Job) -> dict:
    """What the plan asks of the job; a later plan asking something else for the same job is refused."""
    return {"name": job.name, "edit": job.edit, "prompt": job.prompt, "seed": job.seed, "preset": job.preset,
            "train": job.train_command(), "resume": job.resume_command(),
            "eval": None if job.eval_flags is None else job.eval_command()}


def changed(job: Job) -> Optional[str]:
    """How the plan's job differs from the edit this folder holds (None: the same, or nothing saved yet: a job
    that failed before its first checkpoint simply runs with the plan's new command)."""
    saved = read_marker(job, "job")
    if saved is None or (progress(job)[0] == 0 and read_marker(job, "done") is None):
        return None
    now = job_record(job)
    differs = [key for key in ("train", "eval") if saved.get(key) != now[key]]
    return f"its {' and '.join(differs)} command changed" if differs else None


def progress(job: Job) -> tuple:
    """(latest checkpoint step + 1 or 0, the run's total or None), from file names and config.yml alone."""
    models = job.run_dir / "nerfstudio_models"
    steps = [int(m.group(1)) for m in (STEP_FILE.match(p.name) for p in models.glob("step-*.ckpt")) if m] \
        if models.is_dir() else []
    total = None
    try:
        found = TOTAL_LINE.search((job.run_dir / "config.yml").read_text())
        total = int(found.group(1)) if found else None
    except OSError:
        pass
    return (max(steps) + 1 if steps else 0), total


def finished(job: Job) -> bool:
    """The edit saved its last step (nerfstudio saves step total - 1 when the run ends)."""
    done, total = progress(job)
    return total is not None and done >= total


def this_owner() -> dict:
    """Who runs a job here: the Slurm array task, else this process on this host."""
    if os.environ.get("SLURM_JOB_ID"):
        return {"slurm_job": os.environ["SLURM_JOB_ID"],
                "slurm_task": f"{os.environ.get('SLURM_ARRAY_JOB_ID', os.environ['SLURM_JOB_ID'])}_"
                              f"{os.environ.get('SLURM_ARRAY_TASK_ID', '0')}",
                "host": socket.gethostname()}
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": process_start(os.getpid())}


def slurm_states(ids: Iterable[str]) -> Optional[Dict[str, str]]:
    """Slurm's state of each job id (`123` or an array task `122_4`) it still knows; None without squeue."""
    ids = sorted(set(ids))
    if not ids:
        return {}
    if shutil.which("squeue") is None:
        return None
    # This user's jobs, not `-j ids`: squeue refuses the whole list once one id has left its memory.
    result = subprocess.run(["squeue", "--me", "-h", "-r", "-o", "%i|%A|%T"], capture_output=True, text=True, timeout=60)
    if result.returncode != 0:
        return None
    states = {}
    for line in result.stdout.splitlines():
        task, job_id, state = (line.split("|") + ["", ""])[:3]
        states[task.strip()] = states[job_id.strip()] = state.strip()
    return states


def owner_alive(owner: dict, slurm: Optional[Dict[str, str]]) -> Optional[bool]:
    """Whether the job's runner still runs; None: cannot tell from here (no squeue, another host)."""
    if "slurm_job" in owner:
        if slurm is None:
            return None
        return slurm.get(owner["slurm_job"], slurm.get(owner.get("slurm_task", ""))) in SLURM_ALIVE
    return alive(owner)


def writer(job: Job, running: Optional[dict]) -> Optional[dict]:
    """The live process writing the job's run: the command its runner started (which a kill -9 of the runner
    leaves running), or whoever holds the run folder (an `ns-train` resumed by hand); None when none runs."""
    child = (running or {}).get("child")
    if child and alive(child):
        return child
    return holder(job.run_dir)


@dataclass
class JobStatus:
    job: Job
    state: str
    step: int
    total: Optional[int]
    where: str
    note: str = ""

    @property
    def log(self) -> Path:
        return self.job.log


def _owner_text(owner: dict) -> str:
    if "slurm_task" in owner:
        return f"Slurm {owner['slurm_task']}"
    return f"pid {owner.get('pid')} on {owner.get('host')}"


def job_status(job: Job, slurm: Optional[Dict[str, str]]) -> JobStatus:
    step, total = progress(job)
    status = lambda state, where="", note="": JobStatus(job, state, step, total, where, note)  # noqa: E731
    why = changed(job)
    if why:
        return status("changed", note=f"{why} since it ran ({marker(job, 'job')})")
    if read_marker(job, "done") is not None:
        return status("done")
    running, submitted = read_marker(job, "running"), read_marker(job, "submitted")
    working = writer(job, running)
    if running is not None:
        runs = owner_alive(running.get("owner", {}), slurm)
        if runs or runs is None:
            doing = f"{(working.get('command') or '?').split()[0]} pid {working['pid']}" if working else ""
            return status("running", _owner_text(running.get("owner", {})),
                          doing if runs else "cannot check from here")
    if working is not None:  # its runner has ended (kill -9), or someone resumed the edit by hand
        return status("running", _owner_text(working), f"{working.get('command') or 'a process'} writes its run folder"
                      + (f"; its runner ({_owner_text(running.get('owner', {}))}) has ended" if running else ""))
    if submitted is not None:
        queued = slurm is not None and slurm.get(submitted["slurm_task"]) in SLURM_ALIVE
        if queued:
            return status("queued", f"Slurm {submitted['slurm_task']}")
    failed = read_marker(job, "failed")
    if failed is not None:
        return status("failed", failed.get("where", ""), f"{failed.get('stage')}: {failed.get('reason')}")
    if running is not None:
        return status("interrupted", _owner_text(running.get("owner", {})),
                      "the edit ran to its end: evaluated and marked done at the next run" if finished(job) else
                      f"resumes from step {step}" if step else "starts again (no checkpoint yet)")
    return status("pending")


def plan_status(jobs: List[Job]) -> List[JobStatus]:
    """Every job's state; Slurm is asked once, for all of them."""
    ids = []
    for job in jobs:
        for name in ("running", "submitted"):
            owner = read_marker(job, name) or {}
            owner = owner.get("owner", owner)
            ids += [owner[key] for key in ("slurm_job", "slurm_task") if owner.get(key)]
    slurm = slurm_states(ids)
    return [job_status(job, slurm) for job in jobs]


def status_table(statuses: List[JobStatus]) -> str:
    rows = [("job", "state", "steps", "where", "log / note")]
    for s in statuses:
        steps = f"{s.step}/{s.total}" if s.total else (f"{s.step}/?" if s.step else "-")
        rows.append((s.job.name, s.state, steps, s.where or "-", (f"{s.note}; " if s.note else "") + str(s.log)))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row[:4], widths)) + "  " + row[4] for row in rows]
    counts = {state: sum(s.state == state for s in statuses) for state in STATES}
    lines.append(", ".join(f"{n} {state}" for state, n in counts.items() if n) + f" (of {len(statuses)})")
    return "\n".join(lines)
