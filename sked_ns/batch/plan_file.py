"""Reading a plan file: every field checked, each mistake an error naming the plan file, the entry and the field
(the format: plan.py)."""

from __future__ import annotations

import shlex
import tempfile
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from sked_ns.batch.plan import (
    EDIT_FIELDS,
    PLAN_FIELDS,
    PRESETS,
    REQUIRED,
    SAFE_NAME,
    SET_BY_PLAN,
    SLURM_FIELDS,
    SLURM_MEMORY,
    SLURM_TIME,
    Edit,
    Job,
    Jobs,
    Plan,
    merged_flags,
)
from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.guide import guide


def read_plan_file(path: Path) -> dict:
    if path.is_dir():
        raise SkedUserError(f"sked-batch {path}: a folder; pass the plan file (YAML or TOML) itself.")
    if not path.is_file():
        raise SkedFileNotFoundError(f"sked-batch {path}: no such plan file (a YAML or TOML file; see "
                                    f"{guide('batch.md')}).")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise SkedUserError(f"sked-batch {path}: cannot read the plan ({error}); a plan is a YAML or TOML text file.") \
            from error
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
        raise SkedUserError(f"{path}: a plan is a mapping with an `edits:` list (see {guide('batch.md')}).")
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
    """Read and check a plan; `check_paths`: the bases, data, sketch sets and the files `eval:` flags name exist
    (before submitting). Its jobs are counted from its lists, not made (see Jobs)."""
    path = Path(path).resolve()
    data, check = read_plan_file(path), _Checker(path)
    check.unknown("the plan", data, PLAN_FIELDS)
    root = path.parent
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not SAFE_NAME.match(name):
        check.fail("name", f"{name!r}: letters, digits, '.', '_' and '-' only (it names folders and Slurm jobs).")
    output = check.folder("output", data.get("output", f"outputs/{name}"), root)
    if output.exists() and not output.is_dir():
        check.fail("output", f"{output} is a file; the output is a folder the jobs' folders go in.")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        check.fail("defaults", "a mapping of edit fields (preset, flags, seeds, ...).")
    check.unknown("defaults", defaults, [f for f in EDIT_FIELDS if f != "name"])
    edits = data.get("edits")
    if not isinstance(edits, list) or not edits:
        check.fail("edits", f"a list of edits, each with base, data and sketches (see {guide('batch.md')}).")
    slurm = data.get("slurm") or {}
    if not isinstance(slurm, dict):
        check.fail("slurm", f"a mapping of {', '.join(SLURM_FIELDS)}.")
    check.unknown("slurm", slurm, SLURM_FIELDS)
    for key, value in slurm.items():
        problem = slurm_problem(key, value)
        if problem:
            check.fail(f"slurm.{key}", f"{value!r}: {problem}")

    checked: List[Edit] = []
    for index, edit in enumerate(edits):
        if not isinstance(edit, dict):
            check.fail(f"edits[{index}]", "an edit is a mapping with base, data, sketches, prompts, ...")
        label = f"edits[{index}]" + (f" ({edit['name']})" if isinstance(edit.get("name"), str) else "")
        check.unknown(label, edit, EDIT_FIELDS)
        checked.append(_edit(check, label, index, {**defaults, **edit}, defaults, edit, root, output, check_paths))
    _check_job_names(check, checked)
    return Plan(path=path, name=name, output=output, jobs=Jobs(checked), slurm=slurm)


def _check_job_names(check: _Checker, edits: List[Edit]) -> None:
    """Two jobs of one name would share a folder. A job's name is its edit's, its prompt's words and its seed
    (`-s<seed>`, read from the name's end), so within an edit distinct words and distinct seeds make distinct
    names and a sweep is checked from its lists; only a seedless job among seeded ones (its words may end as a
    seed does), and edits whose names overlap, are compared name by name."""
    for edit in edits:
        prompts, seeds = edit.parts
        for field_name, values, parts in (("prompts", edit.prompts, prompts), ("seeds", edit.seeds, seeds)):
            first: Dict[str, int] = {}
            for index, part in enumerate(parts):
                if part in first:
                    other = values[first[part]]
                    check.fail(f"{edit.label}.{field_name}", f"{values[index]!r} is listed twice." if other == values[index]
                               else f"{other!r} and {values[index]!r} make the same job name ({edit.name}{part}...): "
                                    "prompts must differ in the words of their first 40 characters.")
                first[part] = index
        if "" in seeds and len(seeds) > 1:
            _compare_names(check, edit, edit)
    for later, second in enumerate(edits):
        for first_edit in edits[:later]:
            a, b = sorted((first_edit.name, second.name), key=len)
            if a == b or b.startswith(a + "-"):
                _compare_names(check, first_edit, second)


def _compare_names(check: _Checker, first: Edit, second: Edit) -> None:
    seen = set() if first is second else set(first.names())
    for name in second.names():
        if name in seen:
            check.fail(second.label, f"job {name!r} is also made by {first.label}: give the edits different names "
                                     "(or prompts that differ in their words)." if first is not second else
                       f"job {name!r} is made twice (a prompt's words end as a seed's -s<seed> does): reword it.")
        if first is second:
            seen.add(name)


def slurm_problem(key: str, value) -> Optional[str]:
    """What a Slurm setting (the plan's `slurm:` or its flag) must be, when `value` is not that; else None."""
    whole = isinstance(value, int) and not isinstance(value, bool)
    if key in ("partition", "account"):
        ok = isinstance(value, str) and value.strip() and not any(c.isspace() for c in value)
        return None if ok else f"a Slurm {key} name."
    if key == "time":
        if whole:
            return ("write the time as a quoted string (\"4:00:00\", or \"240\" minutes): YAML reads an unquoted "
                    "4:00:00 as the number 14400, which Slurm would take as minutes.")
        return None if isinstance(value, str) and SLURM_TIME.match(value) else (
            "Slurm's time format, e.g. 4:00:00 (hours:minutes:seconds), 1-00:00:00 or 240 (minutes).")
    if key == "mem":
        ok = (whole and value > 0) or (isinstance(value, str) and SLURM_MEMORY.match(value))
        return None if ok else "memory per edit as Slurm writes it, e.g. 32G or 32000 (megabytes)."
    if key in ("gpus", "cpus_per_task", "max_parallel"):
        least = 0 if key == "gpus" else 1
        return None if whole and value >= least else f"a whole number >= {least}."
    if key == "sbatch_args":
        ok = isinstance(value, str) or (isinstance(value, list) and all(isinstance(v, str) for v in value))
        return None if ok else "sbatch options, a string or a list of strings (--qos=high)."
    return None


def output_problem(folder: Path) -> Optional[str]:
    """Why `folder` cannot be made or written in, found by trying in the nearest folder that exists (a probe file
    made and removed there: nothing is left, so a dry run may ask too); None: it can."""
    existing = Path(folder)
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is a file, not a folder."
    try:
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".sked-write-probe-"):
            pass
    except OSError as error:
        return f"cannot write in {existing} ({error.strerror or error})."
    return None


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


def _edit(check, label, index, entry, defaults, edit, root, output, check_paths) -> Edit:
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
    eval_flags = _eval_flags(check, f"{label}.eval", entry.get("eval", True), check_paths)
    prompts = _list_field(check, label, entry, "prompts", "prompt", _prompt)
    seeds = _list_field(check, label, entry, "seeds", "seed", _seed)
    template = Job(name=name, edit=name, prompt=None, seed=None, preset=preset, base=base, data=data, sketches=sketches,
                   flags=flags, dataparser=dataparser, eval_flags=eval_flags, output=output)
    return Edit(label=label, prompts=tuple(prompts), seeds=tuple(seeds), template=template)


def _eval_flags(check: _Checker, where: str, value, check_files: bool) -> Optional[Tuple[str, ...]]:
    """The `sked-eval` flags of `eval:` (None: no evaluation), read as sked-eval reads them, so a typo is refused
    now and not after the edit; `check_files`: the files they name exist."""
    if value is False:
        return None
    flags = () if value is True else check.tokens(where, value)
    if flags and check_files:
        from sked_ns.evaluation.eval_inputs import check_eval_flags

        try:
            check_eval_flags(flags)
        except SkedUserError as error:
            check.fail(where, f"{' '.join(flags)!r}: {error}")
    return flags
