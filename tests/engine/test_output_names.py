"""A file or folder name longer than the file system takes, where an edit writes or in what it reads, is refused in
one line naming its flag, before anything is written (every file operation on such a name fails with
ENAMETOOLONG, Path.exists() included)."""

from __future__ import annotations

import pytest

from sked_ns.engine.base_scene import resolve_base
from sked_ns.engine.edit_inputs import check_disk_space, check_edit_inputs
from sked_ns.engine.presets import edit_preset
from sked_ns.errors import SkedUserError, check_writable_folder, excepthook

LONG = "a" * 300


def _config(tmp_path, **settings):
    config = edit_preset("sked")
    base = tmp_path / "base" / "nerfstudio_models" / "step-000000099.ckpt"
    base.parent.mkdir(parents=True)
    base.write_bytes(b"\0" * 1000)
    config.pipeline.model.base_checkpoint = base
    config.output_dir, config.experiment_name = tmp_path / "outputs", "scene"
    for name, value in settings.items():
        setattr(config, name, value)
    return config


@pytest.mark.parametrize("setting, flag", [
    ({"output_dir": "outputs/" + LONG}, "--output-dir"),
    ({"output_dir": LONG + "/outputs"}, "--output-dir"),
    ({"experiment_name": LONG}, "--experiment-name"),
    ({"timestamp": LONG}, "--timestamp"),
])
def test_a_folder_name_too_long_for_the_file_system_is_refused_naming_its_flag(tmp_path, monkeypatch, capsys,
                                                                             setting, flag):
    monkeypatch.chdir(tmp_path)
    config = _config(tmp_path, **setting)
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(SkedUserError) as refused:
        check_disk_space(config)
    message = str(refused.value)
    assert message.startswith(f"{flag}: the name '{'a' * 24}...' is 300 bytes long") and \
        message.endswith(f"Pass a shorter {flag}."), message
    assert sorted(tmp_path.rglob("*")) == before, "nothing written"
    excepthook(type(refused.value), refused.value, None)
    assert capsys.readouterr().err.count("\n") == 1


def test_names_the_file_system_takes_pass(tmp_path):
    check_disk_space(_config(tmp_path, output_dir=tmp_path / ("b" * 200), experiment_name="c" * 255))


def test_a_run_path_longer_than_the_system_takes_is_refused(tmp_path):
    deep = "/".join(["d" * 200] * 25)  # each name fits, the whole path does not
    with pytest.raises(SkedUserError, match=r"^--output-dir: the path is \d+ bytes long, more than this system allows"):
        check_disk_space(_config(tmp_path, output_dir=tmp_path / deep))


@pytest.mark.parametrize("flag", ["--load-dir", "--load-checkpoint"])
def test_a_scene_to_edit_with_a_name_too_long_is_refused_naming_its_flag(tmp_path, flag):
    with pytest.raises(SkedUserError, match=rf"^{flag}: the name '{'a' * 24}\.\.\.' is 300 bytes long"):
        resolve_base(tmp_path / LONG / "nerfstudio_models", flag=flag)


def test_sketches_with_a_name_too_long_are_refused_naming_the_flag(tmp_path, monkeypatch):
    config = _config(tmp_path)
    config.pipeline.model.sketches, config.machine.device_type = tmp_path / LONG, "cpu"
    monkeypatch.setattr("sked_ns.engine.edit_inputs.check_guidance", lambda *args: None)  # the sketches alone
    with pytest.raises(SkedUserError, match=rf"^--sketches: the name '{'a' * 24}\.\.\.' is 300 bytes long"):
        check_edit_inputs(config)


def test_an_unwritable_output_folder_with_a_name_too_long_says_the_name_not_the_permissions(tmp_path):
    with pytest.raises(SkedUserError, match=r"^--output-dir: the name 'a+\.\.\.' is 300 bytes long.*Pass a shorter"):
        check_writable_folder(tmp_path / LONG / "scene", "--output-dir", tmp_path / LONG)


def test_data_with_a_name_too_long_is_refused_naming_the_flag(tmp_path):
    from types import SimpleNamespace

    from sked_ns.engine.trainer import check_data

    config = _config(tmp_path)
    config.data = tmp_path / LONG
    with pytest.raises(SkedUserError, match=rf"^--data: the name '{'a' * 24}\.\.\.' is 300 bytes long"):
        check_data(config, SimpleNamespace())
