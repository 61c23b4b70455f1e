"""A resumed edit whose config.yml names no SKED method (a typo in an edited copy) is resumed as the method typed,
said in one line, not into a method folder of the typo's name."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_resume import resume, saved_edit

from sked_ns.engine.edit_run import resume_config
from sked_ns.errors import SkedWarning

RUN = Path("/runs/scene/sked/2026-01-01_000000")


def test_a_saved_method_name_that_is_no_sked_method_is_resumed_as_the_method_typed():
    config = resume_config(RUN, Path("/elsewhere"))
    config.timestamp = "now"
    saved = saved_edit()
    saved.method_name = "skedd"
    with pytest.warns(SkedWarning) as said:
        resume(config, saved)
    assert [str(w.message) for w in said] == [
        f"{RUN / 'config.yml'}: method_name 'skedd' is no SKED method (sked, sked-fast, sked-quality); resuming the "
        "edit as sked, the method typed."]
    assert config.method_name == "sked" and config.get_base_dir() == Path("/elsewhere/scene/sked/now")
    assert saved.method_name == "skedd", "the saved config is only read"


@pytest.mark.parametrize("method", ["sked", "sked-fast", "sked-quality"])
def test_a_saved_sked_method_is_kept_without_a_word(method, recwarn):
    config = resume_config(RUN, Path("/elsewhere"))
    saved = saved_edit()
    saved.method_name = method
    resume(config, saved)
    assert config.method_name == method
    assert not [w for w in recwarn if issubclass(w.category, SkedWarning)]
