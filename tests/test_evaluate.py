"""sked-eval's command line: where it writes, what it refuses, named as sked-eval takes it (no model needed)."""

from __future__ import annotations

import argparse
import sys

import pytest

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.evaluate import edit_run_folder, orbit_count, output_paths, positive_int


def test_results_go_next_to_the_edit_and_never_replace_an_earlier_one(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    assert output_paths(run, None, None, overwrite=False) == (run / "sked_eval.json", run / "sked_eval.png")
    (run / "sked_eval.png").write_bytes(b"earlier")
    with pytest.raises(SkedUserError, match=r"sked_eval.png already exist.*--output.*--overwrite"):
        output_paths(run, None, None, overwrite=False)
    assert output_paths(run, None, None, overwrite=True)[1] == run / "sked_eval.png"
    mine = tmp_path / "mine.json"
    assert output_paths(run, mine, None, overwrite=False) == (mine, tmp_path / "mine.png")


def test_a_missing_config_is_named_as_sked_eval_takes_it(tmp_path):
    with pytest.raises(SkedFileNotFoundError, match=r"sked-eval .*absent/config.yml: no .*config.yml") as error:
        edit_run_folder(tmp_path / "absent" / "config.yml")
    assert "--load-dir" not in str(error.value)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yml").write_text("")
    assert edit_run_folder(tmp_path / "run") == edit_run_folder(tmp_path / "run" / "config.yml") == tmp_path / "run"


@pytest.mark.parametrize("text", ["0", "-3", "x"])
def test_sizes_and_counts_must_be_positive_whole_numbers(text):
    with pytest.raises(argparse.ArgumentTypeError):
        positive_int(text)
    with pytest.raises(SkedUserError, match=f"--cameras orbit:{text}: "):
        orbit_count(f"orbit:{text}")
    assert positive_int("3") == 3 and orbit_count("orbit") == 12 and orbit_count("orbit:5") == 5


def test_the_command_refuses_before_loading_anything(tmp_path, monkeypatch, capsys):
    from sked_ns.evaluate import entrypoint

    monkeypatch.setattr(sys, "argv", ["sked-eval", str(tmp_path / "nowhere"), "--resolution", "0"])
    with pytest.raises(SystemExit):
        entrypoint()
    assert "--resolution: 0: must be at least 1" in capsys.readouterr().err
    monkeypatch.setattr(sys, "argv", ["sked-eval", str(tmp_path / "nowhere")])
    with pytest.raises(SkedFileNotFoundError, match="sked-eval .*nowhere"):
        entrypoint()


def test_an_output_folder_that_cannot_be_written_is_refused_before_evaluating(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(SkedUserError, match="--output"):
        output_paths(run, blocker / "metrics.json", None, overwrite=False)
    with pytest.raises(SkedUserError, match="--sheet"):
        output_paths(run, None, blocker / "sheet.png", overwrite=False)
