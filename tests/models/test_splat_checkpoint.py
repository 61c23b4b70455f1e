"""A splat edit's checkpoint holds what the edit changed (its editable Gaussians, their L_pres targets, which of the
base's Gaussians it keeps), not the kept Gaussians: those are read from the edit's copy of its base whenever it loads,
and an edit read as the base of the next is composed from its base and its changes. Edits saved whole by earlier
versions still load."""

from __future__ import annotations

import math
import shutil

import pytest
import torch
from test_splat_model import kept_mask, splat_scene  # noqa: F401  (the tiny saved splatfacto run)

from sked_ns.errors import SkedUserError
from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS, KEPT_IN_BASE

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def saved_edit(splat_scene, tmp_path_factory):  # noqa: F811
    """A finished 2-iteration edit of the tiny splat base, its trainer (the edit as trained) and its checkpoint."""
    from sked_ns.engine.edit_run import edit_config, run_edit

    config = edit_config(splat_scene["base"], splat_scene["data"], splat_scene["sketches"],
                         tmp_path_factory.mktemp("edit") / "out", iterations=2, guidance_resolution=24,
                         silhouette_resolution=16)
    trainer = run_edit(config)
    checkpoint = sorted((trainer.base_dir / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    return {"trainer": trainer, "run": trainer.base_dir, "checkpoint": checkpoint}


def model_state(checkpoint):
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    return {key[len("_model."):]: value for key, value in state["pipeline"].items() if key.startswith("_model.")}


def loaded(config_file):
    """The edit as nerfstudio's ns-render, ns-export and ns-viewer open it."""
    from nerfstudio.utils.eval_utils import eval_setup

    return eval_setup(config_file, test_mode="inference")[1].model


def renders(model, camera):
    model.eval()
    with torch.no_grad():
        return model.get_outputs(camera)


def test_the_checkpoint_holds_the_editable_gaussians_and_not_the_kept_ones(saved_edit, splat_scene):  # noqa: F811
    model = saved_edit["trainer"].pipeline.model
    state = model_state(saved_edit["checkpoint"])
    assert not [key for key in state if key.startswith("kept.")]
    kept = kept_mask(model, splat_scene)
    assert 0 < int(kept.sum()) < len(kept)
    assert torch.equal(state[KEPT_IN_BASE], kept)  # which of the base's Gaussians are kept: one bool each
    editable = len(model.gauss_params["means"])
    stored = {key: len(value) for key, value in state.items() if key.startswith("gauss_params.")}
    assert set(stored.values()) == {editable}, stored
    assert editable == len(kept) - int(kept.sum()) + int((~model.reference.from_base).sum())
    # Not refined yet: L_pres's targets are the base's values (and the seeds', never weighed), read from the base.
    assert not [key for key in state if key.startswith("reference.")]


def test_the_loaded_edit_renders_as_it_was_trained_and_keeps_the_base_bit_for_bit(saved_edit, splat_scene):  # noqa: F811
    trained = saved_edit["trainer"].pipeline.model
    model = loaded(saved_edit["run"] / "config.yml")
    kept = kept_mask(model, splat_scene)
    for name, value in splat_scene["gaussians"].items():
        assert torch.equal(model.kept[name], value[kept]), name
        assert torch.equal(getattr(model, name)[: int(kept.sum())], value[kept]), name  # the scene: kept rows first
        assert torch.equal(getattr(model, name), getattr(trained, name).detach()), name
    for name, value in trained.reference.tensors().items():
        assert torch.equal(model.reference[name], value), name  # L_pres holds what it held, as it trains on
    camera = saved_edit["trainer"].pipeline.datamanager.train_dataset.cameras[0:1]
    before, after = renders(trained, camera), renders(model, camera)
    assert float(after["accumulation"].amax()) > 0.5  # the sphere is in view
    for key in ("rgb", "accumulation", "depth", "preservation_weight"):
        assert torch.equal(after[key], before[key]), key


def test_ns_export_writes_every_gaussian_of_the_edit(saved_edit, tmp_path):
    from nerfstudio.scripts.exporter import ExportGaussianSplat
    from plyfile import PlyData

    model = loaded(saved_edit["run"] / "config.yml")
    ExportGaussianSplat(load_config=saved_edit["run"] / "config.yml", output_dir=tmp_path).main()
    vertex = PlyData.read(str(tmp_path / "splat.ply"))["vertex"]
    visible = model.opacities.detach()[:, 0] >= math.log(1 / 254)  # the exporter drops what gsplat skips (< 1/255)
    assert model.num_points == len(model.kept["means"]) + len(model.gauss_params["means"])
    assert vertex.count == int(visible.sum()) > len(model.gauss_params["means"])  # kept ones included


def test_a_kept_set_saved_by_another_device_is_the_one_loaded(saved_edit):
    """w computed on another device can round across keep_threshold: the saved rows, not this machine's, say which
    Gaussians are kept."""
    model = loaded(saved_edit["run"] / "config.yml")
    state = {key: value.clone() for key, value in model.state_dict().items() if torch.is_tensor(value)}
    base = model._base_in_its_order()
    kept = state[KEPT_IN_BASE]
    kept[int(kept.nonzero()[0])] = False  # one kept Gaussian judged editable there
    model.load_state_dict({**model.state_dict(), KEPT_IN_BASE: kept})
    for name in GAUSSIAN_PARAMS:
        assert torch.equal(model.kept[name], base[name][kept]), name
        assert torch.equal(model._base_in_its_order()[name], base[name]), name
    with pytest.raises(SkedUserError, match="does not fit its base's"):
        model.load_state_dict({**model.state_dict(), KEPT_IN_BASE: kept[1:]})


def test_an_edit_saved_whole_by_an_earlier_version_loads_and_is_saved_whole_again(saved_edit, splat_scene,  # noqa: F811
                                                                                tmp_path):
    run = tmp_path / "run"
    shutil.copytree(saved_edit["run"], run)
    checkpoint = run / "nerfstudio_models" / saved_edit["checkpoint"].name
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    trained = saved_edit["trainer"].pipeline.model
    # The earlier layout: the kept Gaussians saved with the edit, no kept rows. Moved a little, to tell them apart.
    del state["pipeline"][f"_model.{KEPT_IN_BASE}"]
    for name, value in trained.kept.tensors().items():
        state["pipeline"][f"_model.kept.{name}"] = value + 1e-3 if name == "means" else value
    torch.save(state, checkpoint)
    model = loaded(run / "config.yml")
    assert torch.equal(model.kept["means"], trained.kept["means"] + 1e-3)  # as saved, not read from the base
    assert torch.equal(model.means[len(model.kept["means"]):], trained.gauss_params["means"].detach())
    saved = model.state_dict()
    assert torch.equal(saved["kept.means"], model.kept["means"])  # a resumed earlier edit keeps its layout
    camera = saved_edit["trainer"].pipeline.datamanager.train_dataset.cameras[0:1]
    assert torch.isfinite(renders(model, camera)["rgb"]).all()


def test_a_progressive_edit_of_a_splat_edit_edits_the_composed_scene(saved_edit, splat_scene, tmp_path):  # noqa: F811
    """`ns-train sked --load-dir <splat edit> --progressive True`: the new edit's base is the earlier edit's whole
    scene (its base's kept Gaussians and its own), read through the new edit's copy of it, which holds the earlier
    edit's own base too: the new edit loads, with that scene's kept rows, after the earlier edit is deleted, and so
    does a resume of it into a new folder after the new edit is deleted."""
    from sked_ns.engine.edit_run import edit_config, resume_config, run_edit

    earlier_run = tmp_path / "earlier"
    shutil.copytree(saved_edit["run"], earlier_run)
    earlier = loaded(earlier_run / "config.yml")
    config = edit_config(earlier_run, splat_scene["data"], splat_scene["sketches"], tmp_path / "out",
                         iterations=1, guidance_resolution=24, silhouette_resolution=16)
    config.progressive = True
    trainer = run_edit(config)
    model = trainer.pipeline.model
    assert model.config.base_kept is not None and model.config.base_kept.parent == trainer.base_dir / "base"
    assert KEPT_IN_BASE in model_state(model.config.base_kept)  # its base copy is the earlier edit's changes
    base = model._base_in_its_order()
    for name in GAUSSIAN_PARAMS:
        assert torch.equal(base[name], getattr(earlier, name).detach()), name
    shutil.rmtree(earlier_run)
    reloaded = loaded(trainer.base_dir / "config.yml")
    kept = getattr(model, KEPT_IN_BASE)
    for name in GAUSSIAN_PARAMS:
        assert torch.equal(reloaded.kept[name], getattr(earlier, name).detach()[kept]), name
        assert torch.equal(getattr(reloaded, name), getattr(model, name).detach()), name
    # Resumed into a new folder, it takes its base copy along, the earlier edit's base inside it.
    resumed = run_edit(resume_config(trainer.base_dir, tmp_path / "resumed", iterations=2))
    shutil.rmtree(trainer.base_dir)
    reopened = loaded(resumed.base_dir / "config.yml")
    for name in GAUSSIAN_PARAMS:
        assert torch.equal(reopened.kept[name], getattr(earlier, name).detach()[kept]), name
