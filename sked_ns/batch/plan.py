"""A plan file: edits with prompts and seeds, expanded to jobs, each the `ns-train` command a user would type.

```yaml
name: hats                      # default: the file's name
output: outputs/hats            # default: outputs/<name>; relative paths are relative to the plan's folder
defaults:                       # any edit field, for every edit
  preset: sked-fast
  flags: --vis tensorboard      # more `ns-train` flags (a string or a list)
edits:
  - name: sphere-hat
    base: outputs/sphere/nerfacto/2026-01-01_000000
    data: data/sphere
    sketches: sketches/hat
    prompts: ["a red chef hat", "a blue cap"]
    seeds: [0, 1]
```

One job per (edit, prompt, seed), named `<edit>-<prompt words>-s<seed>`, whose run folder is
`<output>/<job>/<preset>/run` (`--output-dir <output> --experiment-name <job> --timestamp run`), so every
later submission finds it again. plan_file.py reads and checks a plan file.
"""

from __future__ import annotations

import bisect
import re
import shlex
from collections import abc
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

from sked_ns.errors import SkedUserError

PRESETS = ("sked", "sked-fast", "sked-quality")
EDIT_FIELDS = ("name", "base", "data", "dataparser", "sketches", "prompts", "prompt", "seeds", "seed", "preset",
               "flags", "eval")
"""What an edit (or the plan's `defaults`) may hold; `prompt` and `seed` are the one-item spellings."""
PLAN_FIELDS = ("name", "output", "defaults", "edits", "slurm")
SLURM_FIELDS = ("partition", "time", "gpus", "account", "cpus_per_task", "mem", "max_parallel", "sbatch_args")
REQUIRED = ("base", "data", "sketches")
SET_BY_PLAN = {
    "--load-dir": "base", "--sketches": "sketches", "--pipeline.model.sketches": "sketches", "--prompt": "prompts",
    "--pipeline.model.prompt": "prompts", "--machine.seed": "seeds", "--data": "data",
    "--output-dir": "output (the plan's)", "--experiment-name": "name", "--timestamp": "name", "--progressive": None,
    "--load-step": None, "--load-checkpoint": None, "--load-config": None,
}
"""`ns-train` flags the plan writes itself (from the named field) or that would make a job another kind of run."""
RUN_TIMESTAMP = "run"
"""Every job's fixed `--timestamp`: its run folder is the same at every submission, so a rerun resumes it."""
SUBCOMMAND = re.compile(r"^[A-Za-z_][\w.-]*:[\w-]+$")
"""`pipeline.model.guidance:reference`: a tyro subcommand, which must follow every plain flag."""
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
PLAUSIBLE_JOBS = 1000
"""More jobs than this in one plan is rarely meant (and more than Slurm's default MaxArraySize, 1001, takes in one
array): the plan is run, after a warning that says how many edits it makes."""
SHOWN_NAMES = 10
"""Job names listed in a message at most (a sweep has thousands)."""
SLURM_TIME = re.compile(r"^(\d+|\d+:\d+|\d+:\d+:\d+|\d+-\d+|\d+-\d+:\d+|\d+-\d+:\d+:\d+|UNLIMITED|INFINITE)$")
"""sbatch --time's formats: minutes, minutes:seconds, hours:minutes:seconds, days-hours[:minutes[:seconds]]."""
SLURM_MEMORY = re.compile(r"^\d+[KMGTkmgt]?$")


@dataclass(frozen=True)
class Job:
    """One `ns-train` run of the plan: an edit with one prompt and one seed."""

    name: str
    edit: str
    prompt: Optional[str]
    seed: Optional[int]
    preset: str
    base: Path
    data: Path
    sketches: Path
    flags: Tuple[str, ...]
    dataparser: Tuple[str, ...]
    eval_flags: Optional[Tuple[str, ...]]
    """`sked-eval` flags after the edit; None: no evaluation."""
    output: Path

    @property
    def folder(self) -> Path:
        """Everything of this job: the run, its log and state markers."""
        return self.output / self.name

    @property
    def run_dir(self) -> Path:
        return self.folder / self.preset / RUN_TIMESTAMP

    @property
    def log(self) -> Path:
        return self.folder / "batch" / "log.txt"

    def _where(self) -> List[str]:
        return ["--output-dir", str(self.output), "--experiment-name", self.name, "--timestamp", RUN_TIMESTAMP]

    def train_command(self) -> List[str]:
        """The new edit, as the user would type it: plain flags, then subcommands, then the dataparser."""
        options, subcommands = split_subcommands(list(self.flags))
        command = ["ns-train", self.preset, "--load-dir", str(self.base), "--sketches", str(self.sketches)]
        if self.prompt is not None:
            command += ["--prompt", self.prompt]
        if self.seed is not None:
            command += ["--machine.seed", str(self.seed)]
        command += self._where()
        vis = [options[i + 1] if option == "--vis" and i + 1 < len(options) else option.partition("=")[2]
               for i, option in enumerate(options) if option == "--vis" or option.startswith("--vis=")]
        if not vis:
            command += ["--vis", "tensorboard"]  # nerfstudio's viewer would keep the job alive after training
        elif "viewer" in vis[-1] and not any(o.startswith("--viewer.quit-on-train-completion") for o in options):
            command += ["--viewer.quit-on-train-completion", "True"]  # the job ends when the edit does
        return command + options + subcommands + list(self.dataparser) + ["--data", str(self.data)]

    def resume_command(self) -> List[str]:
        """Continue the interrupted edit from its last checkpoint, into the same run folder (sked_ns/engine/resume.py)."""
        return ["ns-train", self.preset, "--load-dir", str(self.run_dir)] + self._where()

    def eval_command(self) -> List[str]:
        return ["sked-eval", str(self.run_dir / "config.yml"), "--overwrite", *(self.eval_flags or ())]


@dataclass(frozen=True)
class Edit:
    """One edit of the plan, checked: a job per (prompt, seed), made when asked for, so a sweep's size is known
    from its lists and a million jobs are not a million objects."""

    label: str
    """How errors name it: `edits[0] (sphere-hat)`."""
    prompts: Tuple[Optional[str], ...]
    seeds: Tuple[Optional[int], ...]
    template: Job
    """Its jobs' common fields (name: the edit's; no prompt, no seed)."""

    def __len__(self) -> int:
        return len(self.prompts) * len(self.seeds)

    @property
    def name(self) -> str:
        return self.template.edit

    @cached_property
    def parts(self) -> Tuple[List[str], List[str]]:
        """What each prompt and each seed adds to the edit's name to make a job's."""
        return ([f"-{slug(p)}" if p is not None else "" for p in self.prompts],
                [f"-s{seed}" if seed is not None else "" for seed in self.seeds])

    def names(self) -> Iterator[str]:
        prompts, seeds = self.parts
        return (self.name + prompt + seed for prompt in prompts for seed in seeds)

    def job(self, index: int) -> Job:
        prompt, seed = divmod(index, len(self.seeds))
        prompts, seeds = self.parts
        return replace(self.template, name=self.name + prompts[prompt] + seeds[seed], prompt=self.prompts[prompt],
                       seed=self.seeds[seed])


class Jobs(abc.Sequence):
    """The plan's jobs in order (edit, prompt, seed), each made when it is asked for."""

    def __init__(self, edits: Sequence[Edit]):
        self.edits = list(edits)
        self._ends = []
        for edit in self.edits:
            self._ends.append((self._ends[-1] if self._ends else 0) + len(edit))

    def __len__(self) -> int:
        return self._ends[-1] if self._ends else 0

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        which = bisect.bisect_right(self._ends, index)
        return self.edits[which].job(index - (self._ends[which - 1] if which else 0))

    def __iter__(self) -> Iterator[Job]:
        for edit in self.edits:
            for index in range(len(edit)):
                yield edit.job(index)

    def names(self) -> Iterator[str]:
        """The jobs' names in order, without making the jobs."""
        for edit in self.edits:
            yield from edit.names()


@dataclass
class Plan:
    path: Path
    name: str
    output: Path
    jobs: Sequence[Job]
    slurm: Dict[str, object] = field(default_factory=dict)

    def job(self, name: str) -> Job:
        names = self.jobs.names() if isinstance(self.jobs, Jobs) else (job.name for job in self.jobs)
        for index, candidate in enumerate(names):
            if candidate == name:
                return self.jobs[index]
        raise SkedUserError(f"{self.path}: no job named {name!r}; its jobs are: {some_names(self)} "
                            f"(sked-batch status {shlex.quote(str(self.path))} lists them all).")


def some_names(plan: Plan) -> str:
    """The plan's first few job names, and how many more there are."""
    names = [job.name for job in plan.jobs[:SHOWN_NAMES]]
    more = len(plan.jobs) - len(names)
    return ", ".join(names) + (f" and {more} more" if more > 0 else "")


def split_flags(tokens: List[str]) -> Tuple[List[str], Dict[str, List[str]]]:
    """Plain flags (each with its values), and each subcommand with its own flags, keyed by what it sets:
    `pipeline.model.guidance:reference --pipeline.model.guidance.x 1` -> {"pipeline.model.guidance": [...]}.
    A flag outside the subcommand's own (`--max-num-iterations` after it) is a plain flag."""
    options: List[str] = []
    sections: Dict[str, List[str]] = {}
    current = None
    for token in tokens:
        if SUBCOMMAND.match(token):
            current = token.split(":")[0]
            sections[current] = []
        elif token.startswith("--") and current is not None and not token.startswith(f"--{current}."):
            current = None
        (sections[current] if current is not None else options).append(token)
    return options, sections


def split_subcommands(tokens: List[str]) -> Tuple[List[str], List[str]]:
    """Plain flags first, subcommands (each with its own flags) last: tyro reads them in that order."""
    options, sections = split_flags(tokens)
    return options, [token for section in sections.values() for token in section]


def merged_flags(defaults: Tuple[str, ...], own: Tuple[str, ...]) -> Tuple[str, ...]:
    """The plan's default flags, then the edit's (later flags win in ns-train); subcommands after every plain
    flag, an edit's subcommand replacing the default one it names (`pipeline.model.guidance:...`)."""
    default_options, default_sections = split_flags(list(defaults))
    options, sections = split_flags(list(own))
    sections = {**default_sections, **sections}
    return tuple(default_options + options + [token for section in sections.values() for token in section])


def slug(text: str, limit: int = 40) -> str:
    """Prompt words for a folder name: `a red chef hat` -> `a-red-chef-hat`."""
    words = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return words[:limit].rstrip("-") or "prompt"


def job_iterations(job: Job) -> int:
    """The edit's iterations: its flags' --max-num-iterations, else its preset's."""
    for index, token in enumerate(job.flags):
        if token.startswith("--max-num-iterations"):
            value = token.partition("=")[2] or (job.flags[index + 1] if index + 1 < len(job.flags) else "")
            if value.isdigit():
                return int(value)
    from importlib import resources

    import yaml

    preset = yaml.safe_load((resources.files("sked_ns.configs") / f"{job.preset}.yml").read_text())
    return int(preset["iterations"])


def size_warning(plan: Plan) -> Optional[str]:
    """What a plan of more than PLAUSIBLE_JOBS jobs means (edits, iterations, evaluations), or None."""
    if not isinstance(plan.jobs, Jobs) or len(plan.jobs) <= PLAUSIBLE_JOBS:
        return None
    edits = plan.jobs.edits
    largest = sorted(edits, key=len, reverse=True)[:3]
    sources = "; ".join(f"{e.label}: {len(e.prompts)} prompt(s) x {len(e.seeds)} seed(s)" for e in largest)
    iterations = sum(len(edit) * job_iterations(edit.template) for edit in edits)
    evaluations = sum(len(edit) for edit in edits if edit.template.eval_flags is not None)
    return (f"{plan.path}: {len(plan.jobs)} jobs ({sources}{'; ...' if len(edits) > 3 else ''}): {len(plan.jobs)} "
            f"ns-train edits of {iterations} iterations in all, and {evaluations} sked-eval runs. More than "
            f"{PLAUSIBLE_JOBS} is rarely meant (nor taken in one array by Slurm's default MaxArraySize); check the "
            "prompts and seeds lists, or split the plan.")


