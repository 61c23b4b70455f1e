"""Old module paths of sked_ns, kept importable: runs saved by v0.3 name classes by where they lived then.

A run's config.yml records each config class by module path (`!!python/object:sked_ns.trainer.SkedTrainerConfig`),
and nerfstudio loads it with yaml's unsafe loader, which imports that path. The finder below answers only for
the old `sked_ns.<module>` names listed in MOVED, with the module that now holds the same code; every other import
goes past it untouched.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from typing import Dict

MOVED: Dict[str, str] = {
    "sked_ns.sketches": "sked_ns.sketches.sketch_set",  # the old module became the package: see find_spec
    "sked_ns.cameras": "sked_ns.sketches.cameras",
    "sked_ns.data_frame": "sked_ns.sketches.data_frame",
    "sked_ns.random_views": "sked_ns.sketches.random_views",
    "sked_ns.options": "sked_ns.method.options",
    "sked_ns.validation": "sked_ns.method.validation",
    "sked_ns.preservation": "sked_ns.method.preservation",
    "sked_ns.losses": "sked_ns.method.losses",
    "sked_ns.edit_box": "sked_ns.method.edit_box",
    "sked_ns.photo_anchor": "sked_ns.method.photo_anchor",
    "sked_ns.frozen_base": "sked_ns.method.frozen_base",
    "sked_ns.edit": "sked_ns.method.edit",
    "sked_ns.hull_carving": "sked_ns.method.hull_carving",
    "sked_ns.core": "sked_ns.models.nerf.field_edit",
    "sked_ns.nerfacto_model": "sked_ns.models.nerf.nerfacto",
    "sked_ns.ngp_model": "sked_ns.models.nerf.ngp",
    "sked_ns.occupancy": "sked_ns.models.nerf.occupancy",
    "sked_ns.held_field": "sked_ns.models.nerf.held_field",
    "sked_ns.colour_residual": "sked_ns.models.nerf.colour_residual",
    "sked_ns.nerfacc_kernels": "sked_ns.models.nerf.nerfacc_kernels",
    "sked_ns.nerfacc_backend": "sked_ns.models.nerf.nerfacc_backend",
    "sked_ns.splat_model": "sked_ns.models.splat.model",
    "sked_ns.splat_render": "sked_ns.models.splat.rasterize",
    "sked_ns.base_scene": "sked_ns.engine.base_scene",
    "sked_ns.config": "sked_ns.engine.presets",
    "sked_ns.trainer": "sked_ns.engine.trainer",
    "sked_ns.pipeline": "sked_ns.engine.pipeline",
    "sked_ns.datamanager": "sked_ns.engine.datamanager",
    "sked_ns.resume": "sked_ns.engine.resume",
    "sked_ns.edit_run": "sked_ns.engine.edit_run",
    "sked_ns.safe_step": "sked_ns.engine.safe_step",
    "sked_ns.edit_inputs": "sked_ns.engine.edit_inputs",
    "sked_ns.render": "sked_ns.evaluation.render",
    "sked_ns.metrics": "sked_ns.evaluation.metrics",
    "sked_ns.clip_score": "sked_ns.evaluation.clip_score",
    "sked_ns.novel_views": "sked_ns.evaluation.novel_views",
    "sked_ns.evaluate": "sked_ns.evaluation.evaluate",
    "sked_ns.sketch_viewer": "sked_ns.drawing.sketch_viewer",
    "sked_ns.sketching": "sked_ns.drawing.sketching",
    "sked_ns.hull_check": "sked_ns.drawing.hull_check",
    "sked_ns.authors_import": "sked_ns.drawing.authors_import",
    "sked_ns.demo.scene": "sked_ns.demo.scenes.sphere",
    "sked_ns.demo.benchmark_scenes": "sked_ns.demo.scenes.catalogue",
    "sked_ns.demo.unbounded_scenes": "sked_ns.demo.scenes.unbounded",
}


class _Alias(importlib.abc.Loader):
    """Loads an old name as the module now holding its code (one module object under both names)."""

    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        return importlib.import_module(self.target)

    def exec_module(self, module) -> None:
        pass  # already executed under its new name


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        if new is None or fullname == "sked_ns.sketches":
            return None  # sked_ns.sketches is a real package now; its __init__ answers the old module's names
        return importlib.util.spec_from_loader(fullname, _Alias(new))


def install() -> None:
    """Answer the old names first (idempotent); other finders never see a sked_ns name they could not find."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())
