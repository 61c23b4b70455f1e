"""The guidance interface."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Dict, Optional, Type

import numpy as np
from jaxtyping import Float
from nerfstudio.configs.base_config import InstantiateConfig
from torch import Tensor

from sked_ns.errors import UsualRange, unusual_settings, warn_option

FLAGS = "--pipeline.model.guidance."
"""A guidance's settings as typed after its subcommand."""
VIEW_DIRECTIONS = ("front", "side", "back", "overhead", "bottom")
"""The directions a prompt is suffixed with (DreamFusion's directional prompts): a rendered view's `direction`."""


@dataclass
class RenderedView:
    """One rendered training view and its camera (model frame)."""

    image: Float[Tensor, "1 3 height width"]
    """Rendered colour in [0, 1], differentiable."""
    camera_to_world: np.ndarray
    """3x4, OpenGL axes."""
    focal: float
    direction: str
    """One of VIEW_DIRECTIONS, for directional prompts."""
    base_image: Optional[Tensor] = None
    """The frozen base rendered from the same camera, for guidance that asks for it."""
    samples_per_side: int = 1
    """Each pixel is the mean of samples_per_side^2 samples (splat supersampling): an image compared with it must
    be sampled the same way."""


@dataclass
class GuidanceConfig(InstantiateConfig):
    """A guidance component's settings; `setup()` builds its `Guidance`."""

    _target: Type = field(default_factory=lambda: Guidance)
    uses_prompt: ClassVar[bool] = False
    """Whether the text prompt is what it pulls towards (then no prompt means carving)."""
    usual_ranges: ClassVar[Dict[str, UsualRange]] = {}
    """Each numeric setting's usual range by field name: outside it the value is warned as SKED's own knobs are
    (errors.unusual_settings), and a value that is not a finite number is refused."""

    def check(self) -> None:
        """Refuse settings that cannot work, warn on ones that are almost surely a mistake (before any data is read).
        A guidance refuses what only it knows is impossible, then calls this: its `usual_ranges` checked."""
        for message in unusual_settings(self, self.usual_ranges, FLAGS):
            warn_option(message)

    def check_available(self) -> None:
        """Refuse, before an edit writes anything, when what `prepare` will read (weights) is not there; cheaply,
        without loading it."""


class Guidance:
    """Turns a rendered view into losses; `prepare` runs once before training."""

    needs_base_render: bool = False
    """Set by guidance that compares against the base (costs one more render per step)."""

    def __init__(self, config: GuidanceConfig) -> None:
        self.config = config

    def prepare(self, prompt: Optional[str], device: str, context: Dict) -> None:
        """Load weights, encode the prompt; `context` carries scene facts (dataparser transform) and the model."""

    def __call__(self, view: RenderedView, step: int) -> Dict[str, Tensor]:
        raise NotImplementedError
