"""Each guidance's own numeric settings are checked as SKED's knobs are: one function (errors.unusual_settings) reads
the usual ranges a guidance config declares, warns a value far outside them and refuses one that is no finite number."""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from typing import ClassVar, Dict

import pytest

from sked_ns.errors import SkedOptionError, SkedOptionWarning, UsualRange
from sked_ns.guidance import GuidanceConfig, StableDiffusionGuidanceConfig, check_guidance, guidance_components

FLAGS = "--pipeline.model.guidance."


def _warned(config) -> list:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_guidance(config, None)
    return [str(w.message) for w in caught if issubclass(w.category, SkedOptionWarning)]


@pytest.mark.parametrize("weight", [1e38, 1e5, 1e-3])
def test_a_reference_weight_orders_of_magnitude_off_is_warned_as_skeds_loss_weights_are(weight):
    said = _warned(guidance_components()["reference"](weight=weight))
    assert len(said) == 1 and re.fullmatch(re.escape(f"{FLAGS}weight {weight:g}: ") + r".+ \(usual 0\.1 to 1000, "
                                           r"default 30\)\.", said[0]), said


@pytest.mark.parametrize("settings, flag, value", [
    ({"weight": 1e38}, "weight", "1e+38"), ({"weight": 1e-9}, "weight", "1e-09"),
    ({"guidance_scale": 1e6}, "guidance-scale", "1e+06"), ({"image_size": 51200}, "image-size", "51200"),
])
def test_stable_diffusions_numbers_orders_of_magnitude_off_are_warned(settings, flag, value):
    said = _warned(StableDiffusionGuidanceConfig(model="someone/sd", **settings))
    assert len(said) == 1 and said[0].startswith(f"{FLAGS}{flag} {value}: ") and "(usual " in said[0], said


@pytest.mark.parametrize("name", sorted(guidance_components()))
def test_each_guidance_declares_fields_it_has_and_its_defaults_are_usual(name):
    component = guidance_components()[name]
    names = {item.name for item in dataclasses.fields(component)}
    assert set(component.usual_ranges) <= names, "a range for a setting the guidance does not have"
    config = component()
    for field, usual in component.usual_ranges.items():
        assert usual.low <= getattr(config, field) <= usual.high, field
    if name == "stable-diffusion":
        config.model = "someone/sd"  # not read by check
    assert _warned(config) == []



@dataclasses.dataclass
class StrengthGuidanceConfig(GuidanceConfig):
    usual_ranges: ClassVar[Dict[str, UsualRange]] = {"strength": UsualRange(0.5, 2.0, "too weak", "too strong")}
    strength: float = 1.0


def test_a_guidance_that_declares_its_ranges_is_warned_and_refused_without_code_of_its_own():
    assert _warned(StrengthGuidanceConfig(strength=50.0)) == [f"{FLAGS}strength 50: too strong (usual 0.5 to 2, "
                                                              "default 1)."]
    assert _warned(StrengthGuidanceConfig(strength=1.5)) == []
    for value in (math.nan, math.inf):
        with pytest.raises(SkedOptionError, match=rf"{re.escape(FLAGS)}strength {value}: must be a finite number"):
            check_guidance(StrengthGuidanceConfig(strength=value), None)
