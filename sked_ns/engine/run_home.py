"""An edit's run folder opens as itself wherever it is: moved, copied, archived and unpacked elsewhere.

nerfstudio's config.yml names the run's place by the paths it was written with (`output_dir`, and through it every
checkpoint), and an edit's config names its own copies of its base and sketch set by absolute path. A copied folder
read as written would load the original's files. So when an edit's config.yml is read from a file, the config is
re-rooted at the folder it was read from: its run folder becomes that folder (checkpoints, and a resume's new run
beside it), and every path it names inside its old run folder names the same file inside this one. Paths outside
the run (the base run, the data) are left as they are.

The file being read is found on the reader's stack: nerfstudio's `eval_setup(config_path)` (ns-render, ns-export,
ns-viewer, ns-eval), `ns-train --load-config` and sked_ns's own readers all hold it as a local `Path` (or on a
config's `load_config`) while yaml builds the config. A config built from yaml text with no file behind it is left as
written.
"""

from __future__ import annotations

import sys
from dataclasses import fields, is_dataclass
from pathlib import Path, PurePath
from typing import Iterator, Optional

HOME = "_sked_home"
"""The config's attribute naming its timestamp and the folder it was read from, when that folder is not laid out as
nerfstudio lays out runs (not a field: never saved in config.yml)."""
WRITTEN_IN = "_sked_written_in"
"""The config's attribute naming the run folder it was written in, when it was read from another."""
CONFIG_SUFFIXES = (".yml", ".yaml")


def config_file_being_read(timestamp: str) -> Optional[Path]:
    """The config file being read with yaml: a Path to an existing .yml file whose text names this run's
    timestamp, held by the reader (the first frame outside yaml and the config class) or by up to two callers."""
    frame = sys._getframe(1)
    while frame is not None and _module(frame) in _LOADING:
        frame = frame.f_back
    for _ in range(3):
        if frame is None:
            return None
        for candidate in _candidates(frame.f_locals):
            if timestamp in _text(candidate):
                return candidate
        frame = frame.f_back
    return None


_LOADING = {"yaml", __name__, "sked_ns.engine.trainer"}
"""Modules on the stack between the reader and here, besides yaml's."""


def _module(frame) -> str:
    name = frame.f_globals.get("__name__", "")
    return "yaml" if name == "yaml" or name.startswith("yaml.") else name


def _candidates(local_values: dict) -> Iterator[Path]:
    for value in local_values.values():
        for path in (value, getattr(value, "load_config", None)):
            if isinstance(path, PurePath) and path.suffix in CONFIG_SUFFIXES:
                yield Path(path)


def _text(path: Path) -> str:
    try:
        return path.read_text() if path.is_file() else ""
    except (OSError, UnicodeDecodeError):
        return ""


def saved_run_folder(config) -> Path:
    """The run folder config.yml was written in, as nerfstudio derives it."""
    return Path(f"{config.output_dir}/{config.experiment_name}/{config.method_name}/{config.timestamp}")


def inside(path: Path, folder: Path) -> Optional[PurePath]:
    """`path` relative to `folder`, or None. A relative `folder` (nerfstudio's default `outputs/...`, relative to
    wherever training ran) is found as a run of whole components in an absolute `path`."""
    try:
        return path.relative_to(folder)
    except ValueError:
        pass
    if folder.is_absolute() or not path.is_absolute():
        return None
    parts, want = path.parts, folder.parts
    for start in range(len(parts) - len(want), 0, -1):
        if parts[start:start + len(want)] == want:
            return PurePath(*parts[start + len(want):])
    return None


def rehome(config, run_dir: Path) -> None:
    """Re-root `config` (read from `run_dir`/config.yml) at `run_dir`, in place: see the module's docstring."""
    run_dir = Path(run_dir).absolute()
    saved = saved_run_folder(config)
    if saved.absolute() == run_dir:
        return
    object.__setattr__(config, WRITTEN_IN, saved)
    for node, name, path in _path_settings(config):
        relative = inside(path, saved)
        if relative is not None:
            setattr(node, name, run_dir / relative)
    if run_dir.parent.name == config.method_name:  # laid out as nerfstudio lays out runs: say it in its own fields
        config.output_dir, config.experiment_name = run_dir.parent.parent.parent, run_dir.parent.parent.name
    else:
        object.__setattr__(config, HOME, (config.timestamp, run_dir))


def home_run_folder(config) -> Optional[Path]:
    """The run folder of a config re-rooted at a folder not laid out as nerfstudio's output_dir/experiment/method/
    timestamp (otherwise output_dir and experiment_name say it): that folder for its own run, a folder beside it for
    another timestamp (a resume's new run)."""
    home = vars(config).get(HOME)
    if home is None:
        return None
    timestamp, run_dir = home
    return run_dir if config.timestamp == timestamp else run_dir.parent / config.timestamp


def written_in(config) -> Optional[Path]:
    """The run folder a re-rooted config was written in (None: read where it was written)."""
    return vars(config).get(WRITTEN_IN)


def carry_home(config, saved, typed_paths) -> None:
    """A resume of `saved` writes its new run beside the folder it was given, unless --output-dir or
    --experiment-name were typed."""
    home = vars(saved).get(HOME)
    if home is not None and not {"output_dir", "experiment_name"} & set(typed_paths):
        object.__setattr__(config, HOME, home)


def _path_settings(node, depth: int = 0):
    """(config, field name, Path) for every Path-valued setting of a nested config."""
    if not is_dataclass(node) or isinstance(node, type) or depth > 8:
        return
    for item in fields(node):
        value = getattr(node, item.name, None)
        if isinstance(value, PurePath):
            yield node, item.name, Path(value)
        elif is_dataclass(value):
            yield from _path_settings(value, depth + 1)
