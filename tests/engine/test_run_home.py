"""An edit's run folder opens as itself wherever it is: moved, or copied and the original changed or deleted, every
loader (sked_ns's, nerfstudio's eval_setup behind ns-render, ns-export and ns-viewer) reads the folder it is given,
and a resume writes beside it. Edits of one base under one output folder share one copy of its weights."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
import yaml

from sked_ns.engine.edit_run import edit_config, resume_config, run_edit
from sked_ns.engine.run_home import inside, rehome
from sked_ns.errors import SkedUserError
from sked_ns.evaluation.eval_inputs import edit_scene
from sked_ns.evaluation.render import load_pipeline, render_at
from sked_ns.sketches.sketch_set import load_sketch_set

ELSEWHERE = "copies of édits/my edit"
"""A folder name with a space and a non-ASCII character."""


def _tiny_edit(scene, base: Path, out: Path, iterations: int = 2) -> Path:
    config = edit_config(base, scene["data"], scene["sketches"], out, iterations=iterations, steps_per_save=1,
                         guidance_resolution=16, silhouette_resolution=16)
    return run_edit(config).base_dir


def _render(run: Path, view) -> torch.Tensor:
    return render_at(load_pipeline(run).model, view, 16)["rgb"]


def _eval_setup(config_path: Path, cwd: Path):
    """nerfstudio's loader for ns-render, ns-export and ns-viewer, run from `cwd`."""
    from nerfstudio.utils.eval_utils import eval_setup

    here = os.getcwd()
    os.chdir(cwd)
    try:
        return eval_setup(config_path, test_mode="inference")
    finally:
        os.chdir(here)


def _change_weights(checkpoint: Path, by: float) -> None:
    """Replace a checkpoint by one with every float weight moved (a new file: a linked one is left as it was)."""
    state = torch.load(checkpoint, map_location="cpu")
    for key, value in state["pipeline"].items():
        if torch.is_tensor(value) and value.is_floating_point():
            state["pipeline"][key] = value + by
    checkpoint.unlink()
    torch.save(state, checkpoint)


@pytest.fixture(scope="module")
def finished_edit(scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("home")
    return _tiny_edit(scene, scene["base"], root / "outputs"), root


def test_a_copied_edit_reads_its_own_files_and_resumes_beside_itself(scene, finished_edit, tmp_path):
    original, _ = finished_edit
    run = tmp_path / "outputs" / "edit" / "sked" / original.name
    shutil.copytree(original, run)  # a private original, to change and delete
    view = load_sketch_set(scene["sketches"]).views[0]
    before = _render(run, view)

    copy = tmp_path / ELSEWHERE
    shutil.copytree(run, copy)
    # The original changed or taken away every way a loader could read it: its edit, its base copy, its sketches.
    for checkpoint in (run / "nerfstudio_models").glob("*.ckpt"):
        _change_weights(checkpoint, 0.5)
    assert not torch.equal(_render(run, view), before)
    shutil.rmtree(run / "sketches")
    shutil.rmtree(run / "base")

    assert torch.equal(_render(copy, view), before)
    edit = edit_scene(copy)  # sked-eval's reader
    model = edit.model_config
    assert edit.run_dir == copy and inside(Path(model.base_kept), copy) and inside(Path(model.sketches), copy)
    config, pipeline, checkpoint, step = _eval_setup(copy / "config.yml", cwd=tmp_path.parent)
    assert Path(checkpoint).parent == copy / "nerfstudio_models" and step == 1
    assert config.get_base_dir() == copy and Path(pipeline.model.config.base_kept).parent == copy / "base"

    shutil.rmtree(tmp_path / "outputs")  # the original deleted
    assert torch.equal(_render(copy, view), before)
    resumed = run_edit(resume_config(copy, iterations=3)).base_dir
    assert resumed.parent == copy.parent and resumed != copy  # a new run beside the folder it was given
    assert (resumed / "nerfstudio_models" / "step-000000002.ckpt").exists()


def test_a_moved_edit_opens_where_it_is_now(scene, finished_edit, tmp_path):
    original, _ = finished_edit
    view = load_sketch_set(scene["sketches"]).views[0]
    before = _render(original, view)
    run = tmp_path / "outputs" / "edit" / "sked" / original.name
    shutil.copytree(original, run)
    moved = tmp_path / "moved" / "edit" / "sked" / original.name
    moved.parent.mkdir(parents=True)
    run.rename(moved)
    text = (moved / "config.yml").read_text()
    assert torch.equal(_render(moved, view), before)
    config, _, checkpoint, _ = _eval_setup(Path(os.path.relpath(moved / "config.yml", tmp_path)), cwd=tmp_path)
    assert Path(checkpoint).is_relative_to(moved) and config.output_dir == tmp_path / "moved"
    assert (moved / "config.yml").read_text() == text  # reading a run never writes it


def test_a_copy_missing_its_checkpoints_is_not_read_from_the_original(finished_edit, tmp_path):
    original, _ = finished_edit
    copy = tmp_path / ELSEWHERE
    shutil.copytree(original, copy, ignore=shutil.ignore_patterns("nerfstudio_models"))
    with pytest.raises(SystemExit):  # nerfstudio's own "No checkpoint directory found" and exit 1
        _eval_setup(copy / "config.yml", cwd=tmp_path)
    with pytest.raises(SkedUserError, match=r"copied or moved without its nerfstudio_models/ from .*Copy .*nerfstudio_models into it"):
        edit_scene(copy)


@pytest.mark.parametrize("damage, said", [(0, "empty"), (100, "changed or cut short")])
def test_a_damaged_base_copy_says_what_it_is_and_where_to_get_it(finished_edit, tmp_path, damage, said):
    original, _ = finished_edit
    copy = tmp_path / "copy"
    shutil.copytree(original, copy)
    kept = next((copy / "base").glob("step-*.ckpt"))
    data = kept.read_bytes()
    kept.unlink()
    kept.write_bytes(data[:damage])
    with pytest.raises(SkedUserError, match=rf"{kept}: the edit's copy of its base checkpoint is damaged \(.*{said}.*"
                                            r"\.sked-bases/[0-9a-f]{64}\.ckpt"):
        load_pipeline(copy)


def test_edits_of_one_base_share_one_copy_of_its_weights(scene, finished_edit):
    first, root = finished_edit
    second = _tiny_edit(scene, scene["base"], root / "outputs")
    kept = [next((run / "base").glob("step-*.ckpt")) for run in (first, second)]
    assert os.path.samefile(*kept)
    stored = list((root / "outputs" / ".sked-bases").glob("*.ckpt"))
    assert len(stored) == 1 and os.path.samefile(stored[0], kept[0])
    digest = yaml.load((second / "config.yml").read_text(), Loader=yaml.Loader).pipeline.model.base_digest
    assert stored[0].name == f"{digest}.ckpt"


def test_inside_finds_a_relative_run_folder_in_an_absolute_path():
    assert inside(Path("/a/outputs/x/sked/t1/base/s.ckpt"), Path("outputs/x/sked/t1")) == Path("base/s.ckpt")
    assert inside(Path("/a/outputs/x/sked/t1/base/s.ckpt"), Path("/a/outputs/x/sked/t1")) == Path("base/s.ckpt")
    assert inside(Path("/a/outputs/x/sked/t2/base/s.ckpt"), Path("outputs/x/sked/t1")) is None
    assert inside(Path("/data/scene"), Path("/a/outputs/x/sked/t1")) is None


def test_rehome_names_the_new_folder_and_leaves_outside_paths(finished_edit, tmp_path):
    original, _ = finished_edit
    config = yaml.load((original / "config.yml").read_text(), Loader=yaml.Loader)  # no file behind it: as written
    assert config.get_base_dir() == original
    data = config.pipeline.datamanager.data
    rehome(config, tmp_path / "elsewhere")
    assert config.get_base_dir() == tmp_path / "elsewhere"
    assert Path(config.pipeline.model.sketches) == tmp_path / "elsewhere" / "sketches"
    assert config.pipeline.datamanager.data == data


@pytest.fixture(scope="module")
def splat_edit(tmp_path_factory):
    """A finished edit of a small splatfacto base, in its output folder with the base."""
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.demo.splat_base import SplatFit, fit_demo_splat_base
    from sked_ns.sketches.sketch_set import save_sketch_set

    root = tmp_path_factory.mktemp("splat-home")
    demo_scene.write_demo_dataset(root / "data", num_views=8, size=32)
    save_sketch_set(demo_scene.demo_sketch_set(size=32), root / "sketches")
    base = fit_demo_splat_base(root / "data", root / "outputs", SplatFit(steps=10, num_gaussians=200))
    scene = {"data": root / "data", "sketches": root / "sketches"}
    return _tiny_edit(scene, base, root / "outputs"), root


def test_a_copied_splat_edit_opens_and_resumes_with_the_original_gone(splat_edit, tmp_path):
    original, root = splat_edit
    view = load_sketch_set(root / "sketches").views[0]
    before = _render(original, view)
    copy = tmp_path / ELSEWHERE
    shutil.copytree(root, tmp_path / "root")  # a private copy of base and edit, to delete
    shutil.copytree(tmp_path / "root" / original.relative_to(root), copy)
    shutil.rmtree(tmp_path / "root")

    assert torch.equal(_render(copy, view), before)
    config, pipeline, checkpoint, _ = _eval_setup(copy / "config.yml", cwd=tmp_path)  # ns-export gaussian-splat's
    assert Path(checkpoint).parent == copy / "nerfstudio_models"
    assert pipeline.model.num_points == load_pipeline(copy).model.num_points > 0
    resumed = run_edit(resume_config(copy, iterations=3)).base_dir
    assert resumed.parent == copy.parent and torch.isfinite(_render(resumed, view)).all()


def test_a_finished_edit_saves_what_it_changed_not_adams_moments(finished_edit):
    original, _ = finished_edit
    state = torch.load(sorted((original / "nerfstudio_models").glob("step-*.ckpt"))[-1], map_location="cpu")
    assert state["optimizers"] and all(not optimizer["state"] and optimizer["param_groups"]
                                       for optimizer in state["optimizers"].values())


def test_an_edit_of_an_edit_opens_with_the_earlier_edit_and_its_base_deleted(scene, tmp_path):
    base = tmp_path / "base-run"
    shutil.copytree(scene["base"], base)
    first = _tiny_edit(scene, base, tmp_path / "first")
    config = edit_config(first, scene["data"], scene["sketches"], tmp_path / "second", iterations=2, steps_per_save=1,
                         guidance_resolution=16, silhouette_resolution=16)
    config.progressive = True
    second = run_edit(config).base_dir
    view = load_sketch_set(scene["sketches"]).views[0]
    before = _render(second, view)
    shutil.rmtree(tmp_path / "first")
    shutil.rmtree(base)
    assert torch.equal(_render(second, view), before)
    assert (second / "base" / "sketches").is_dir() and (second / "base" / "base").is_dir()
