"""What sked-sketch reads from its base: the frame it saves a set in, and how much it renders at once on a CPU."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from sked_ns.drawing.sketch_viewer import CPU_RAYS_PER_CHUNK, load_base, sketch_frame
from sked_ns.engine.moved_data import KeptViewsConfig
from sked_ns.sketches.sketch_set import DataparserTransform


def test_an_edit_as_the_base_is_sketched_in_the_frame_it_recorded():
    """An edit loaded after its data moved reads its cameras from its own record (a KeptViews dataparser, which
    knows nothing of the data's transforms.json): the data -> model frame is the one the edit recorded (the
    datamanager's), not the run transform alone, which starts from the COLMAP frame for a processed capture."""
    run = np.array([[0.0, 1.0, 0.0, 0.2], [1.0, 0.0, 0.0, -0.1], [0.0, 0.0, -1.0, 0.3]])
    recorded = DataparserTransform(np.array([[1.0, 0.0, 0.0, 0.2], [0.0, 1.0, 0.0, -0.1], [0.0, 0.0, 1.0, 0.3]]), 0.25)
    outputs = SimpleNamespace(dataparser_transform=torch.from_numpy(run).float(), dataparser_scale=0.5)
    datamanager = SimpleNamespace(train_dataparser_outputs=outputs, data_frame_transform=recorded,
                                  config=SimpleNamespace(dataparser=KeptViewsConfig(views={})))
    frame = sketch_frame(SimpleNamespace(datamanager=datamanager))
    assert np.allclose(frame.transform, recorded.transform) and frame.scale == recorded.scale


def test_a_stock_base_is_sketched_in_its_run_transform_when_the_data_file_moves_nothing(tmp_path):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    (tmp_path / "transforms.json").write_text('{"frames": []}')
    run = np.array([[0.0, 1.0, 0.0, 0.2], [1.0, 0.0, 0.0, -0.1], [0.0, 0.0, -1.0, 0.3]])
    outputs = SimpleNamespace(dataparser_transform=torch.from_numpy(run).float(), dataparser_scale=0.5)
    datamanager = SimpleNamespace(train_dataparser_outputs=outputs,
                                  config=SimpleNamespace(dataparser=NerfstudioDataParserConfig(data=tmp_path)))
    frame = sketch_frame(SimpleNamespace(datamanager=datamanager))
    assert np.allclose(frame.transform, run, atol=1e-6) and frame.scale == 0.5


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_a_cpu_renders_the_base_in_small_chunks(tmp_path, monkeypatch, device):
    """nerfacto's default chunk holds GBs of samples per render on a CPU (a default-size capture base's captured view
    ran out of memory beside the viewer's own render); on a GPU the base's own chunk stays."""
    import sked_ns.evaluation.render as render

    recorded = DataparserTransform(np.eye(4)[:3], 1.0)
    pipeline = SimpleNamespace(model=SimpleNamespace(config=SimpleNamespace(eval_num_rays_per_chunk=1 << 15)),
                               datamanager=SimpleNamespace(data_frame_transform=recorded))
    monkeypatch.setattr(render, "load_pipeline", lambda *args, **kwargs: pipeline)
    _, loaded, _ = load_base(tmp_path, device)
    assert loaded.model.config.eval_num_rays_per_chunk == (CPU_RAYS_PER_CHUNK if device == "cpu" else 1 << 15)
    assert CPU_RAYS_PER_CHUNK < 1 << 15
