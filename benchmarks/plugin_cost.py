"""What the plugin costs a command that never builds a SKED model.

    python benchmarks/plugin_cost.py [--runs 5] [--note TEXT] [--output benchmarks/results/plugin_cost.json]

Every `ns-*` command imports the plugin through nerfstudio's method registry. Measured in one run, as ratios
against the same environment with the plugin's entry points left out of nerfstudio's lookup (filtered in the child
process; nothing is uninstalled): the modules method discovery imports, `ns-train --help`'s wall and CPU time (the
two interleaved, medians of --runs each, both started through the same launcher), and the process-wide state
discovery leaves behind: import finders and path hooks, after-fork and exit callbacks, logging handlers and levels,
warnings filters, signal handlers, threads, environment variables, interpreter hooks and torch's settings.
Prints a table and writes JSON. tests/foundation/test_discovery_cost.py holds the plugin to the same probe.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Sequence

PLUGIN_PACKAGE = "sked_ns"
HEAVY = ("torchmetrics", "diffusers", "transformers", "matplotlib", "scipy")
"""Libraries that load with a model, an evaluation or a viewer, never with method discovery."""
MODULE_BUDGET = 100
"""Modules method discovery may import beyond nerfstudio's own discovery."""
HOOKS = ("meta_path", "path_hooks", "at_fork", "atexit", "threading_atexit", "logging", "warnings_filters",
         "signals", "threads", "environment", "interpreter_hooks", "torch_settings")
"""The process-wide state compared (`process_state`)."""
DOCUMENTED = {"meta_path": ["sked_ns.moved.MovedModuleFinder"]}
"""What docs/development.md says importing the plugin adds ("What the plugin changes outside SKED"); its user-error
excepthook and numpy's types in torch's safe list are reported apart (`excepthook`, `torch_safe_globals`)."""


def _without_plugin() -> None:
    """nerfstudio's entry-point lookup, less the plugin's (this process only)."""
    import importlib.metadata as metadata

    lookup = metadata.entry_points

    def entry_points(**selection):
        found = lookup(**selection)
        if "group" not in selection:
            return found
        return metadata.EntryPoints(entry for entry in found if entry.module.split(".")[0] != PLUGIN_PACKAGE)

    metadata.entry_points = entry_points


def _record_registrations() -> Dict[str, List[str]]:
    """Names of the callbacks registered from here on with os.register_at_fork, atexit and threading's exit list."""
    import atexit
    import threading

    seen: Dict[str, List[str]] = {"at_fork": [], "atexit": [], "threading_atexit": []}

    def recording(kind, register, names_of):
        def wrapper(*args, **kwargs):
            seen[kind].extend(_function(function) for function in names_of(args, kwargs))
            return register(*args, **kwargs)
        return wrapper

    if hasattr(os, "register_at_fork"):
        os.register_at_fork = recording("at_fork", os.register_at_fork, lambda args, kwargs: kwargs.values())
    atexit.register = recording("atexit", atexit.register, lambda args, kwargs: args[:1])
    if hasattr(threading, "_register_atexit"):
        threading._register_atexit = recording("threading_atexit", threading._register_atexit,
                                               lambda args, kwargs: args[:1])
    return seen


def _qualified(thing) -> str:
    kind = thing if isinstance(thing, type) else type(thing)
    return f"{kind.__module__}.{kind.__qualname__}"


def _function(function) -> str:
    owner = getattr(function, "__self__", None)  # a builtin method names its object (an lru_cache's cache_clear)
    if getattr(function, "__module__", None) is None and owner is not None and not isinstance(owner, type(sys)):
        return f"{_function(owner)}.{function.__name__}"
    if hasattr(function, "__qualname__"):
        return f"{getattr(function, '__module__', None)}.{function.__qualname__}"
    return re.sub(r" at 0x[0-9a-f]+", "", repr(function))  # a partial or a callable object: its address differs


def process_state(registered: Dict[str, List[str]]) -> Dict[str, object]:
    """This process's process-wide state, as comparable lists of strings (and the documented hooks apart)."""
    import atexit
    import logging
    import signal
    import threading
    import warnings

    import torch

    loggers = {"": logging.getLogger()}
    loggers.update((name, logger) for name, logger in logging.Logger.manager.loggerDict.items()
                   if isinstance(logger, logging.Logger))
    logging_state = [f"{name or 'root'}: {_qualified(handler)}" for name, logger in loggers.items()
                     for handler in logger.handlers]
    logging_state += [f"{name or 'root'}: level {logger.level}" for name, logger in loggers.items() if logger.level]
    logging_state += [f"{name or 'root'}: does not propagate" for name, logger in loggers.items() if not logger.propagate]
    signals = []
    for number in sorted(signal.valid_signals()):
        try:
            handler = signal.getsignal(number)
        except (OSError, ValueError):
            continue
        signals.append(f"{number}: {_function(handler) if callable(handler) else handler}")
    state: Dict[str, object] = {
        "modules": sorted(sys.modules),
        "meta_path": [_qualified(finder) for finder in sys.meta_path],
        "path_hooks": [_function(hook) for hook in sys.path_hooks],
        "at_fork": registered["at_fork"],
        # Registered before the probe started (or from C): the same on both sides, so an extra one is new.
        "atexit": registered["atexit"] + ["(unnamed)"] * (atexit._ncallbacks() - len(registered["atexit"])),
        "threading_atexit": registered["threading_atexit"],
        "logging": logging_state,
        "warnings_filters": [f"{action} {getattr(message, 'pattern', message)!r} {category.__name__} "
                             f"{getattr(module, 'pattern', module)!r} {line}"
                             for action, message, category, module, line in warnings.filters],
        "signals": signals,
        "threads": [thread.name for thread in threading.enumerate()],
        "environment": [f"{key}={value}" for key, value in sorted(os.environ.items())],
        "interpreter_hooks": [f"{name}: {_function(getattr(sys, name))}" for name in
                              ("displayhook", "unraisablehook", "breakpointhook")]
                             + [f"trace: {sys.gettrace()}", f"profile: {sys.getprofile()}",
                                f"threading.excepthook: {_function(threading.excepthook)}"],
        "torch_settings": [f"default dtype {torch.get_default_dtype()}", f"threads {torch.get_num_threads()}",
                           f"float32 matmul {torch.get_float32_matmul_precision()}",
                           f"cudnn benchmark {torch.backends.cudnn.benchmark}",
                           f"grad enabled {torch.is_grad_enabled()}"],
        "excepthook": _function(sys.excepthook),
        "torch_safe_globals": sorted(_function(item) if callable(item) else repr(item)
                                     for item in torch.serialization.get_safe_globals()),
    }
    return state


def _probe(plugin: bool, also_import: Sequence[str]) -> None:
    """Method discovery as `ns-*` commands run it, then this process's state as one JSON line."""
    if not plugin:
        _without_plugin()
    registered = _record_registrations()
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    for name in also_import:
        __import__(name)
    state = process_state(registered)
    state["methods"] = sorted(methods)
    print(json.dumps(state))


def discovery_state(plugin: bool, also_import: Sequence[str] = ()) -> Dict[str, object]:
    """`process_state` of a fresh process after method discovery, with or without the plugin's entry points;
    `also_import`: modules imported after discovery (to see that the probe sees what they bring)."""
    command = [sys.executable, str(Path(__file__).resolve()), "--probe", "plugin" if plugin else "stock",
               *[f"--also-import={name}" for name in also_import]]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    if result.returncode != 0:
        raise RuntimeError(f"the discovery probe failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def changes(stock: Dict[str, object], plugin: Dict[str, object]) -> Dict[str, Dict[str, List[str]]]:
    """Per list in the state: what the plugin's process has that the stock one lacks, and the reverse."""
    found = {}
    for key, value in plugin.items():
        if isinstance(value, list):
            ours, theirs = collections.Counter(value), collections.Counter(stock[key])
            found[key] = {"added": sorted((ours - theirs).elements()), "removed": sorted((theirs - ours).elements())}
    return found


def undocumented(found: Dict[str, Dict[str, List[str]]]) -> Dict[str, Dict[str, List[str]]]:
    """The hooks changed beyond docs/development.md's list."""
    return {key: {way: [item for item in found[key][way] if way != "added" or item not in DOCUMENTED.get(key, ())]
                  for way in ("added", "removed")} for key in HOOKS
            if any(item not in DOCUMENTED.get(key, ()) for item in found[key]["added"]) or found[key]["removed"]}


def heavy_imports(modules: Sequence[str]) -> Dict[str, int]:
    """Modules of HEAVY libraries among `modules`, counted per library."""
    return dict(collections.Counter(name.split(".")[0] for name in modules if name.split(".")[0] in HEAVY))


def _help_run(plugin: bool) -> None:
    """`ns-train --help`, started as its console script starts it."""
    if not plugin:
        _without_plugin()
    from nerfstudio.scripts.train import entrypoint

    sys.argv = ["ns-train", "--help"]
    entrypoint()


def _timed_help(plugin: bool) -> Dict[str, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    result = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--help-run",
                             "plugin" if plugin else "stock"], capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0 or ("sked" in result.stdout) != plugin:
        raise RuntimeError(f"ns-train --help ({'with' if plugin else 'without'} the plugin) failed or listed the "
                           f"wrong methods:\n{result.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu}


def _ratio(ours: float, theirs: float) -> float:
    return ours / theirs if theirs else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5, help="ns-train --help runs per side (interleaved)")
    parser.add_argument("--note", default="", help="added to the results' notes (e.g. what else loads the machine)")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "plugin_cost.json")
    parser.add_argument("--probe", choices=("plugin", "stock"), help=argparse.SUPPRESS)
    parser.add_argument("--also-import", action="append", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--help-run", choices=("plugin", "stock"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.probe:
        return _probe(args.probe == "plugin", args.also_import)
    if args.help_run:
        return _help_run(args.help_run == "plugin")
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    from sole_writer import claim

    claim("plugin_cost.py", args.output)
    load_before = os.getloadavg()
    stock, plugin = discovery_state(plugin=False), discovery_state(plugin=True)
    if not any(name.startswith("sked") for name in plugin["methods"]) or any(
            name.startswith("sked") for name in stock["methods"]):
        raise RuntimeError("the probe did not tell the plugin's methods apart: is sked_ns installed?")
    found = changes(stock, plugin)
    added = found["modules"]["added"]
    times = {"stock": [], "plugin": []}
    for run in range(args.runs):  # interleaved, each side first in turn: a load change hits both alike
        for side in (("stock", "plugin") if run % 2 == 0 else ("plugin", "stock")):
            times[side].append(_timed_help(side == "plugin"))
    median = {side: {key: statistics.median(run[key] for run in runs) for key in ("wall_s", "cpu_s")}
              for side, runs in times.items()}
    load_after = os.getloadavg()

    rows = [("modules after method discovery", len(stock["modules"]), len(plugin["modules"])),
            (f"ns-train --help wall (s, median of {args.runs})", median["stock"]["wall_s"], median["plugin"]["wall_s"]),
            (f"ns-train --help CPU (s, median of {args.runs})", median["stock"]["cpu_s"], median["plugin"]["cpu_s"])]
    print("| measure | stock nerfstudio | with the plugin | ratio |")
    print("|---|---|---|---|")
    for label, theirs, ours in rows:
        fmt = "{:d}" if isinstance(theirs, int) else "{:.2f}"
        print(f"| {label} | {fmt.format(theirs)} | {fmt.format(ours)} | {_ratio(ours, theirs):.3f} |")
    by_package = collections.Counter(name.split(".")[0] for name in added)
    print(f"| modules the plugin adds (budget {MODULE_BUDGET}) | | {len(added)} | "
          + ", ".join(f"{package} {count}" for package, count in by_package.most_common()) + " |")
    print(f"| heavy libraries among them | | {heavy_imports(added) or 'none'} | |")
    for key in HOOKS:
        change = found[key]
        text = "; ".join([f"+ {item}" for item in change["added"]] + [f"- {item}" for item in change["removed"]])
        documented = " (documented)" if change["added"] and all(item in DOCUMENTED.get(key, ()) for item in
                                                              change["added"]) and not change["removed"] else ""
        print(f"| {key.replace('_', ' ')} | | {text or 'unchanged'}{documented} | |")
    hook = "unchanged" if stock["excepthook"] == plugin["excepthook"] else plugin["excepthook"] + " (documented)"
    print(f"| sys.excepthook | | {hook} | |")
    safe = found["torch_safe_globals"]["added"]
    print(f"| torch safe globals | | + {len(safe)} (documented: numpy's) | |")

    results = {
        "benchmark": "plugin_cost",
        "command": f"python benchmarks/plugin_cost.py --runs {args.runs}",
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_average_1_5_15_min": {"before": load_before, "after": load_after}},
        "notes": " ".join(filter(None, [
            "Stock: the same environment with the plugin's entry points filtered out of nerfstudio's lookup in the "
            "child process. ns-train --help on both sides is started through this script's launcher (the console "
            "script's entry point, with --help), so the ratio is the plugin's share.", args.note])),
        "discovery": {
            "modules": {"stock": len(stock["modules"]), "plugin": len(plugin["modules"]), "added": len(added),
                        "budget": MODULE_BUDGET, "added_by_package": dict(by_package.most_common()),
                        "heavy": heavy_imports(added), "added_names": added},
            "methods": {"stock": len(stock["methods"]), "plugin": len(plugin["methods"])},
            "state_changes": {key: found[key] for key in HOOKS},
            "undocumented_changes": undocumented(found),
            "excepthook": {"stock": stock["excepthook"], "plugin": plugin["excepthook"]},
            "torch_safe_globals_added": safe,
        },
        "ns_train_help": {"runs": args.runs, "median": median,
                          "ratio": {key: _ratio(median["plugin"][key], median["stock"][key]) for key in ("wall_s", "cpu_s")},
                          "each": times},
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
