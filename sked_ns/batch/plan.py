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
later submission finds it again. Every mistake is an error naming the plan file, the entry and the field.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from sked_ns.errors import SkedFileNotFoundError, SkedUserError

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
        """Continue the interrupted edit from its last checkpoint, into the same run folder (sked_ns/resume.py)."""
        return ["ns-train", self.preset, "--load-dir", str(self.run_dir)] + self._where()

    def eval_command(self) -> List[str]:
        return ["sked-eval", str(self.run_dir / "config.yml"), "--overwrite", *(self.eval_flags or ())]


@dataclass
class Plan:
    path: Path
    name: str
    output: Path
    jobs: List[Job]
    slurm: Dict[str, object] = field(default_factory=dict)

    def job(self, name: str) -> Job:
        for job in self.jobs:
            if job.name == name:
                return job
        raise SkedUserError(f"{self.path}: no job named {name!r}; its jobs are: {', '.join(j.name for j in self.jobs)}.")


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


def read_plan_file(path: Path) -> dict:
    if not path.is_file():
        raise SkedFileNotFoundError(f"sked-batch {path}: no such plan file (a YAML or TOML file; see the README, "
                                    "'Many edits: sked-batch').")
    text = path.read_text()
    try:
        if path.suffix == ".toml":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise SkedUserError(f"{path}: TOML plans need Python 3.11 or later; write the plan in YAML.") from None

            data = tomllib.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except SkedUserError:
        raise
    except Exception as error:  # the parser's message says where
        raise SkedUserError(f"{path}: cannot read the plan: {error}") from error
    if not isinstance(data, dict):
        raise SkedUserError(f"{path}: a plan is a mapping with an `edits:` list (see the README, 'Many edits: sked-batch').")
    return data


class _Checker:
    """Errors that name the plan file, the entry and the field."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, message: str):
        raise SkedUserError(f"{self.path}: {where}: {message}")

    def unknown(self, where: str, entry: dict, known) -> None:
        extra = sorted(set(entry) - set(known))
        if extra:
            self.fail(where, f"unknown field(s) {', '.join(extra)}; known: {', '.join(known)}.")

    def tokens(self, where: str, value) -> Tuple[str, ...]:
        if value is None:
            return ()
        if isinstance(value, str):
            try:
                return tuple(shlex.split(value))
            except ValueError as error:
                self.fail(where, f"cannot split {value!r} into flags ({error}).")
        if isinstance(value, list) and all(isinstance(v, (str, int, float)) and not isinstance(v, bool) for v in value):
            return tuple(str(v) for v in value)
        self.fail(where, f"{value!r}: flags are a string (`--pipeline.model.beta 0.05`) or a list of strings.")

    def folder(self, where: str, value, root: Path) -> Path:
        if not isinstance(value, str) or not value.strip():
            self.fail(where, f"{value!r}: a path (relative paths are relative to the plan's folder {root}).")
        path = Path(value).expanduser()
        return (path if path.is_absolute() else root / path).resolve()


def load_plan(path: Path, check_paths: bool = True) -> Plan:
    """Read and check a plan; `check_paths`: the bases, data and sketch sets exist (before submitting)."""
    path = Path(path).resolve()
    data, check = read_plan_file(path), _Checker(path)
    check.unknown("the plan", data, PLAN_FIELDS)
    root = path.parent
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not SAFE_NAME.match(name):
        check.fail("name", f"{name!r}: letters, digits, '.', '_' and '-' only (it names folders and Slurm jobs).")
    output = check.folder("output", data.get("output", f"outputs/{name}"), root)
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        check.fail("defaults", "a mapping of edit fields (preset, flags, seeds, ...).")
    check.unknown("defaults", defaults, [f for f in EDIT_FIELDS if f != "name"])
    edits = data.get("edits")
    if not isinstance(edits, list) or not edits:
        check.fail("edits", "a list of edits, each with base, data and sketches (see the README, 'Many edits: sked-batch').")
    slurm = data.get("slurm") or {}
    if not isinstance(slurm, dict):
        check.fail("slurm", f"a mapping of {', '.join(SLURM_FIELDS)}.")
    check.unknown("slurm", slurm, SLURM_FIELDS)

    jobs: List[Job] = []
    seen: Dict[str, str] = {}
    for index, edit in enumerate(edits):
        if not isinstance(edit, dict):
            check.fail(f"edits[{index}]", "an edit is a mapping with base, data, sketches, prompts, ...")
        label = f"edits[{index}]" + (f" ({edit['name']})" if isinstance(edit.get("name"), str) else "")
        check.unknown(label, edit, EDIT_FIELDS)
        for new in _edit_jobs(check, label, index, {**defaults, **edit}, defaults, edit, root, output, check_paths):
            if new.name in seen:
                check.fail(label, f"job {new.name!r} is also made by {seen[new.name]}: give the edits different names "
                                  "(or prompts that differ in their words).")
            seen[new.name] = label
            jobs.append(new)
    return Plan(path=path, name=name, output=output, jobs=jobs, slurm=slurm)


def _list_field(check: _Checker, where: str, entry: dict, plural: str, singular: str, kind) -> list:
    if plural in entry and singular in entry:
        check.fail(where, f"give {plural} (a list) or {singular} (one), not both.")
    if singular in entry:
        values = [entry[singular]]
    else:
        values = entry.get(plural, [None])
        if not isinstance(values, list) or not values:
            check.fail(f"{where}.{plural}", f"{values!r}: a non-empty list.")
    for value in values:
        if value is not None and not kind(value):
            check.fail(f"{where}.{plural if plural in entry else singular}", f"{value!r} is not {kind.__doc__}.")
    return values


def _prompt(value) -> bool:
    """a non-empty text (leave it out, or null, for no prompt)"""
    return isinstance(value, str) and bool(value.strip())


def _seed(value) -> bool:
    """a whole number >= 0"""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _edit_jobs(check, label, index, entry, defaults, edit, root, output, check_paths) -> List[Job]:
    name = edit.get("name", f"edit{index}")
    if not isinstance(name, str) or not SAFE_NAME.match(name):
        check.fail(f"{label}.name", f"{name!r}: letters, digits, '.', '_' and '-' only (it names the job folders).")
    for required in REQUIRED:
        if entry.get(required) is None:
            check.fail(label, f"no {required} (give it here or under defaults).")
    base = check.folder(f"{label}.base", entry["base"], root)
    data = check.folder(f"{label}.data", entry["data"], root)
    sketches = check.folder(f"{label}.sketches", entry["sketches"], root)
    if check_paths:
        if not (base / "config.yml").is_file() and not (base.parent / "config.yml").is_file():
            check.fail(f"{label}.base", f"{base}: no config.yml there; give a trained run folder "
                                        "(outputs/<scene>/nerfacto/<timestamp>).")
        if not data.exists():
            check.fail(f"{label}.data", f"{data}: no such file or folder (the base's data).")
        if not (sketches / "sketches.json").is_file():
            check.fail(f"{label}.sketches", f"{sketches}: no sketches.json there (a sketch set: sked-sketch writes one).")
    preset = entry.get("preset", "sked")
    if preset not in PRESETS:
        check.fail(f"{label}.preset", f"{preset!r}: one of {', '.join(PRESETS)}.")
    flags = merged_flags(check.tokens("defaults.flags", defaults.get("flags")),
                         check.tokens(f"{label}.flags", edit.get("flags")))
    for token in flags:
        flag = token.split("=")[0]
        if flag in SET_BY_PLAN:
            field_name = SET_BY_PLAN[flag]
            check.fail(f"{label}.flags", f"{flag} is not for the flags: " + (
                f"the plan sets it from {field_name}." if field_name else "a plan's jobs are new edits (or resumed by "
                                                                          "sked-batch itself)."))
    dataparser = check.tokens(f"{label}.dataparser", entry.get("dataparser", "nerfstudio-data"))
    if not dataparser or dataparser[0].startswith("-"):
        check.fail(f"{label}.dataparser", f"{' '.join(dataparser)!r}: the base's dataparser subcommand first "
                                          "(nerfstudio-data, instant-ngp-data, ...), then its flags.")
    eval_value = entry.get("eval", True)
    if eval_value is False:
        eval_flags = None
    elif eval_value is True:
        eval_flags = ()
    else:
        eval_flags = check.tokens(f"{label}.eval", eval_value)
    prompts = _list_field(check, label, entry, "prompts", "prompt", _prompt)
    seeds = _list_field(check, label, entry, "seeds", "seed", _seed)
    jobs = []
    for prompt in prompts:
        for seed in seeds:
            job_name = name + (f"-{slug(prompt)}" if prompt is not None else "") + (f"-s{seed}" if seed is not None else "")
            jobs.append(Job(name=job_name, edit=name, prompt=prompt, seed=seed, preset=preset, base=base, data=data,
                            sketches=sketches, flags=flags, dataparser=dataparser, eval_flags=eval_flags, output=output))
    return jobs
