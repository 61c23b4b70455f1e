"""What a rerun of `sked-demo` picks up where the last one stopped, in the folder it owns (`--output`).

- The fitted base, when its record (`base/<kind>.json`) says it was fitted with the same settings from the same
  photos and its checkpoint still hashes to what the fit wrote; else the base is fitted again from nothing.
- The edit with the same settings (`edits/demo.json` keeps each edit's chain of runs): continued from the latest run's
  last intact checkpoint, as `ns-train sked --load-dir <run>` resumes it (a new run beside it), or taken as it is
  when it is done; the runs a continuation replaces are removed once it ends, so one run of each edit is left.

Ctrl-C anywhere in the demo ends in `DemoInterrupted`: where it stopped, and what the next run will reuse.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

from sked_ns.atomic import write_text_atomically

EDIT_RECORD = "demo.json"
"""In the demo's `edits/` folder: each edit's settings and its chain of runs, oldest first."""


class DemoInterrupted(KeyboardInterrupt):
    """Ctrl-C in the demo: the message says where it stopped and what running the demo again reuses."""


def file_digest(*paths: Path) -> str:
    digest = hashlib.sha256()
    for path in paths:
        with open(path, "rb") as file:
            for block in iter(lambda: file.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def data_digest(data: Path) -> str:
    """The demo dataset's cameras and image names: a base fitted to another dataset is not reused (its pixels may
    differ in the last bit with the thread count, which changes no fit)."""
    return file_digest(Path(data) / "transforms.json")


def _read(path: Path) -> Optional[dict]:
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # missing, or cut short: nothing is reused from it
    return record if isinstance(record, dict) else None


EXPERIMENTS = {"nerfacto": "demo-base", "splatfacto": "demo-base-splat"}
"""The experiment folder each kind of demo base is saved in (base.py, splat_base.py), under `<output>/base/`."""


def base_folder(output: Path, kind: str) -> Path:
    """The `kind` base's experiment folder: all of it is the fit's, and is removed before fitting again."""
    return Path(output) / "base" / EXPERIMENTS[kind]


def _base_record(output: Path, kind: str) -> Path:
    return Path(output) / "base" / f"{kind}.json"


def reusable_base(output: Path, kind: str, settings: dict) -> Optional[Path]:
    """The run folder of a base fitted with `settings` and intact since, or None."""
    record = _read(_base_record(output, kind))
    if record is None or record.get("settings") != settings:
        return None
    run = Path(output) / record.get("run", "")
    checkpoint = run / "nerfstudio_models" / record.get("checkpoint", "")
    if not all(path.is_file() for path in (run / "config.yml", run / "dataparser_transforms.json", checkpoint)):
        return None
    if len(list(checkpoint.parent.glob("step-*.ckpt"))) != 1 or file_digest(checkpoint) != record.get("sha256"):
        return None  # changed since the fit: nerfstudio would load another checkpoint, or this one damaged
    return run


def forget_base(output: Path, kind: str) -> None:
    """Before fitting again: no record (a fit cut short is never reused) and none of the old fit's files."""
    folder = base_folder(output, kind)
    _base_record(output, kind).unlink(missing_ok=True)
    shutil.rmtree(folder, ignore_errors=True)


def record_base(output: Path, kind: str, settings: dict, run: Path) -> str:
    """Written once the fit is saved whole; returns the checkpoint's digest (an edit's record names its base by it)."""
    checkpoint = next((run / "nerfstudio_models").glob("step-*.ckpt"))
    digest = file_digest(checkpoint)
    record = {"settings": settings, "run": str(run.relative_to(output)), "checkpoint": checkpoint.name, "sha256": digest}
    write_text_atomically(_base_record(output, kind), json.dumps(record, indent=2))
    return digest


def base_digest(output: Path, kind: str) -> str:
    return (_read(_base_record(output, kind)) or {}).get("sha256", "")


@dataclass
class EditPlan:
    """What the demo does for its edit: start one, continue `run` from `step`, or take `run` as done."""

    run: Optional[Path] = None
    step: Optional[int] = None
    done: bool = False
    chain: List[Path] = field(default_factory=list)
    """This edit's runs so far, oldest first: the ones a continuation replaces."""

    def describe(self, iterations: int) -> str:
        if self.run is None:
            return f"the edit ({iterations} iterations)"
        if self.done:
            return f"the edit, done already in {self.run} (the same settings): taken as it is"
        return f"the edit, continued from its checkpoint at step {self.step} in {self.run} to {iterations} iterations"


def _last_checkpoint(run: Path):
    """The run's latest intact checkpoint and its total length, or None (it stopped before its first)."""
    from sked_ns.engine.base_scene import checkpoint_step, resolve_base
    from sked_ns.errors import SkedUserError

    try:
        scene = resolve_base(run)
    except (SkedUserError, OSError):
        return None
    return checkpoint_step(scene.checkpoint), int(scene.config.max_num_iterations)


def plan_edit(edits: Path, settings: dict, iterations: int) -> EditPlan:
    """Continue the latest run of the edit with `settings` that saved a checkpoint, when it is short of `iterations`;
    take it when it is done at exactly `iterations`; else start anew."""
    chain = [edits / name for name in _recorded_runs(edits, settings) if (edits / name).is_dir()]
    for run in reversed(chain):
        found = _last_checkpoint(run)
        if found is None:
            continue
        step, total = found
        if step + 1 < iterations:
            return EditPlan(run, step, chain=chain)
        if step + 1 >= total == iterations:
            return EditPlan(run, step, done=True, chain=chain)
        break  # longer than asked: a new edit of this length, the longer one kept as it is
    else:
        return EditPlan(chain=chain)  # none saved a checkpoint: start again, and drop what they left
    return EditPlan()


def _entries(edits: Path) -> List[dict]:
    entries = (_read(edits / EDIT_RECORD) or {}).get("edits", [])
    return [entry for entry in entries if isinstance(entry, dict)] if isinstance(entries, list) else []


def _recorded_runs(edits: Path, settings: dict) -> List[str]:
    runs = next((entry.get("runs") for entry in _entries(edits) if entry.get("settings") == settings), None)
    return [run for run in runs if isinstance(run, str)] if isinstance(runs, list) else []


def record_runs(edits: Path, settings: dict, runs: List[Path]) -> None:
    """The edit with `settings` is now `runs` (oldest first), before the newest starts writing."""
    entries = [entry for entry in _entries(edits) if entry.get("settings") != settings]
    entries.append({"settings": settings, "runs": [str(Path(run).relative_to(edits)) for run in runs]})
    write_text_atomically(edits / EDIT_RECORD, json.dumps({"edits": entries}, indent=2))


def drop_replaced(edits: Path, settings: dict, final: Path, chain: List[Path]) -> None:
    """The edit ended in `final`: the runs it continued (or restarted) are removed, and it alone is recorded."""
    record_runs(edits, settings, [final])
    for run in chain:
        if run != final and Path(edits) in run.parents:
            shutil.rmtree(run, ignore_errors=True)
