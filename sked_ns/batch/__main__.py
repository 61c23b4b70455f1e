"""`python -m sked_ns.batch`: the same as `sked-batch` (what the Slurm array tasks run)."""

from sked_ns.batch import entrypoint

entrypoint()
