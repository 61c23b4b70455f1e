"""models/registry.py: one row per representation, each naming loadable classes and hooks."""

from __future__ import annotations

import pytest
from nerfstudio.configs.method_configs import method_configs

from sked_ns.method.options import SkedOptions
from sked_ns.models.registry import REPRESENTATIONS, family, renders_cameras, representation_of


@pytest.mark.parametrize("row", REPRESENTATIONS, ids=lambda row: row.name)
def test_every_row_names_a_sked_config_of_its_base_kind_with_its_own_fields(row):
    config = row.sked_config_class()
    assert issubclass(config, row.base_config) and issubclass(config, SkedOptions)
    assert representation_of(config()) is row, "a SKED config is found by its base's row"
    assert SkedOptions.EDIT_OWNED <= config.EDIT_OWNED
    assert family(config()) == "sked"


def test_splats_bring_their_optimisers_and_nerfs_keep_the_presets():
    splat = representation_of(method_configs["splatfacto"].pipeline.model)
    groups = splat.edit_optimizers(100, splat.sked_config_class()())
    assert set(groups) == {"means", "scales", "quats", "features_dc", "features_rest", "opacities"}
    nerf = representation_of(method_configs["nerfacto"].pipeline.model)
    assert nerf.edit_optimizers(100, nerf.sked_config_class()()) is None


@pytest.mark.parametrize("method, kind, cameras", [("nerfacto", "nerfacto", False), ("nerfacto-big", "nerfacto", False),
                                                   ("instant-ngp", "instant-ngp", False),
                                                   ("splatfacto-big", "splatfacto", True), ("vanilla-nerf", None, False)])
def test_bases_are_told_apart_by_config_type(method, kind, cameras):
    config = method_configs[method].pipeline.model
    assert family(config) == kind

    class Built:  # a model as nerfstudio builds it: it holds its config
        pass

    model = Built()
    model.config = config
    assert renders_cameras(model) is cameras
