"""Guidance: what pulls the sketched region towards the target (text, or reference renders).

Each guidance has its own config with `_target` and returns a dict of named losses from a
rendered view, so swapping Stable Diffusion for a reference scene touches nothing else.
Guidance objects are plain Python objects, not submodules: their weights never enter a
checkpoint.
"""

from sked_ns.guidance.base import Guidance, GuidanceConfig, RenderedView
from sked_ns.guidance.reference import ReferenceGuidance, ReferenceGuidanceConfig
from sked_ns.guidance.stable_diffusion import StableDiffusionGuidance, StableDiffusionGuidanceConfig

__all__ = [
    "Guidance",
    "GuidanceConfig",
    "RenderedView",
    "ReferenceGuidance",
    "ReferenceGuidanceConfig",
    "StableDiffusionGuidance",
    "StableDiffusionGuidanceConfig",
]
