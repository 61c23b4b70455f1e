"""The representations SKED edits: the one place that tells them apart.

Each row names, for bases of one nerfstudio model config type, the SKED model config that edits them, how it
renders (ray bundles, or whole cameras), and its optimiser groups when they are not the presets' NeRF groups.
The SKED classes are named by import path and loaded on demand, so reading a row imports no model. Every
question "which representation is this?" (the base reader, the trainer, the renderers, the pipeline) asks here.

Adding a representation: a folder under models/ with its SKED model config (a subclass of the base's config and
`SkedOptions`, declaring `EDIT_OWNED`) and model (a subclass of the base's model and `SkedEdit`, with its hooks),
and one row in REPRESENTATIONS (docs/development.md lists the hooks).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Dict, Literal, Optional, Tuple

from nerfstudio.models.instant_ngp import InstantNGPModelConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.models.splatfacto import SplatfactoModelConfig

from sked_ns.method.options import SkedOptions


def _load(path: str):
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class Representation:
    name: str
    """The base kind, as messages and sked-eval name it."""
    base_config: type
    """nerfstudio's model config type of bases of this kind (subclasses included: nerfacto-big, splatfacto-big)."""
    sked_config: str
    """`module:Class` of the SKED model config that edits such a base."""
    renders: Literal["rays", "cameras"]
    """What the model renders at once: ray bundles (NeRFs) or whole cameras (Gaussian splats)."""
    optimizers: Optional[str] = None
    """`module:function(iterations, options) -> optimizers` where the presets' NeRF groups do not fit; None keeps them."""
    stock_render_needs_cuda: bool = False
    """nerfstudio renders a stock run of this kind with CUDA kernels only (instant-ngp's nerfacc marching); SKED's
    own commands install kernels that build here (models/nerf/nerfacc_backend.py)."""
    samples_from_proposals: bool = False
    """Samples per ray follow the config's proposal and field counts (nerfacto); else the scene does (a grid)."""
    seeds_new_gaussians: bool = False
    """An edit starts new Gaussians in the sketches' hull (`num_seeds`): the memory plan counts them."""

    def sked_config_class(self) -> type:
        return _load(self.sked_config)

    def edit_optimizers(self, iterations: int, options: SkedOptions) -> Optional[Dict[str, Dict]]:
        return None if self.optimizers is None else _load(self.optimizers)(iterations, options)


REPRESENTATIONS: Tuple[Representation, ...] = (  # the most specific config type first
    Representation("splatfacto", SplatfactoModelConfig, "sked_ns.models.splat.model:SkedSplatModelConfig", "cameras",
                   optimizers="sked_ns.models.splat.rates:splat_optimizers", seeds_new_gaussians=True),
    Representation("instant-ngp", InstantNGPModelConfig, "sked_ns.models.nerf.ngp:SkedNGPModelConfig", "rays",
                   stock_render_needs_cuda=True),
    Representation("nerfacto", NerfactoModelConfig, "sked_ns.models.nerf.nerfacto:SkedNerfactoModelConfig", "rays",
                   samples_from_proposals=True),
)


def representation_of(model_config) -> Optional[Representation]:
    """The row for a base's (or an edit's) model config, by type; None for a kind SKED cannot edit."""
    for row in REPRESENTATIONS:
        if isinstance(model_config, row.base_config):
            return row
    return None


def representation_named(name: str) -> Representation:
    """The row called `name` (nerfacto, instant-ngp, splatfacto)."""
    for row in REPRESENTATIONS:
        if row.name == name:
            return row
    raise KeyError(f"no representation {name!r}; known: {[row.name for row in REPRESENTATIONS]}")


def family(model_config) -> Optional[str]:
    """nerfacto, instant-ngp, splatfacto, or sked (an earlier edit, whatever its representation); None otherwise."""
    if isinstance(model_config, SkedOptions):
        return "sked"
    row = representation_of(model_config)
    return None if row is None else row.name


def renders_cameras(model) -> bool:
    """Whether a built model (SKED or stock) renders whole cameras rather than ray bundles."""
    row = representation_of(getattr(model, "config", None))
    return row is not None and row.renders == "cameras"


def is_sked_model(model) -> bool:
    return isinstance(getattr(model, "config", None), SkedOptions)

