"""The edit's own copy of its base: what it needs of the base run, kept in its own run folder.

An edit is its changes to one base checkpoint, read whenever the edit is loaded (the frozen base is not saved in the
edit's checkpoints), in the frame of the base's run. So when an edit starts, its run folder gets `<edit run>/base/`:

- `step-N.ckpt`: the base checkpoint's step and model weights (its optimiser state dropped: nothing reads it), a file
  of the edit's own, so no later write to the base run (a base trained on or resumed to the same step rewrites its
  checkpoint in place) can change what the edit renders. It is a hard link to a read-only copy in the output folder's
  `.sked-bases/`, named by its digest, so ten edits of one base hold its weights once on disk; a copy of the run
  folder copies the file itself. Its digest is in config.yml and checked whenever the edit loads;
- `base_config.yml` and `dataparser_transforms.json`: the base run's config and data frame, so the edit opens after
  its base run is moved or deleted (not named config.yml: the folder is not a run of its own);
- `base/`: when the base is itself an edit, that edit's own kept folder, nested (`keep_chain`).

Every later load reads this folder, never the base run. The sketch set, which shapes the edit's kept space whenever
it renders, is copied likewise into `<edit run>/sketches/` (where a session draws its own), and config.yml names
that copy. The files are written once, by the edit that starts.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import torch

from sked_ns.atomic import publish_atomically, write_atomically
from sked_ns.engine.drawn_sketches import SESSION_SKETCHES
from sked_ns.errors import SkedUserError
from sked_ns.method.frozen_base import KEPT_CONFIG, file_digest, kept_config

KEPT = "base"
"""The folder in the edit's run that holds its copy of the base."""
FRAME = "dataparser_transforms.json"
"""The base run's data frame (the name nerfstudio gives it)."""
STORE = ".sked-bases"
"""The folder under an output folder holding one read-only copy of each base's weights its edits link to."""


def keep_base(model, run_dir: Path, store: Path) -> None:
    """Copy what the edit reads of its base into `run_dir` and record the copy on the model config (`base_kept`, and
    its digest): from the base run for a new edit, from the interrupted run's copy for one resumed into a new folder.
    The weights are linked from `store` (`link_from_store`)."""
    if model.base_checkpoint is None:
        return
    folder = (Path(run_dir) / KEPT).absolute()
    kept = Path(model.base_kept) if model.base_kept is not None else None
    if kept is not None and kept.parent == folder and kept.exists():
        return  # this run's own copy, made when it started
    base_run = Path(model.base_checkpoint).parent.parent
    sources = {KEPT_CONFIG: base_run / "config.yml", FRAME: base_run / FRAME}
    checkpoint = Path(model.base_checkpoint)
    if kept is not None and kept.exists():  # resumed into a new folder: the interrupted run's copy is the base
        checkpoint = kept
        if kept_config(kept):
            sources = {name: kept.parent / name for name in sources}
    if not checkpoint.exists():
        return  # base_weights names it when the edit loads
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for target, source in sources.items():
            if source.exists():
                write_atomically(folder / target, lambda path, source=source: shutil.copyfile(source, path))
        for name in (KEPT, SESSION_SKETCHES):  # a base that is an edit: what it reads of its own run goes along
            keep_chain((kept.parent if checkpoint == kept else base_run) / name, folder / name)
        state = torch.load(checkpoint, map_location="cpu")
        weights = {"step": state.get("step", 0), "pipeline": state["pipeline"]}
        digest = link_from_store(weights, store, folder / checkpoint.name)
    except OSError as error:
        raise SkedUserError(f"{folder}: cannot keep the edit's copy of its base checkpoint {checkpoint} there "
                            f"({error.strerror or error}); the edit reads it whenever it is loaded. Free space "
                            "there, or pass another --output-dir.") from error
    model.base_kept, model.base_digest = folder / checkpoint.name, digest


def keep_chain(chain: Path, target: Path) -> None:
    """A base that is itself an edit loads with its own base (a splat edit saves only its changes): its kept folder
    goes along, nested, its files linked (never written in place), so the edit reads nothing outside its run."""
    if not chain.is_dir() or target.exists():
        return
    partial = target.with_name(f".{target.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(chain, partial, copy_function=link_or_copy)
    os.replace(partial, target)


def link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system, or one without hard links
        shutil.copyfile(source, target)


def link_from_store(weights: dict, store: Path, path: Path) -> str:
    """Write `weights` at `path` as a hard link to the store's read-only copy of them (added to the store if new), so
    edits of one base under one output folder share its bytes on disk; a plain copy where links are refused. Returns
    the weights file's digest, which every load checks (frozen_base.base_weights)."""
    store.mkdir(parents=True, exist_ok=True)
    handle, written = tempfile.mkstemp(prefix=".weights.", suffix=".partial", dir=store)
    os.close(handle)
    written = Path(written)
    try:
        with open(written, "wb") as file:  # through a file object: torch names the archive after a path it is given
            torch.save(weights, file)
        digest = file_digest(written)
        stored = store / f"{digest}.ckpt"
        if stored.exists() and file_digest(stored) == digest:
            written.unlink()
        else:  # new, or a damaged entry replaced whole
            written.chmod(0o444)  # never written in place: every edit linked to it would change
            publish_atomically(written, stored)
    finally:
        written.unlink(missing_ok=True)
    try:
        write_atomically(path, lambda partial: (os.unlink(partial), os.link(stored, partial)))
    except OSError:  # another file system, or one without hard links
        write_atomically(path, lambda partial: shutil.copyfile(stored, partial))
    return digest


def keep_sketches(model, run_dir: Path) -> None:
    """Save the sketch set the edit was given into `run_dir`'s `sketches/` and point the model config at it, so a
    sketch folder changed or removed afterwards changes nothing the edit renders."""
    from sked_ns.sketches.sketch_set import SKETCHES_JSON, load_sketch_set, save_sketch_set

    own = (Path(run_dir) / SESSION_SKETCHES).absolute()
    if model.sketches is None or Path(model.sketches).absolute() == own:
        return  # none yet, or drawn in this run's viewer
    if not (own / SKETCHES_JSON).exists():
        try:
            save_sketch_set(load_sketch_set(Path(model.sketches)), own)  # as loaded: what the edit trains on
        except OSError as error:
            raise SkedUserError(f"{own}: cannot keep the edit's copy of its sketch set {model.sketches} there "
                                f"({error.strerror or error}). Free space there, or pass another --output-dir.") \
                from error
    model.sketches = own
