"""The package's house: layers by role, each importing only layers below it, NeRF and splat models apart, no
circles, and every question "which representation?" answered by models/registry.py.

Every import counts, also those inside functions and under TYPE_CHECKING: a lazy import hides a cycle from
Python but not from a reader.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

PACKAGE = Path(__file__).resolve().parents[2] / "sked_ns"

LAYERS: List[Set[str]] = [
    # 0: what everything may use
    {"sked_ns", "sked_ns.errors", "sked_ns.atomic", "sked_ns.compat", "sked_ns.moved", "sked_ns.run_lock"},
    {"sked_ns.sketches"},  # 1: sketch sets, cameras, the data frame, random views
    {"sked_ns.guidance"},  # 2: what pulls the sketched region (Stable Diffusion, installed components)
    {"sked_ns.method"},  # 3: what SKED adds to any representation
    {"sked_ns.models"},  # 4: the representations and their registry
    {"sked_ns.engine"},  # 5: nerfstudio glue: presets, trainer, pipeline, datamanager, base scene, resume
    {"sked_ns.evaluation"},  # 6: rendering saved runs, metrics, sked-eval
    {"sked_ns.drawing"},  # 7: sked-sketch and its panel, the authors' importer
    {"sked_ns.session"},  # 8: ns-train sked's trainer and methods: sketch, edit and edit again in one viewer session
    {"sked_ns.batch"},  # 9: sked-batch
    {"sked_ns.demo"},  # 10: sked-demo and its analytic scenes
]
MAX_FLOORS = 10
MAX_LINES = 450
REPRESENTATION_TYPES = {"SplatfactoModel", "SplatfactoModelConfig", "NerfactoModel", "NerfactoModelConfig", "NGPModel",
                        "InstantNGPModelConfig", "SkedSplatModel", "SkedSplatModelConfig", "SkedNerfactoModel",
                        "SkedNerfactoModelConfig", "SkedNGPModel", "SkedNGPModelConfig"}


def module_paths() -> Dict[str, Path]:
    return {".".join(("sked_ns",) + path.relative_to(PACKAGE).with_suffix("").parts).removesuffix(".__init__"): path
            for path in PACKAGE.rglob("*.py")}


def import_graph() -> Dict[str, Set[str]]:
    """Module -> the sked_ns modules it imports anywhere in its source."""
    modules = module_paths()
    graph = {}
    for name, path in modules.items():
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module)
                imported |= {f"{node.module}.{alias.name}" for alias in node.names}
        graph[name] = {module for module in imported if module in modules and module != name}
    return graph


def layer(module: str) -> int:
    best, found = -1, None
    for index, roots in enumerate(LAYERS):
        for root in roots:
            if (module == root or module.startswith(root + ".")) and len(root) > best:
                best, found = len(root), index
    assert found is not None, f"{module} is in no layer: add its folder to LAYERS"
    return found


def upward_imports(graph: Dict[str, Set[str]]) -> List[str]:
    return sorted(f"{module} -> {imported}" for module, imports in graph.items() for imported in imports
                  if layer(imported) > layer(module) and not module.startswith(imported + "."))


def cycles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """Each strongly connected group of more than one module (Tarjan), a package's own __init__ excepted."""
    graph = {module: {m for m in imports if not module.startswith(m + ".")} for module, imports in graph.items()}
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def visit(module):
        index[module] = low[module] = counter[0]
        counter[0] += 1
        stack.append(module)
        on_stack.add(module)
        for other in graph[module]:
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in on_stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == module:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for module in graph:
        if module not in index:
            visit(module)
    return found


def folder_graph(graph: Dict[str, Set[str]]) -> Dict[str, Set[str]]:
    """Folder -> the folders its modules import: the house's floors as a reader walks them (the top-level modules
    are the folder `sked_ns`, the ground floor everything stands on)."""
    paths = module_paths()
    folder = lambda module: module if paths[module].name == "__init__.py" else module.rsplit(".", 1)[0]  # noqa: E731
    folders: Dict[str, Set[str]] = {}
    for module, imports in graph.items():
        here = folder(module)
        folders.setdefault(here, set()).update(
            folder(other) for other in imports if folder(other) != here and not here.startswith(folder(other) + "."))
    return folders


def floors(graph: Dict[str, Set[str]]) -> int:
    """The longest chain of imports between the nodes of `graph` (a node importing nothing is floor 1)."""
    depth: Dict[str, int] = {}

    def height(module):
        if module not in depth:
            depth[module] = 1 + max((height(other) for other in graph.get(module, ())), default=0)
        return depth[module]

    return max(height(module) for module in graph)


def test_the_graph_sees_every_kind_of_import():
    graph = import_graph()
    assert "sked_ns.sketches.sketch_set" in graph["sked_ns.method.edit_box"]  # top level
    assert "sked_ns.engine.viewer" in graph["sked_ns.engine.trainer"]  # inside a function
    assert "sked_ns.sketches.sketch_set" in graph["sked_ns.method.options"]  # under TYPE_CHECKING


def test_the_checks_can_fail():
    """The rules catch what they are for, on a made-up graph."""
    made_up = {"sked_ns.method.a": {"sked_ns.engine.b"}, "sked_ns.engine.b": {"sked_ns.method.a"}}
    assert upward_imports(made_up) == ["sked_ns.method.a -> sked_ns.engine.b"]
    assert cycles(made_up) == [["sked_ns.engine.b", "sked_ns.method.a"]]
    assert floors({"sked_ns.a": {"sked_ns.b"}, "sked_ns.b": {"sked_ns.c"}, "sked_ns.c": set()}) == 3


def test_every_module_is_in_a_layer_and_no_layer_imports_a_higher_one():
    graph = import_graph()
    for module in graph:
        layer(module)
    assert upward_imports(graph) == []


def test_nerf_and_splat_models_never_import_each_other():
    graph = import_graph()
    for module, imports in graph.items():
        for family, other in (("nerf", "splat"), ("splat", "nerf")):
            if module.startswith(f"sked_ns.models.{family}"):
                assert not {m for m in imports if m.startswith(f"sked_ns.models.{other}")}, module


def test_no_import_circles():
    assert cycles(import_graph()) == []


def test_import_floors_and_module_sizes_stay_small():
    assert floors(folder_graph(import_graph())) <= MAX_FLOORS
    long = {name: len(path.read_text().splitlines()) for name, path in module_paths().items()}
    assert {name: lines for name, lines in long.items() if lines > MAX_LINES} == {}


def test_only_the_registry_tells_representations_apart():
    """isinstance / issubclass against a representation's type lives in models/ (the registry and the models
    themselves); the demo builds its bases and is exempt."""
    offenders = []
    for name, path in module_paths().items():
        if name.startswith(("sked_ns.models", "sked_ns.demo")):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("isinstance", "issubclass"):
                kinds = node.args[1] if len(node.args) > 1 else None
                names = {getattr(n, "id", getattr(n, "attr", None)) for n in ast.walk(kinds)} if kinds else set()
                if names & REPRESENTATION_TYPES:
                    offenders.append(f"{name}:{node.lineno}")
    assert offenders == []


REPRESENTATION_NAMES = {"nerfacto", "instant-ngp", "splatfacto"}


def name_comparisons(source: str) -> list:
    """Lines comparing a value with a representation's name ("== 'splatfacto'", "in ('nerfacto', ...)")."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            constants = {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
            if constants & REPRESENTATION_NAMES:
                found.append(node.lineno)
    return found


def test_no_representation_is_told_apart_by_its_name_outside_the_registry():
    """`family == "instant-ngp"` is a registry question asked by name: it passes an isinstance guard. The registry
    answers it (a row's properties); the demo builds its bases by name, and an option's value may be a name."""
    assert name_comparisons("if kind == 'splatfacto': pass") == [1]  # the check can fail
    exempt = {"sked_ns.models.registry", "sked_ns.models.splat.rates"}  # rates: the option value "splatfacto"
    offenders = [f"{name}:{line}" for name, path in module_paths().items()
                 if name not in exempt and not name.startswith("sked_ns.demo")
                 for line in name_comparisons(path.read_text())]
    assert offenders == []
