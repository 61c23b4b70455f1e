"""Resuming an edit: the saved run's config.yml is the edit; the command line may change only where and how it runs.

`ns-train sked --load-dir <edit run>` parses into a full config whose every unset flag holds the preset's
default (Stable Diffusion without a prompt, 10,000 iterations at 128 px): used as is, it would carve
instead of continuing the edit. So the saved config is taken whole, and of what the user typed (a value
that differs from the preset's default, or a flag named on the `ns-train` command line) only the
RESUME_SETTABLE settings apply; any other typed value that differs from the saved edit is refused.
"""

from __future__ import annotations

import copy
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path, PurePath
from typing import Dict, Iterator, Optional, Tuple

from nerfstudio.utils.rich_utils import CONSOLE

from sked_ns.engine.run_home import carry_home
from sked_ns.errors import SkedUserError, warn

RESUME_SETTABLE = (
    "output_dir", "experiment_name", "project_name", "max_num_iterations", "steps_per_save",
    "steps_per_eval_batch", "steps_per_eval_image", "steps_per_eval_all_images", "save_only_latest_checkpoint",
    "vis", "viewer", "logging", "machine", "data", "pipeline.datamanager.data", "pipeline.datamanager.dataparser",
    "pipeline.model.eval_num_rays_per_chunk",
    "pipeline.model.field_chunk",  # memory, not results (the same gradients): chosen anew for the device it resumes on
)
"""Where and how the resumed edit runs (and its data, whose frame is checked): the command line may change these."""
DATA_SETTINGS = ("data", "pipeline.datamanager.data", "pipeline.datamanager.dataparser")
"""Typed data replace the saved ones whole, as for a new edit (nerfstudio prefers the --data alias to the dataparser's)."""
RUN_FIELDS = ("timestamp", "load_dir", "load_step", "load_checkpoint", "load_config", "progressive")
"""How this command was started, not part of the edit: this run's own, never compared with the saved edit's."""
SETTINGS_SINCE = {
    "pipeline.datamanager.edit_fill": (0.0, "0.2"),
    "pipeline.model.guidance.sampling": ("pixel-centre", "0.2"),
    "pipeline.model.base_proposal_grid": (0, "0.6"),
    "pipeline.model.nerf_edit_field": ("full-copy", "0.7"),
}
"""Settings added after edits were saved, each with the value that continues such an edit as it ran and the last
sked_ns version without it: a config.yml without the setting would otherwise read the new default."""
BASE_SHAPED = ("pipeline.model",)
"""Configs whose class follows from the base (nerfacto, instant-ngp or splatfacto), not from a subcommand: the
preset's class parsed here is no change, and each typed setting in them is compared on its own."""
ALIASES = {"sketches": "pipeline.model.sketches", "prompt": "pipeline.model.prompt"}
"""Top-level flags that stand for a model setting."""
MISSING = object()


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def flat_settings(node, path: str = "") -> Iterator[Tuple[str, object]]:
    """(dotted path, value) for every setting of a config; a nested config also yields its type (a subcommand)."""
    if is_dataclass(node) and not isinstance(node, type):
        if path:
            yield path, type(node)
        for item in fields(node):
            if item.name != "_target":  # follows from the type
                yield from flat_settings(getattr(node, item.name, None), _join(path, item.name))
    elif isinstance(node, dict):
        for key, value in node.items():
            yield from flat_settings(value, _join(path, str(key)))
    else:
        yield path, node


def get_setting(config, path: str):
    node = config
    for name in path.split("."):
        node = node.get(name, MISSING) if isinstance(node, dict) else getattr(node, name, MISSING)
        if node is MISSING:
            return MISSING
    return node


def set_setting(config, path: str, value) -> None:
    *parents, name = path.split(".")
    node = config
    for parent in parents:
        node = node[parent] if isinstance(node, dict) else getattr(node, parent)
    if isinstance(node, dict):
        node[name] = value
    else:
        setattr(node, name, value)


def same_setting(a, b) -> bool:
    """Equal as settings: paths by where they point, lists and tuples alike."""
    if isinstance(a, PurePath) or isinstance(b, PurePath):
        return a is not None and b is not None and Path(a).expanduser().resolve() == Path(b).expanduser().resolve()
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_setting(x, y) for x, y in zip(a, b))
    try:
        return bool(a == b)
    except Exception:  # e.g. arrays
        return repr(a) == repr(b)


def flag(path: str) -> str:
    """A setting as the user types it: `pipeline.model.lambda_pres` -> `--pipeline.model.lambda-pres`."""
    return "--" + path.replace("_", "-")


def command_line_paths(config, argv=None) -> set:
    """Settings named on the `ns-train` command line, so a typed value equal to the preset's default counts too."""
    argv = sys.argv if argv is None else argv
    if not argv or Path(argv[0]).name != "ns-train":
        return set()
    named = {token[2:].split("=")[0].replace("-", "_") for token in argv[1:] if token.startswith("--")}
    named |= {token.split(":")[0].replace("-", "_") for token in argv[1:] if ":" in token and not token.startswith("-")}
    return {path for path, _ in flat_settings(config) if path in named}


def typed_settings(config, default, argv=None) -> Dict[str, object]:
    """What the command line set: the settings that differ from the preset's `default`, or that it names."""
    defaults = dict(flat_settings(default))
    named = command_line_paths(config, argv)
    return {path: value for path, value in flat_settings(config)
            if path in named or not same_setting(defaults.get(path, MISSING), value)}


def _under(path: str, names) -> bool:
    return any(path == name or path.startswith(name + ".") for name in names)


def _settable(path: str) -> bool:
    return _under(path, RESUME_SETTABLE + RUN_FIELDS)


def _derived(path: str) -> bool:
    """The learning-rate schedules' length (resolve_edit sets it from --max-num-iterations), and the edit's copy of its
    base (set when a run folder's config.yml is first written; an older edit has none)."""
    return (path.startswith("optimizers.") and path.endswith(".scheduler.max_steps")) or \
        path in ("pipeline.model.base_kept", "pipeline.model.base_digest")


def _show(value) -> str:
    return value.__name__ if isinstance(value, type) else "(unset)" if value is MISSING else repr(value)


def changed_subcommand(config, saved, path: str):
    """The outermost config on `path` of another type (subcommand) than in the saved edit, or None."""
    parts = path.split(".")
    for end in range(1, len(parts) + 1):
        node = ".".join(parts[:end])
        here = get_setting(config, node)
        if is_dataclass(here) and node not in BASE_SHAPED and type(here) is not type(get_setting(saved, node)):
            return node
    return None


def _owner(saved, path: str) -> str:
    """The class of the innermost config on `path` that the saved edit has (its model for a model setting)."""
    parts = path.split(".")
    for end in range(len(parts) - 1, 0, -1):
        node = get_setting(saved, ".".join(parts[:end]))
        if is_dataclass(node):
            return type(node).__name__
    return type(saved).__name__


def refused_changes(typed: Dict[str, object], config, saved) -> list:
    """Typed settings outside RESUME_SETTABLE that differ from the saved edit, as the user types them."""
    changes, reported = [], set()
    aliased = {ALIASES[path] for path in typed if path in ALIASES}  # said as the user typed it (--sketches)
    for path, value in sorted(typed.items()):
        if _settable(path) or _derived(path) or path in aliased:
            continue
        node = changed_subcommand(config, saved, path)
        if node is not None:  # a subcommand changed: said once, not with each of its settings
            if node not in reported:
                reported.add(node)
                before = get_setting(saved, node)
                changes.append(f"{node.replace('_', '-')} (a subcommand): {type(get_setting(config, node)).__name__} "
                               f"here, {_show(before if before is MISSING else type(before))} in the saved edit")
            continue
        before = get_setting(saved, ALIASES.get(path, path))
        if isinstance(value, type) and is_dataclass(before):
            before = type(before)  # a subcommand's node stands for its type
        if before is MISSING:  # e.g. a NeRF's setting typed for a splat edit
            changes.append(f"{flag(path)}: {_show(value)} here; the saved edit's {_owner(saved, path)} has no such "
                           "setting")
        elif not same_setting(value, before):
            changes.append(f"{flag(path)}: {_show(value)} here, {_show(before)} in the saved edit")
    return changes


def settings_saved_before(saved) -> Dict[str, object]:
    """Fill in (in place) the SETTINGS_SINCE that `saved`, read from an older config.yml, lacks; returns them."""
    filled = {}
    for path, (value, _) in SETTINGS_SINCE.items():
        *parents, name = path.split(".")
        node = get_setting(saved, ".".join(parents))
        # Loaded from yaml, a config's __dict__ holds what the file had; a field of another class (SD guidance) is not ours.
        if is_dataclass(node) and name in {item.name for item in fields(node)} and name not in vars(node):
            setattr(node, name, value)
            filled[path] = value
    return filled


def resumed_config(config, saved, default, run_dir: Path, argv=None, checkpoint: Optional[Path] = None) -> None:
    """Make `config` the `saved` edit's config (in place), with the settable settings typed on this command line;
    `checkpoint`: the one resumed, whose representation the model must be built as before its optimisers are."""
    for path, value in settings_saved_before(saved).items():
        CONSOLE.print(f"{run_dir / 'config.yml'} predates {flag(path)} (sked_ns {SETTINGS_SINCE[path][1]} or older): continuing with "
                      f"{_show(value)}, as it ran")
    typed = typed_settings(config, default, argv)
    changes = refused_changes(typed, config, saved)
    if changes:
        raise SkedUserError(
            f"--load-dir {run_dir}: resuming continues the saved edit ({run_dir / 'config.yml'}), so these settings "
            "cannot change:\n  " + "\n  ".join(changes) + "\nLeave them out to continue the edit, or add "
            "--progressive True to edit its result again with new settings."
        )
    kept = {path: copy.deepcopy(get_setting(config, path)) for path in typed if _settable(path)}
    if any(_under(path, DATA_SETTINGS) for path in typed):
        kept.update({path: copy.deepcopy(get_setting(config, path)) for path in DATA_SETTINGS})
    kept.update({name: getattr(config, name) for name in RUN_FIELDS if hasattr(config, name)})
    method = config.method_name
    for item in fields(saved):
        if hasattr(config, item.name):
            setattr(config, item.name, copy.deepcopy(getattr(saved, item.name)))
    for path in sorted(kept):  # a subcommand's node before its own settings
        set_setting(config, path, kept[path])
    carry_home(config, saved, typed)
    keep_sked_method(config, method, run_dir)
    if checkpoint is not None:
        keep_saved_representation(config.pipeline.model, checkpoint)


def keep_saved_representation(model, checkpoint: Path) -> None:
    """A local edit saved as a residual (0.8's "local") under a config.yml that says "local" resumes as one, and a
    local field saved without its hull proposal (0.9) resumes without one: its optimiser state is what it trained."""
    from sked_ns.method.frozen_base import read_model_state
    from sked_ns.models.nerf.edited_base import is_saved_residual
    from sked_ns.models.nerf.local_field import LOCAL, LOCAL_RESIDUAL

    if getattr(model, "nerf_edit_field", None) != LOCAL:
        return
    state = read_model_state(checkpoint)
    if is_saved_residual(state):
        CONSOLE.print(f"{checkpoint}: saved as a residual on its base's outputs; continuing as "
                      "--pipeline.model.nerf-edit-field local-residual, as it ran")
        model.nerf_edit_field = LOCAL_RESIDUAL
    elif any(key.startswith("local_field.") for key in state):
        saved = lambda module: any(key.startswith(module + ".") for key in state)  # noqa: E731
        if getattr(model, "hull_proposal_grid", 0) > 0 and not saved("hull_proposal"):
            CONSOLE.print(f"{checkpoint}: saved without a learned hull proposal (0.9); continuing with "
                          "--pipeline.model.hull-proposal-grid 0, as it ran")
            model.hull_proposal_grid = 0
        if getattr(model, "colour_residual", False) and not saved("colour_residual"):
            CONSOLE.print(f"{checkpoint}: saved without a colour residual (0.9); continuing with "
                          "--pipeline.model.colour-residual False, as it ran")
            model.colour_residual = False


def keep_sked_method(config, typed_method: str, run_dir: Path) -> None:
    """A saved method_name that is no SKED method (a typo in an edited copy of config.yml) would name the new run's
    method folder and a method no ns-train command knows: the edit is resumed as the method typed, said in one line."""
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    sked = sorted(name for name, method in methods.items() if type(method).__module__.startswith("sked_ns."))
    if config.method_name not in sked:
        warn(f"{run_dir / 'config.yml'}: method_name {config.method_name!r} is no SKED method "
             f"({', '.join(sked)}); resuming the edit as {typed_method}, the method typed.")
        config.method_name = typed_method


def preset_config(method_name: str):
    """A fresh copy of the preset `ns-train <method_name>` starts from (the `sked` one for any other name), from
    nerfstudio's method registry (where engine/presets.py registers them)."""
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    return copy.deepcopy(methods[method_name if method_name in methods and method_name.startswith("sked") else "sked"])
