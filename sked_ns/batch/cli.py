"""The `sked-batch` command line."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from collections import Counter, abc
from itertools import islice
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence

from sked_ns.batch.plan import Job, Jobs, Plan, size_warning
from sked_ns.batch.plan_file import load_plan, output_problem, slurm_problem
from sked_ns.batch.state import TO_RUN, JobStatus, plan_status, status_table
from sked_ns.errors import ArgumentParser, SkedUserError, show_warnings_as_lines, warn
from sked_ns.guide import guide

SHOWN_JOBS = 50
"""Jobs listed one by one when a plan is submitted (or dry-run) at most; the rest are counted."""
SLURM_FLAGS = ("partition", "time", "gpus", "account", "cpus_per_task", "mem", "max_parallel", "sbatch_arg")

USAGE = """sked-batch PLAN --local | --slurm [options]   run the plan's edits not done yet (resumes interrupted ones)
       sked-batch status PLAN                         done / running / queued / failed / interrupted / pending, with logs
       sked-batch report PLAN                         results.csv, results.json and contact_sheet.png
       sked-batch task PLAN --job NAME                run one job here (what each Slurm array task runs)"""


def run_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="sked-batch", usage=USAGE, description=(
        "A batch of SKED edits from a plan file (YAML or TOML): one `ns-train` run per edit, prompt and seed, each in "
        "its own folder; submitting the plan again skips finished edits, resumes interrupted ones and reruns failed "
        f"ones. See {guide('batch.md')}."))
    parser.add_argument("plan", type=Path, help="the plan file")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--local", action="store_true", help="run here: one after another, or one per visible GPU at once")
    where.add_argument("--slurm", action="store_true", help="submit a Slurm job array, one task per edit")
    parser.add_argument("--devices", default=None,
                        help="--local: GPUs to use, one edit each at once (e.g. 0,1; default: the visible ones; "
                             "'none': one after another on what ns-train is told to use)")
    parser.add_argument("--job", action="append", default=None, metavar="NAME", help="only these jobs (repeatable)")
    parser.add_argument("--dry-run", action="store_true", help="print what would run (and the sbatch script) and stop")
    slurm = parser.add_argument_group("--slurm (over the plan's slurm: settings)")
    slurm.add_argument("--partition", help="Slurm partition (default: the cluster's)")
    slurm.add_argument("--time", help="per edit, Slurm's format (4:00:00); an edit it cuts resumes when resubmitted")
    slurm.add_argument("--gpus", type=int, help="GPUs per edit (default 1; 0 on a CPU partition)")
    slurm.add_argument("--account", help="Slurm account to charge (default: yours)")
    slurm.add_argument("--cpus-per-task", type=int, help="CPU cores per edit (default: Slurm's)")
    slurm.add_argument("--mem", help="memory per edit, Slurm's format (e.g. 32G; default: Slurm's)")
    slurm.add_argument("--max-parallel", type=int, help="at most this many edits at once (--array=0-N%%M)")
    slurm.add_argument("--sbatch-arg", action="append", default=None, metavar="ARG",
                       help="any other sbatch option, e.g. --sbatch-arg=--qos=high (repeatable)")
    slurm.add_argument("--no-report-job", action="store_true", help="do not submit the report job after the array")
    return parser


def print_status(statuses: List[JobStatus]) -> None:
    print(status_table(statuses))


def _names(jobs: Sequence[Job]) -> Iterator[str]:
    return jobs.names() if isinstance(jobs, Jobs) else (job.name for job in jobs)


def started_states(plan: Plan, jobs: Sequence[Job]) -> Dict[str, JobStatus]:
    """state.plan_status of the jobs that have a folder; a job without one is pending (nothing of it ran), so a
    sweep's many new jobs cost neither file reads nor objects."""
    try:
        folders = {entry.name for entry in os.scandir(plan.output) if entry.is_dir()}
    except OSError:  # no output folder yet
        folders = set()
    started = [jobs[index] for index, name in enumerate(_names(jobs)) if name in folders] if folders else []
    return {status.job.name: status for status in plan_status(started)}


def job_states(jobs: Sequence[Job], started: Dict[str, JobStatus]) -> Iterator[JobStatus]:
    """Every job's state in plan order, each job made when reached."""
    for index, name in enumerate(_names(jobs)):
        yield started.get(name) or JobStatus(jobs[index], "pending", 0, None, "")


class Waiting(abc.Sequence):
    """The jobs to run (pending, failed, interrupted) in plan order, each made when asked for."""

    def __init__(self, jobs: Sequence[Job], started: Dict[str, JobStatus]):
        self.jobs, self.started = jobs, started
        self.indices = [index for index, name in enumerate(_names(jobs))
                        if name not in started or started[name].state in TO_RUN]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        job = self.jobs[self.indices[index]]
        return self.started.get(job.name) or JobStatus(job, "pending", 0, None, "")

    def run(self) -> Sequence[Job]:
        """Their jobs, each made when asked for."""
        return _JobsToRun(self)

    def counts(self) -> Counter:
        started = Counter(s.state for s in self.started.values() if s.state in TO_RUN)
        return started + Counter(pending=len(self) - sum(started.values()))


class _JobsToRun(abc.Sequence):
    def __init__(self, waiting: Waiting):
        self.waiting = waiting

    def __len__(self) -> int:
        return len(self.waiting)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return self.waiting.jobs[self.waiting.indices[index]]


def waiting(plan: Plan, names: Optional[List[str]]) -> Waiting:
    """The plan's jobs (or those named) that are pending, failed or interrupted; a job whose plan entry changed is
    refused."""
    jobs = [plan.job(name) for name in names] if names else plan.jobs
    started = started_states(plan, jobs)
    changed = [s for s in started.values() if s.state == "changed"]
    if changed:
        raise SkedUserError(f"{plan.path}: " + "; ".join(f"{s.job.name}: {s.note}" for s in changed) + ". Its run "
                            "folder holds the earlier edit: give the edit another name, or remove "
                            + ", ".join(str(s.job.folder) for s in changed) + " to run it anew.")
    return Waiting(jobs, started)


def to_run(plan: Plan, names: Optional[List[str]]) -> List[JobStatus]:
    """The plan's jobs that are pending, failed or interrupted; a job whose plan entry changed is refused."""
    return list(waiting(plan, names))


def all_states(plan: Plan) -> List[JobStatus]:
    return list(job_states(plan.jobs, started_states(plan, plan.jobs)))


def check_output(plan: Plan) -> None:
    """The plan's output folder can be made and written in (tried without leaving anything)."""
    problem = output_problem(plan.output)
    if problem:
        raise SkedUserError(f"{plan.path}: output: {plan.output}: {problem} Give the plan a writable output: folder.")


def check_submission(plan: Plan, args) -> None:
    """The command line's settings, before anything is written: Slurm's as the plan's slurm: are checked, flags
    for the other runner are warned about (they would be ignored)."""
    for name in SLURM_FLAGS:
        value = getattr(args, name)
        for one in (value if isinstance(value, list) else [value]):
            problem = None if one is None else slurm_problem("sbatch_args" if name == "sbatch_arg" else name, one)
            if problem:
                raise SkedUserError(f"--{name.replace('_', '-')} {one}: {problem}")
    if args.local:
        typed = [f"--{name.replace('_', '-')}" for name in SLURM_FLAGS if getattr(args, name) is not None]
        typed += ["--no-report-job"] if args.no_report_job else []
        if typed:
            warn(f"{', '.join(typed)}: for --slurm only; --local ignores them.")
        if args.devices is not None and args.devices != "none":
            check_devices(args.devices)
    elif args.devices is not None:
        warn(f"--devices {args.devices}: for --local only; with --slurm, Slurm places each edit (--gpus per edit).")
    check_output(plan)


def check_devices(devices: str) -> None:
    """--devices: GPUs visible here, each named once."""
    from sked_ns.batch.runners import visible_gpus

    named = devices.split(",")
    if any(not device.strip() for device in named) or len(set(named)) != len(named):
        raise SkedUserError(f"--devices {devices}: GPUs separated by commas, each once (e.g. 0,1), or 'none'.")
    visible = visible_gpus()
    if not visible:
        raise SkedUserError(f"--devices {devices}: no GPU is visible here; pass --devices none (one edit after "
                            "another on what ns-train is told to use).")
    missing = [device for device in named if device.isdigit() and all(v.isdigit() for v in visible)
               and device not in visible]
    if missing:
        raise SkedUserError(f"--devices {devices}: GPU {', '.join(missing)} not visible here (visible: "
                            f"{', '.join(visible)}).")


def print_waiting(jobs: Waiting) -> None:
    notes = {"failed": lambda s: " (rerun)",
             "interrupted": lambda s: f" (resumes from step {s.step})" if s.step else ""}
    for status in islice(jobs, SHOWN_JOBS):
        print(f"{status.job.name}: {status.state}{notes.get(status.state, lambda s: '')(status)}")
    if len(jobs) > SHOWN_JOBS:
        counts = ", ".join(f"{n} {state}" for state, n in jobs.counts().items() if n)
        print(f"... {len(jobs) - SHOWN_JOBS} more, {len(jobs)} in all ({counts})")


def submit(args) -> int:
    from sked_ns.batch.runners import run_local, sbatch_script, slurm_options, submit_slurm

    plan = load_plan(args.plan)
    if size_warning(plan):
        warn(size_warning(plan))
    check_submission(plan, args)
    jobs = waiting(plan, args.job)
    if not jobs:
        print(f"{plan.path}: nothing to run (every job is done, running or queued):")
        print_status(all_states(plan))
        return 0
    print_waiting(jobs)
    if args.slurm:
        typed = {"partition": args.partition, "time": args.time, "gpus": args.gpus, "account": args.account,
                 "cpus_per_task": args.cpus_per_task, "mem": args.mem, "max_parallel": args.max_parallel,
                 "sbatch_args": args.sbatch_arg}
        options = slurm_options(plan, typed)
        options.report_job = options.report_job and not args.no_report_job
        if args.dry_run:  # printed, nothing written
            print(shortened(sbatch_script(plan, jobs.run(), options)))
            return 0
        submit_slurm(plan, list(jobs.run()), options)
        return 0
    if args.dry_run:
        for status in islice(jobs, SHOWN_JOBS):
            print(shlex.join(status.job.train_command()))  # pasted into a shell, each argument stays one
        if len(jobs) > SHOWN_JOBS:
            print(f"... and {len(jobs) - SHOWN_JOBS} more edits like these (sked-batch status {shlex.quote(str(args.plan))} lists them)")
        return 0
    devices = None if args.devices is None else [] if args.devices == "none" else args.devices.split(",")
    codes = run_local(list(jobs.run()), devices)
    from sked_ns.batch.report import write_report

    statuses = all_states(plan)
    paths = write_report(plan, statuses)
    print_status(statuses)
    print(f"wrote {paths['csv']}, {paths['json']} and {paths['sheet']}")
    return 1 if any(codes.values()) else 0


def shortened(script: str) -> str:
    """An sbatch script with its list of job names cut to the first few (a sweep's runs to megabytes)."""
    lines = script.split("\n")
    for index, line in enumerate(lines):
        names = line[len("JOBS=("):-1].split(" ") if line.startswith("JOBS=(") else []
        if len(names) > SHOWN_JOBS:
            lines[index] = (f"JOBS=({' '.join(names[:SHOWN_JOBS])} ...)  "
                            f"# {len(names)} names, {len(names) - SHOWN_JOBS} not shown here")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> None:
    show_warnings_as_lines()
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv else ""
    if command in ("status", "report", "task"):
        parser = ArgumentParser(prog=f"sked-batch {command}", usage=USAGE)
        parser.add_argument("plan", type=Path)
        if command == "task":
            parser.add_argument("--job", required=True, help="the job's name (sked-batch status PLAN lists them)")
        args = parser.parse_args(argv[1:])
        plan = load_plan(args.plan, check_paths=command == "task")
        if command != "status":
            check_output(plan)
        if command == "status":
            print_status(all_states(plan))
        elif command == "report":
            from sked_ns.batch.report import write_report

            paths = write_report(plan, all_states(plan))
            print(f"wrote {paths['csv']}, {paths['json']} and {paths['sheet']}")
        else:
            from sked_ns.batch.task import run_job

            sys.exit(run_job(plan.job(args.job)))
        return
    sys.exit(submit(run_parser().parse_args(argv)))
