"""sked-eval on a capture: novel views at the photos the base held out, scored against those photos."""

from __future__ import annotations

import pytest
import torch

from sked_ns.demo.scenes import capture
from sked_ns.evaluation import novel_views
from sked_ns.evaluation.evaluate import EVAL_SPLIT, novel_summary

COUNT, HEIGHT = 12, 48


@pytest.fixture(scope="module")
def eval_split(tmp_path_factory):
    """The capture-like scene's eval split, as a base's datamanager holds it (no model needed to read it)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.data.datasets.base_dataset import InputDataset

    data = capture.write_benchmark("bust", tmp_path_factory.mktemp("capture"), count=COUNT, height=HEIGHT,
                                   sketch_size=HEIGHT)["data"]
    outputs = NerfstudioDataParserConfig(data=data, center_method="focus").setup().get_dataparser_outputs("val")
    return InputDataset(outputs)


def test_the_eval_split_of_a_capture_is_its_held_out_photos_through_its_lens(eval_split):
    from types import SimpleNamespace

    pipeline = SimpleNamespace(datamanager=SimpleNamespace(eval_dataset=eval_split))
    views = novel_views.eval_split_views(pipeline, HEIGHT * 2, background=(0.0, 0.0, 0.0))
    assert [view.name for view in views] == [path.name for path in eval_split.image_filenames] and views
    for index, view in enumerate(views):
        camera = view.camera
        assert int(camera.height) == HEIGHT * 2 and int(camera.width) < int(camera.height)  # portrait, as taken
        assert torch.equal(camera.distortion_params, eval_split.cameras.distortion_params[index])  # the lens kept
        assert camera.distortion_params.abs().sum() > 0
        assert view.ground_truth.shape == (int(camera.height), int(camera.width), 3)
        photo = eval_split.get_image_float32(index)
        assert (view.ground_truth[::2, ::2] - photo).abs().mean() < 0.05  # the photo itself, upsampled


def test_kept_pixels_are_scored_against_the_photos_for_the_edit_and_its_base(monkeypatch):
    """PSNR and SSIM against the photo, edit and base apart: a base that misses its photos is the base's figure."""
    import sked_ns.evaluation.render as render

    generator = torch.Generator().manual_seed(0)
    photo = torch.rand(32, 24, 3, generator=generator)
    blurred = (photo + 0.1 * torch.randn(32, 24, 3, generator=generator)).clamp(0, 1)  # the base misses its photo

    def fake_render(model, camera, base=False):
        # The edit here matches the photo exactly; the base renders the noisy copy. Everything is kept.
        rgb = blurred if base else photo
        return {"rgb": rgb, "accumulation": torch.ones(32, 24), "preservation_weight": torch.ones(32, 24)}

    monkeypatch.setattr(render, "render_camera", fake_render)
    entry = novel_views.score_view(None, novel_views.NovelView(None, "photo", ground_truth=photo))["entry"]
    assert entry["ssim_keep_gt"] == pytest.approx(1.0, abs=1e-4) and entry["ssim_keep_gt_base"] < 0.95
    assert entry["psnr_keep_gt"] > entry["psnr_keep_gt_base"] + 10
    line = novel_summary({"views": [entry], "cameras": EVAL_SPLIT, "mean": {k: v for k, v in entry.items()
                                                                            if isinstance(v, float)}})
    assert "kept vs photos" in line and "SSIM kept vs photos 1 (base" in line
