"""An edit whose data moved after it trained: ns-render, ns-viewer and ns-export open it as it was (they need no
photo), a read of a photo says where it was, Ctrl-C ends an edit's viewer in one line, and a resume says which words
give the data's new place, words that resume it."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro
import yaml
from session_helpers import terminal_sigint

from sked_ns.engine.edit_run import edit_config, resume_config, run_edit
from sked_ns.errors import SkedFileNotFoundError

NS_VIEWER = Path(sys.executable).parent / "ns-viewer"


def _eval_setup(run: Path, mode: str):
    """nerfstudio's loader behind ns-render ("inference") and ns-viewer ("test")."""
    from nerfstudio.utils.eval_utils import eval_setup

    return eval_setup(run / "config.yml", test_mode=mode)[1]


def _render(pipeline, pose: torch.Tensor) -> torch.Tensor:
    from nerfstudio.cameras.cameras import Cameras

    camera = Cameras(camera_to_worlds=pose[None], fx=20.0, fy=20.0, cx=12.0, cy=12.0, width=24, height=24)
    with torch.no_grad():
        return pipeline.model.get_outputs_for_camera(camera)["rgb"]


def _ns_render(run: Path, pose: torch.Tensor, out: Path) -> np.ndarray:
    """`ns-render camera-path` of one camera, as images; the rendered image."""
    from nerfstudio.scripts.render import RenderCameraPath

    if shutil.which("ffmpeg") is None:
        pytest.skip("ns-render needs ffmpeg")
    path = out.parent / f"{out.name}.json"
    c2w = torch.cat([pose, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]).flatten().tolist()
    path.write_text(json.dumps({"camera_type": "perspective", "render_height": 24, "render_width": 24, "seconds": 1,
                                "camera_path": [{"camera_to_world": c2w, "fov": 50, "aspect": 1}]}))
    RenderCameraPath(load_config=run / "config.yml", camera_path_filename=path, output_path=out,
                     output_format="images", image_format="png").main()
    import cv2

    return cv2.imread(str(next(out.glob("*.png"))))


@pytest.fixture(scope="module")
def moved(scene, tmp_path_factory):
    """A finished edit of a copy of the demo data, rendered, then its data moved away."""
    root = tmp_path_factory.mktemp("moved data")
    data = root / "my data"
    shutil.copytree(scene["data"], data)
    config = edit_config(scene["base"], data, scene["sketches"], root / "edits", iterations=2, steps_per_save=1,
                         guidance_resolution=16, silhouette_resolution=16)
    run = run_edit(config).base_dir
    pipeline = _eval_setup(run, "inference")
    pose = pipeline.datamanager.train_dataset.cameras.camera_to_worlds[0]
    before = {"render": _render(pipeline, pose), "ns-render": _ns_render(run, pose, root / "render-before"),
              "train": pipeline.datamanager.train_dataset.cameras, "eval": pipeline.datamanager.eval_dataset.cameras}
    new = root / "moved to"
    data.rename(new)
    return {"run": run, "old": data, "new": new, "pose": pose, "before": before, "root": root}


@pytest.mark.parametrize("mode", ["inference", "test"])  # ns-render, ns-export; ns-viewer
def test_an_edit_whose_data_moved_opens_and_renders_as_before(moved, mode):
    pipeline = _eval_setup(moved["run"], mode)
    assert torch.equal(_render(pipeline, moved["pose"]), moved["before"]["render"])
    datamanager = pipeline.datamanager
    for split, dataset in (("train", datamanager.train_dataset), ("eval", datamanager.eval_dataset)):
        cameras = moved["before"][split]
        assert len(dataset) == len(cameras) and torch.equal(dataset.cameras.camera_to_worlds, cameras.camera_to_worlds)
        assert torch.equal(dataset.cameras.fx, cameras.fx) and torch.equal(dataset.cameras.width, cameras.width)
    # What nerfstudio's viewer draws on each training camera's frustum: a blank picture of the camera's size.
    item = datamanager.train_dataset[0]
    assert item["image"].shape == (int(datamanager.train_dataset.cameras.height[0]),
                                   int(datamanager.train_dataset.cameras.width[0]), 3)
    assert torch.all(item["image"] == 0.5)
    # A photo is never made up: reading one (sked-eval's, ns-eval's ground truth) says where the data was.
    photo = datamanager.eval_dataset.image_filenames[0]
    with pytest.raises(SkedFileNotFoundError, match=rf"^{photo}: the edit's photos are no longer there \(its data "
                                                    rf"{moved['old']} moved"):
        datamanager.eval_dataset.get_image_float32(0)
    with pytest.raises(SkedFileNotFoundError, match="photos are no longer there"):
        datamanager.train_dataset.get_image_float32(0)


def test_ns_render_of_an_edit_whose_data_moved_renders_the_same_image(moved):
    after = _ns_render(moved["run"], moved["pose"], moved["root"] / "render-after")
    assert np.array_equal(after, moved["before"]["ns-render"])


def test_ns_export_of_an_edit_whose_data_moved_samples_its_training_cameras(moved):
    from nerfstudio.exporter.exporter_utils import generate_point_cloud

    pipeline = _eval_setup(moved["run"], "test")  # as ns-export pointcloud and poisson load it
    rays, batch = pipeline.datamanager.next_train(0)
    cameras, (image, row, column) = pipeline.datamanager.train_dataset.cameras, batch["indices"].T
    assert torch.allclose(rays.origins, cameras.camera_to_worlds[image, :, 3], atol=1e-6)
    assert bool((row < cameras.height[image, 0]).all() and (column < cameras.width[image, 0]).all())
    cloud = generate_point_cloud(pipeline, num_points=64, remove_outliers=False, reorient_normals=False,
                                 estimate_normals=False, rgb_output_name="rgb", depth_output_name="depth",
                                 normal_output_name=None)
    assert len(cloud.points) >= 64 and np.isfinite(np.asarray(cloud.points)).all()


def test_an_edit_without_a_record_of_its_cameras_says_to_put_the_data_back(moved, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(moved["run"], run)
    (run / "base" / "views.pt").unlink()  # as an edit saved by an older sked_ns
    with pytest.raises(SkedFileNotFoundError, match=rf"^{moved['old']}: this edit's data is no longer there .*Put the "
                                                    "data back there"):
        _eval_setup(run, "inference")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _viewer_stopped_by_ctrl_c(config: Path) -> subprocess.CompletedProcess:
    """`ns-viewer --load-config CONFIG` until it serves, then Ctrl-C (SIGINT, as a terminal sends it)."""
    command = [str(NS_VIEWER), "--load-config", str(config), "--viewer.websocket-port", str(_free_port())]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "OMP_NUM_THREADS": "1"}, preexec_fn=terminal_sigint)
    shown = []
    for line in process.stdout:  # serving once nerfstudio's viewer has set up its writer
        shown.append(line)
        if "local writer" in line:
            break
    process.send_signal(signal.SIGINT)
    try:
        rest, errors = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        process.kill()
        rest, errors = process.communicate()
        pytest.fail(f"{command}: still running after Ctrl-C")
    return subprocess.CompletedProcess(command, process.returncode, "".join(shown) + rest, errors)


def test_ns_viewer_of_an_edit_whose_data_moved_serves_and_ends_in_one_line_on_ctrl_c(moved):
    result = _viewer_stopped_by_ctrl_c(moved["run"] / "config.yml")
    shown = " ".join(result.stdout.split())  # as rich wraps it
    assert "no longer there; it opens from its own record of its cameras" in shown, result.stdout[-3000:]
    assert "Traceback" not in result.stderr and result.stderr.rstrip().endswith("ns-viewer: stopped (Ctrl-C)."), \
        result.stderr[-3000:]
    assert result.returncode == -signal.SIGINT  # ended by the signal, as a shell expects of Ctrl-C


def test_only_an_edits_ns_viewer_ends_quietly(monkeypatch):
    """The hook is installed where an edit's pipeline is set up to render in an ns-viewer process, and nowhere else:
    a stock run's viewer (no SKED code runs in it) and every other command keep Python's traceback."""
    from sked_ns.engine.pipeline import end_viewer_quietly

    def shown(*exception):
        seen.append(exception[0])

    seen = []
    for command in ("ns-render", "ns-train", "sked-eval", "pytest"):
        monkeypatch.setattr(sys, "argv", [f"/venv/bin/{command}"])
        monkeypatch.setattr(sys, "excepthook", shown)
        end_viewer_quietly()
        assert sys.excepthook is shown, command
    monkeypatch.setattr(sys, "argv", ["/venv/bin/ns-viewer", "--load-config", "config.yml"])
    end_viewer_quietly()
    hook = sys.excepthook
    end_viewer_quietly()  # once per process, however many pipelines it sets up
    assert sys.excepthook is hook and hook is not shown
    hook(KeyboardInterrupt, KeyboardInterrupt(), None)
    hook(ValueError, ValueError("x"), None)
    assert seen == [ValueError]  # any other exception is shown as before


def test_a_resume_after_the_data_moved_says_where_it_was_and_the_words_that_resume_it(moved, monkeypatch):
    config = resume_config(moved["run"], iterations=3)
    with pytest.raises(SkedFileNotFoundError) as refused:
        config.print_to_terminal()  # nerfstudio's first hook: before anything is written
    said = str(refused.value)
    assert said.startswith(f"{moved['run']}: this edit's data is no longer at {moved['old']} (moved or deleted)")
    assert "no such file or folder" not in said and f"--data {moved['old']}" not in said
    words = said.split("`")[1]
    assert words == "nerfstudio-data --data NEW"
    # The command line with those words added, NEW the data's new place, as ns-train parses it.
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    argv = ["sked", "--load-dir", str(moved["run"]), "--max-num-iterations", "3",
            *[str(moved["new"]) if word == "NEW" else word for word in words.split()]]
    monkeypatch.setattr(sys, "argv", ["ns-train", *argv])
    resumed = run_edit(tyro.cli(AnnotatedBaseConfigUnion, args=argv)).base_dir
    assert resumed != moved["run"] and (resumed / "nerfstudio_models" / "step-000000002.ckpt").exists()
    saved = yaml.load((resumed / "config.yml").read_text(), Loader=yaml.Loader)
    assert Path(saved.pipeline.datamanager.dataparser.data) == moved["new"]


@pytest.mark.slow
def test_a_splat_edit_whose_data_moved_renders_as_before(tmp_path):
    import copy

    from nerfstudio.engine.optimizers import Optimizers

    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.demo.splat_base import SplatFit, save_run, splatfacto_config
    from sked_ns.method.options import without_lpips
    from sked_ns.sketches.sketch_set import save_sketch_set

    demo_scene.write_demo_dataset(tmp_path / "data", num_views=8, size=40)
    save_sketch_set(demo_scene.demo_sketch_set(size=40), tmp_path / "sketches")
    torch.manual_seed(0)
    config = splatfacto_config(tmp_path / "data", tmp_path / "runs", SplatFit(steps=1, num_gaussians=16))
    with without_lpips():
        pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    base = save_run(config, pipeline, Optimizers(copy.deepcopy(config.optimizers), pipeline.model.get_param_groups()), 0)
    run = run_edit(edit_config(base, tmp_path / "data", tmp_path / "sketches", tmp_path / "edits", iterations=2,
                               steps_per_save=1, guidance_resolution=16, silhouette_resolution=16)).base_dir
    pose = _eval_setup(run, "inference").datamanager.train_dataset.cameras.camera_to_worlds[0]
    before = _render(_eval_setup(run, "inference"), pose)
    (tmp_path / "data").rename(tmp_path / "moved")
    for mode in ("inference", "test"):
        assert torch.equal(_render(_eval_setup(run, mode), pose), before), mode
