"""An edit is a thing of its own: it renders the same for as long as its folder is untouched, whatever happens to
its base run's files (rewritten in place, replaced, moved, deleted), and a damaged base is refused before it trains."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
import yaml

from sked_ns.engine.base_scene import resolve_base
from sked_ns.engine.edit_run import edit_config, resume_config, run_edit
from sked_ns.engine.trainer import resolve_edit
from sked_ns.errors import SkedUserError
from sked_ns.evaluation.render import load_pipeline, render_at
from sked_ns.method.frozen_base import read_model_state
from sked_ns.sketches.sketch_set import load_sketch_set


def _tiny_edit(scene, base: Path, out: Path, sketches: Path) -> Path:
    config = edit_config(base, scene["data"], sketches, out, iterations=2, steps_per_save=1,
                         guidance_resolution=16, silhouette_resolution=16)
    return run_edit(config).base_dir


def _render(run: Path, view) -> torch.Tensor:
    return render_at(load_pipeline(run).model, view, 16)["rgb"]


def test_an_edit_renders_the_same_whatever_happens_to_its_base_run(scene, tmp_path):
    base = tmp_path / "base-run"
    shutil.copytree(scene["base"], base)
    sketches = tmp_path / "sketches"
    shutil.copytree(scene["sketches"], sketches)
    run = _tiny_edit(scene, base, tmp_path / "edits", sketches)
    checkpoint = resolve_base(base).checkpoint
    kept = run / "base" / checkpoint.name

    # The edit's own files: a copy (not a link) of the base's weights, its config and frame; one config.yml in the run.
    assert kept.exists() and not os.path.samefile(kept, checkpoint)
    assert (run / "base" / "base_config.yml").read_bytes() == (base / "config.yml").read_bytes()
    assert (run / "base" / "dataparser_transforms.json").exists()
    assert [path.parent for path in run.rglob("config.yml")] == [run]
    saved = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    assert Path(saved.pipeline.model.base_kept) == kept.absolute()
    assert Path(saved.pipeline.model.sketches) == run / "sketches"  # the sketch set too, as the edit loaded it
    given, own = load_sketch_set(sketches), load_sketch_set(run / "sketches")
    assert all((a.mask == b.mask).all() and (a.camera_to_world == b.camera_to_world).all()
               for a, b in zip(given.views, own.views, strict=True)) and given.frame == own.frame
    original = read_model_state(checkpoint)
    assert {key: torch.equal(value, original[key]) for key, value in read_model_state(kept).items()} == \
        {key: True for key in original}
    assert set(torch.load(kept, map_location="cpu")) == {"step", "pipeline"}  # no optimiser state: nothing reads it

    view = load_sketch_set(scene["sketches"]).views[0]
    before = _render(run, view)

    # The sketch folder removed: the edit's kept space is its own copy's.
    shutil.rmtree(sketches)

    # Rewritten in place (a base run resumed to the same step, a script fixing up a checkpoint): the same inode.
    state = torch.load(checkpoint, map_location="cpu")
    for key, value in state["pipeline"].items():
        if torch.is_tensor(value) and value.is_floating_point():
            state["pipeline"][key] = value + 0.5
    inode = checkpoint.stat().st_ino
    torch.save(state, checkpoint)
    assert checkpoint.stat().st_ino == inode
    assert torch.equal(_render(run, view), before)

    # The base run moved away: every loader opens the edit from its own folder, and the edit resumes.
    base.rename(tmp_path / "moved-base-run")
    assert torch.equal(_render(run, view), before)
    from nerfstudio.utils.eval_utils import eval_setup  # ns-render, ns-export and ns-viewer load runs with it

    cwd = os.getcwd()
    os.chdir(tmp_path)  # eval_setup finds checkpoints under config.yml's output_dir, relative to where it runs
    try:
        config_path = Path(os.path.relpath(run / "config.yml", tmp_path))
        _, pipeline, _, step = eval_setup(config_path, test_mode="inference")
    finally:
        os.chdir(cwd)
    assert step == 1 and pipeline.model.config.base_kept == saved.pipeline.model.base_kept
    resumed = run_edit(resume_config(run, iterations=3)).base_dir  # nerfstudio resumes into a new run folder
    assert (resumed / "nerfstudio_models" / "step-000000002.ckpt").exists()
    assert (resumed / "base" / kept.name).exists() and (resumed / "base" / "base_config.yml").exists()

    # Only the edit's own folder matters: the resumed run opens without the first's; without its own copy of the
    # base, one line names the file.
    shutil.rmtree(run / "base")
    assert torch.isfinite(_render(resumed, view)).all()
    with pytest.raises(SkedUserError, match=rf"{kept}: the edit's copy of its base checkpoint is missing"):
        load_pipeline(run)
    # An edit kept by an older sked_ns (its checkpoint alone) reads its base's config from the base run, now gone.
    (resumed / "base" / "base_config.yml").unlink()
    with pytest.raises(SkedUserError, match=rf"{base}: the edit's base run was moved or deleted .*Put that run back"):
        load_pipeline(resumed)


def _saved_state(path: Path, **tensors) -> Path:
    torch.save({"step": 0, "pipeline": {f"_model.{name}": value for name, value in tensors.items()}}, path)
    return path


@pytest.mark.parametrize("bad, said", [(float("nan"), "NaN values in field.bad"),
                                       (float("inf"), "infinite values in field.bad"),
                                       (-float("inf"), "infinite values in field.bad"),
                                       (1e30, "1e\\+30 in field.bad")])
def test_a_base_with_damaged_weights_is_refused_naming_the_tensor(tmp_path, bad, said):
    good = torch.randn(4, 3)
    damaged = torch.randn(5)
    damaged[2] = bad
    path = _saved_state(tmp_path / "step-000000001.ckpt", **{"field.good": good, "field.bad": damaged,
                                                             "field.count": torch.tensor([2**40])})
    with pytest.raises(SkedUserError, match=rf"{path}: the base's weights are damaged or diverged: it holds {said}"):
        read_model_state(path)


def test_weights_a_trained_scene_can_hold_are_accepted(tmp_path):
    path = _saved_state(tmp_path / "step-000000001.ckpt", **{"field.means": torch.full((3, 3), 1e6),
                                                             "field.tiny": torch.full((2,), 1e-30),
                                                             "field.empty": torch.zeros(0),
                                                             "field.half": torch.full((2,), 6e4).half()})
    assert set(read_model_state(path)) == {"field.means", "field.tiny", "field.empty", "field.half"}


def test_an_edit_of_a_diverged_base_is_refused_before_anything_is_written(scene, tmp_path):
    base = tmp_path / "base-run"
    shutil.copytree(scene["base"], base)
    checkpoint = resolve_base(base).checkpoint
    state = torch.load(checkpoint, map_location="cpu")
    name = next(key for key, value in state["pipeline"].items() if torch.is_tensor(value)
                and value.is_floating_point() and key.startswith("_model.field."))
    state["pipeline"][name] = torch.full_like(state["pipeline"][name], float("nan"))
    torch.save(state, checkpoint)
    config = edit_config(base, scene["data"], scene["sketches"], tmp_path / "edits", iterations=2)
    with pytest.raises(SkedUserError, match=rf"NaN values in {name[len('_model.'):]}"):
        resolve_edit(config)
    assert not (tmp_path / "edits").exists()
