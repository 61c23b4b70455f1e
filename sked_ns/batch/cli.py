"""The `sked-batch` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional

from sked_ns.batch.plan import Plan, load_plan
from sked_ns.batch.state import TO_RUN, JobStatus, plan_status, status_table
from sked_ns.errors import SkedUserError

USAGE = """sked-batch PLAN --local | --slurm [options]   run the plan's edits not done yet (resumes interrupted ones)
       sked-batch status PLAN                         done / running / queued / failed / interrupted / pending, with logs
       sked-batch report PLAN                         results.csv, results.json and contact_sheet.png
       sked-batch task PLAN --job NAME                run one job here (what each Slurm array task runs)"""


def run_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sked-batch", usage=USAGE, description=(
        "A batch of SKED edits from a plan file (YAML or TOML): one `ns-train` run per edit, prompt and seed, each in "
        "its own folder; submitting the plan again skips finished edits, resumes interrupted ones and reruns failed "
        "ones. See the README, 'Many edits: sked-batch'."))
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
    slurm.add_argument("--partition")
    slurm.add_argument("--time", help="per edit, Slurm's format (4:00:00); an edit it cuts resumes when resubmitted")
    slurm.add_argument("--gpus", type=int, help="GPUs per edit (default 1; 0 on a CPU partition)")
    slurm.add_argument("--account")
    slurm.add_argument("--cpus-per-task", type=int)
    slurm.add_argument("--mem")
    slurm.add_argument("--max-parallel", type=int, help="at most this many edits at once (--array=0-N%%M)")
    slurm.add_argument("--sbatch-arg", action="append", default=None, metavar="ARG",
                       help="any other sbatch option, e.g. --sbatch-arg=--qos=high (repeatable)")
    slurm.add_argument("--no-report-job", action="store_true", help="do not submit the report job after the array")
    return parser


def print_status(statuses: List[JobStatus]) -> None:
    print(status_table(statuses))


def to_run(plan: Plan, names: Optional[List[str]]) -> List[JobStatus]:
    """The plan's jobs that are pending, failed or interrupted; a job whose plan entry changed is refused."""
    jobs = [plan.job(name) for name in names] if names else plan.jobs
    statuses = plan_status(jobs)
    changed = [s for s in statuses if s.state == "changed"]
    if changed:
        raise SkedUserError(f"{plan.path}: " + "; ".join(f"{s.job.name}: {s.note}" for s in changed) + ". Its run "
                            "folder holds the earlier edit: give the edit another name, or remove "
                            + ", ".join(str(s.job.folder) for s in changed) + " to run it anew.")
    return [s for s in statuses if s.state in TO_RUN]


def submit(args) -> int:
    from sked_ns.batch.runners import run_local, slurm_options, submit_slurm

    plan = load_plan(args.plan)
    waiting = to_run(plan, args.job)
    if not waiting:
        print(f"{plan.path}: nothing to run (every job is done, running or queued):")
        print_status(plan_status(plan.jobs))
        return 0
    jobs = [s.job for s in waiting]
    for status in waiting:
        note = {"failed": " (rerun)", "interrupted": f" (resumes from step {status.step})" if status.step else ""}
        print(f"{status.job.name}: {status.state}{note.get(status.state, '')}")
    if args.slurm:
        typed = {"partition": args.partition, "time": args.time, "gpus": args.gpus, "account": args.account,
                 "cpus_per_task": args.cpus_per_task, "mem": args.mem, "max_parallel": args.max_parallel,
                 "sbatch_args": args.sbatch_arg}
        options = slurm_options(plan, typed)
        options.report_job = options.report_job and not args.no_report_job
        submit_slurm(plan, jobs, options, dry_run=args.dry_run)
        return 0
    if args.dry_run:
        for job in jobs:
            print(" ".join(job.train_command()))
        return 0
    devices = None if args.devices is None else [] if args.devices == "none" else args.devices.split(",")
    codes = run_local(jobs, devices)
    from sked_ns.batch.report import write_report

    statuses = plan_status(plan.jobs)
    paths = write_report(plan, statuses)
    print_status(statuses)
    print(f"wrote {paths['csv']}, {paths['json']} and {paths['sheet']}")
    return 1 if any(codes.values()) else 0


def main(argv: Optional[List[str]] = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv else ""
    if command in ("status", "report", "task"):
        parser = argparse.ArgumentParser(prog=f"sked-batch {command}", usage=USAGE)
        parser.add_argument("plan", type=Path)
        if command == "task":
            parser.add_argument("--job", required=True, help="the job's name (sked-batch status PLAN lists them)")
        args = parser.parse_args(argv[1:])
        plan = load_plan(args.plan, check_paths=command == "task")
        if command == "status":
            print_status(plan_status(plan.jobs))
        elif command == "report":
            from sked_ns.batch.report import write_report

            paths = write_report(plan)
            print(f"wrote {paths['csv']}, {paths['json']} and {paths['sheet']}")
        else:
            from sked_ns.batch.task import run_job

            sys.exit(run_job(plan.job(args.job)))
        return
    sys.exit(submit(run_parser().parse_args(argv)))
