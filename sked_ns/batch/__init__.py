"""`sked-batch`: many edits from one plan file, run one after another, one per GPU, or as a Slurm job array.

A plan (plan.py) expands to jobs, one per (edit, prompt, seed), each exactly the `ns-train <preset> ...`
command a user would type, writing into its own folder named from the plan. What happened to a job is read
from files in that folder (state.py), so submitting the same plan again skips finished jobs, resumes
interrupted ones from their last checkpoint and reruns failed ones. Each job is run by `task.py` (the same
code on a laptop and in an array task: the edit, then `sked-eval` on it); `report.py` gathers one table and
one contact sheet. Nothing here schedules: `--local` runs them here, `--slurm` hands them to `sbatch --array`.
"""

from __future__ import annotations


def entrypoint() -> None:
    from sked_ns.batch.cli import main

    main()
