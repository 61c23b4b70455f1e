"""Which distributions an offline GPU node needs besides its own torch/torchvision.

    python .ci/offline/lists.py imports runtime   # what ns-train sked (NeRF and splat bases), sked-eval, sked-sketch, sked-batch, ns-render import
    python .ci/offline/lists.py imports export    # the same plus ns-export
    python .ci/offline/lists.py lock              # rewrite runtime.txt / export.txt, pinned to this environment

`lock` also runs a tiny edit of each base kind in-process (benchmarks/gpu_check.py --size tiny),
so packages that are only imported while training are found. The node keeps what torch and
torchvision brought (numpy, pillow, sympy, jinja2, ...): they are never listed.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import re
import runpy
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
RUNTIME_MODULES = [
    "nerfstudio.scripts.train", "nerfstudio.configs.method_configs", "nerfstudio.viewer.viewer",
    "nerfstudio.scripts.viewer.run_viewer", "nerfstudio.scripts.render", "nerfstudio.utils.writer",
    "torch.utils.tensorboard", "sked_ns.engine.presets", "sked_ns.models.nerf.ngp", "sked_ns.guidance.stable_diffusion",
    "sked_ns.evaluation.evaluate", "sked_ns.evaluation.clip_score", "sked_ns.drawing.sketch_viewer", "sked_ns.demo.run", "sked_ns.drawing.authors_import",
    "sked_ns.models.splat.model", "sked_ns.models.splat.rasterize", "sked_ns.demo.splat_base", "sked_ns.batch.cli", "sked_ns.batch.report",
    "yaml",
    "diffusers.models.unets.unet_2d_condition", "diffusers.models.autoencoders.autoencoder_kl",
    "diffusers.schedulers.scheduling_ddpm", "transformers.models.clip.modeling_clip",
    "transformers.models.clip.tokenization_clip", "torchmetrics.image.lpip",
]
EXPORT_MODULES = ["nerfstudio.scripts.exporter"]
# Imported when present but optional (guarded imports), and never needed to train, evaluate or sketch.
OPTIONAL = {"ipython", "traitlets", "pysocks", "sked-ns"}
# Two distributions of one module: the node needs only the superset (both install `cv2`).
SUPERSEDED = {"opencv-python-headless": "opencv-contrib-python-headless"}


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(roots) -> set:
    """Distributions `roots` require (transitively, no extras), from this environment's metadata."""
    from packaging.requirements import Requirement

    installed = {normalise(d.metadata["Name"]): d for d in importlib.metadata.distributions()}
    seen, stack = set(), list(roots)
    while stack:
        name = stack.pop()
        if name in seen or name not in installed:
            continue
        seen.add(name)
        for line in installed[name].requires or []:
            requirement = Requirement(line)
            if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                stack.append(normalise(requirement.name))
    return seen


def node_provided() -> set:
    """What a node with a CUDA build of torch and torchvision already has."""
    return _closure(["torch", "torchvision"]) | {"torch", "torchvision"} | {
        normalise(d.metadata["Name"]) for d in importlib.metadata.distributions()
        if normalise(d.metadata["Name"]).startswith(("nvidia-", "cuda-"))
    }


def imported_distributions() -> set:
    owners = importlib.metadata.packages_distributions()
    stdlib = set(sys.stdlib_module_names)
    found = set()
    for name in list(sys.modules):
        top = name.split(".")[0]
        if top in stdlib or top.lstrip("_") in stdlib:
            continue
        found.update(normalise(owner) for owner in owners.get(top, []))
    return found


def needed(kind: str) -> set:
    for module in RUNTIME_MODULES + (EXPORT_MODULES if kind == "export" else []):
        importlib.import_module(module)
    return _drop_superseded(imported_distributions() - node_provided() - OPTIONAL)


def _drop_superseded(names: set) -> set:
    return {name for name in names if SUPERSEDED.get(name) not in names}


def read_list(path: Path) -> dict:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            pins[normalise(name)] = version
    return pins


def lock() -> None:
    runtime = needed("runtime")
    sys.argv = ["gpu_check.py", "--device", "cpu", "--size", "tiny", "--skip", "profile",
                "--output", str(Path("/tmp") / "sked_lock_gpu_check.json")]
    runpy.run_path(str(ROOT / "benchmarks" / "gpu_check.py"), run_name="__main__")
    runtime = _drop_superseded(runtime | imported_distributions() - node_provided() - OPTIONAL)
    export = needed("export") - runtime
    versions = {normalise(d.metadata["Name"]): d.version for d in importlib.metadata.distributions()}
    header = ("# Written by `python .ci/offline/lists.py lock` from a tested environment; the node keeps its own\n"
              "# torch, torchvision and what they brought (numpy, pillow, ...). Installed with --no-deps.\n")
    for name, names in (("runtime", runtime), ("export", export)):
        lines = [f"{n}=={versions[n]}" for n in sorted(names)]
        (HERE / f"{name}.txt").write_text(header + "\n".join(lines) + "\n")
        print(f"{name}.txt: {len(lines)} distributions")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python .ci/offline/lists.py", formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n", 1)[0], epilog=__doc__.split("\n\n", 1)[1])
    commands = parser.add_subparsers(dest="command", required=True, metavar="{imports,lock}")
    imports = commands.add_parser("imports", help="print the distributions the commands import (minutes: it "
                                  "imports nerfstudio, diffusers, transformers, ...)")
    imports.add_argument("kind", nargs="?", choices=("runtime", "export"), default="runtime",
                         help="runtime: ns-train sked, sked-eval, sked-sketch, sked-batch, ns-render, ns-viewer; "
                         "export: the same plus ns-export (default runtime)")
    commands.add_parser("lock", help="rewrite runtime.txt and export.txt, pinned to this environment (runs a tiny "
                        "edit of each base kind)")
    return parser.parse_args(argv)


if __name__ == "__main__":
    arguments = parse_args()
    if arguments.command == "lock":
        lock()
    else:
        for distribution in sorted(needed(arguments.kind)):
            print(distribution)
