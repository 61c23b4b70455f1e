"""Where the jobs run: here (one after another, or one per visible GPU at once) or as one Slurm job array.

Both run only the jobs that are pending, failed or interrupted (state.TO_RUN). Slurm gets a generated
sbatch script whose array task i runs the i-th of those jobs (`python -m sked_ns.batch task PLAN --job NAME`),
submitted with Slurm's own `sbatch`; then a report job that waits for the array (`--dependency=afterany`).
"""

from __future__ import annotations

import itertools
import json
import os
import queue
import shlex
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

from sked_ns.batch.plan import Job, Plan
from sked_ns.batch.state import write_marker
from sked_ns.batch.task import job_env, now, run_job
from sked_ns.errors import SkedUserError
from sked_ns.progress import Progress


def visible_gpus() -> List[str]:
    """The GPUs this process may use, as CUDA_VISIBLE_DEVICES entries (none on a CPU machine)."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [d.strip() for d in visible.split(",") if d.strip() and d.strip() != "-1"]
    try:
        import torch

        return [str(i) for i in range(torch.cuda.device_count())]
    except Exception:  # no torch with CUDA: run on the CPU
        return []


def run_local(jobs: List[Job], devices: Optional[List[str]] = None) -> Dict[str, int]:
    """Run the jobs here: one after another, or one per device at once (CUDA_VISIBLE_DEVICES=<device> each)."""
    devices = visible_gpus() if devices is None else devices
    codes: Dict[str, int] = {}
    progress = Progress("sked-batch", "edits", len(jobs))

    def finished(job: Job, code: int) -> None:
        codes[job.name] = code
        failed = sum(1 for value in codes.values() if value != 0)
        progress.step(f": {job.name} {'done' if code == 0 else f'failed (exit {code})'}"
                      + (f"; {failed} failed so far" if failed else ""))

    if len(devices) <= 1:
        for job in jobs:
            finished(job, run_job(job, job_env(devices[0] if devices else None)))
        return codes
    waiting: "queue.Queue[Job]" = queue.Queue()
    for job in jobs:
        waiting.put(job)

    def worker(device: str) -> None:
        while True:
            try:
                job = waiting.get_nowait()
            except queue.Empty:
                return
            finished(job, run_job(job, job_env(device)))

    threads = [threading.Thread(target=worker, args=(device,), daemon=True) for device in devices]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return codes


@dataclass
class SlurmOptions:
    partition: Optional[str] = None
    time: Optional[str] = None
    """Per array task, Slurm's format (`4:00:00`, `1-00:00:00`); an edit cut by it resumes when resubmitted."""
    gpus: int = 1
    account: Optional[str] = None
    cpus_per_task: Optional[int] = None
    mem: Optional[str] = None
    max_parallel: Optional[int] = None
    """At most this many array tasks at once (`--array=0-N%M`)."""
    sbatch_args: List[str] = field(default_factory=list)
    report_job: bool = True

    def directives(self) -> List[str]:
        options = [("partition", self.partition), ("time", self.time), ("account", self.account),
                   ("cpus-per-task", self.cpus_per_task), ("mem", self.mem)]
        lines = [f"--{name}={value}" for name, value in options if value is not None]
        if self.gpus:
            lines.append(f"--gpus={self.gpus}")
        return lines + list(self.sbatch_args)


def slurm_options(plan: Plan, typed: Dict[str, object]) -> SlurmOptions:
    """The plan's `slurm:` settings, with what was typed on the command line over them."""
    settings = {**plan.slurm, **{k: v for k, v in typed.items() if v is not None}}
    args = settings.pop("sbatch_args", [])
    if isinstance(args, str):
        args = shlex.split(args)
    options = SlurmOptions(**{k: v for k, v in settings.items() if k != "report_job"}, sbatch_args=list(args),
                           report_job=bool(settings.get("report_job", True)))
    if isinstance(options.gpus, bool) or not isinstance(options.gpus, int) or options.gpus < 0:
        raise SkedUserError(f"{plan.path}: slurm.gpus / --gpus {options.gpus!r}: a whole number >= 0 (GPUs per edit).")
    return options


def python_command() -> List[str]:
    """This environment's Python running sked-batch: what every array task runs (a shared file system assumed)."""
    return [sys.executable, "-m", "sked_ns.batch"]


SBATCH_SPECIAL = frozenset(" \t\"'\\#")
"""What sbatch's reading of an #SBATCH line treats specially: whitespace splits, quotes group, a backslash escapes
the next character, an unescaped # starts a comment."""


def sbatch_word(argument: str) -> str:
    """One argument as sbatch reads it back from an #SBATCH line: in double quotes when it holds a special character,
    with `"` and `\\` escaped inside (Slurm before 23 ends an argument at a backslash-escaped space, never in quotes)."""
    if "\n" in argument or "\r" in argument:
        raise SkedUserError(f"{argument!r}: an #SBATCH line cannot hold a line break; rename the folder or value.")
    if not SBATCH_SPECIAL.intersection(argument):
        return argument
    return '"' + argument.replace("\\", "\\\\").replace('"', '\\"') + '"'


def sbatch_script(plan: Plan, jobs: List[Job], options: SlurmOptions) -> str:
    """A job array, task i -> the i-th job to run; output of each task in <output>/slurm/<array>_<task>.out."""
    logs = plan.output / "slurm"
    array = f"0-{len(jobs) - 1}" + (f"%{options.max_parallel}" if options.max_parallel else "")
    # The plan's path in JSON's escapes: a newline in it must not end the comment line.
    lines = ["#!/bin/bash", f"# sked-batch {json.dumps(str(plan.path))}: {len(jobs)} edit(s), written {now()}",
             f"#SBATCH {sbatch_word(f'--job-name=sked-batch-{plan.name}')}", f"#SBATCH --array={array}",
             # %% is Slurm's literal % in a file name pattern; %A_%a the array's job and task.
             f"#SBATCH {sbatch_word('--output=' + str(logs).replace('%', '%%') + '/%A_%a.out')}"]
    lines += [f"#SBATCH {sbatch_word(directive)}" for directive in options.directives()]
    lines += ["", "set -euo pipefail", "# SLURM_ARRAY_TASK_ID -> the job it runs (the plan's jobs that were not done)",
              "JOBS=(" + " ".join(shlex.quote(job.name) for job in jobs) + ")",
              "exec " + " ".join(shlex.quote(t) for t in python_command() + ["task", str(plan.path)])
              + ' --job "${JOBS[$SLURM_ARRAY_TASK_ID]}"', ""]
    return "\n".join(lines)


def sbatch(arguments: List[str]) -> str:
    """Submit with Slurm's sbatch; the job id."""
    try:
        result = subprocess.run(["sbatch", "--parsable", *arguments], capture_output=True, text=True, timeout=120)
    except FileNotFoundError:
        raise SkedUserError("sked-batch --slurm: no `sbatch` on this machine; run it on the cluster's login node "
                            "(or use --local).") from None
    if result.returncode != 0:
        raise SkedUserError(f"sbatch refused the job: {result.stderr.strip() or result.stdout.strip()} "
                            f"(sbatch {' '.join(arguments)})")
    return result.stdout.strip().split(";")[0]


def new_script(logs: Path, script: str) -> Path:
    """`submit-<time>.sbatch`, a file of this submission's own: two in one second get `-2`, `-3`... (each array
    runs the jobs its own script lists, and its markers name that script)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for number in itertools.count(1):
        path = logs / (f"submit-{stamp}.sbatch" if number == 1 else f"submit-{stamp}-{number}.sbatch")
        try:
            with open(path, "x") as file:  # created here, or another submission's: the next name
                file.write(script)
            return path
        except FileExistsError:
            continue


def submit_slurm(plan: Plan, jobs: List[Job], options: SlurmOptions, dry_run: bool = False) -> Optional[str]:
    """Submit the jobs as one array (and the report after it); the array's job id."""
    logs = plan.output / "slurm"
    logs.mkdir(parents=True, exist_ok=True)
    script = sbatch_script(plan, jobs, options)
    if dry_run:
        print(script)
        return None
    script_path = new_script(logs, script)
    array_id = sbatch([str(script_path)])
    for index, job in enumerate(jobs):
        write_marker(job, "submitted", {"slurm_task": f"{array_id}_{index}", "script": str(script_path), "at": now()})
    print(f"submitted Slurm job array {array_id} ({len(jobs)} task(s)): {script_path}; task output in {logs}")
    if options.report_job:
        report = " ".join(shlex.quote(t) for t in python_command() + ["report", str(plan.path)])
        plain = [f"--{name}={value}" for name, value in (("partition", options.partition), ("account", options.account))
                 if value is not None]
        report_id = sbatch([f"--job-name=sked-batch-{plan.name}-report", f"--dependency=afterany:{array_id}",
                            f"--output={logs}/%j-report.out", "--time=00:30:00", *plain, "--wrap", report])
        print(f"submitted the report as Slurm job {report_id} (runs when the array has ended): "
              f"{plan.output / 'results.csv'}")
    return array_id
