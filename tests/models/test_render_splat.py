"""sked-eval's renders of a plain splatfacto run (`--base <splatfacto run>`) off CUDA."""

from __future__ import annotations

import pytest
import torch
from test_splat_model import edit_pipeline, splat_scene  # noqa: F401  (the tiny saved splatfacto run)

from sked_ns.evaluation.render import load_pipeline, render_camera

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def test_a_plain_splatfacto_run_renders_on_the_cpu_as_the_edits_frozen_copy_of_it(splat_scene, tmp_path):  # noqa: F811
    stock = load_pipeline(splat_scene["base"]).model  # nerfstudio's SplatfactoModel, as ns-train splatfacto saved it
    _, pipeline = edit_pipeline(splat_scene, tmp_path)
    camera = pipeline.datamanager.train_dataset.cameras[0:1]
    rendered = render_camera(stock, camera)
    frozen = render_camera(pipeline.model, camera, base=True)  # the same Gaussians through the edit's own path
    assert rendered["accumulation"].amax() > 0.5  # the sphere is in view
    assert torch.allclose(rendered["accumulation"], frozen["accumulation"], atol=1e-4)
    assert torch.allclose(rendered["rgb"], frozen["rgb"], atol=1e-4)
