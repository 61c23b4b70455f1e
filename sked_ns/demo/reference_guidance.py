"""Reference guidance: renders of a known target scene pull the edit towards them.

Deterministic and weight-free, for tests, benchmarks and the offline demo: the built-in
target is the demo scene with its hat (an analytic scene rendered exactly at any camera).
The reference is "the base plus the known change": the analytic target where it differs
from the analytic base, the frozen base model's own render everywhere else, so the edit is
pulled towards the change without being pulled towards the analytic scene elsewhere.

For a scene with no analytic twin (a capture), `--pipeline.model.guidance.primitive` makes the change a
primitive set into the edit box and depth-tested against the frozen base's own render (composite_target.py):
a tool for measuring an edit of any base, not a way to edit one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Dict, Literal, Optional, Tuple, Type

import torch
from torch import Tensor

from sked_ns.errors import SkedUserError, UsualRange, is_number
from sked_ns.guidance.base import Guidance, GuidanceConfig, RenderedView


@dataclass
class ReferenceGuidanceConfig(GuidanceConfig):
    _target: Type = field(default_factory=lambda: ReferenceGuidance)
    usual_ranges: ClassVar[Dict[str, UsualRange]] = {
        # The image MSE is a mean of order 0.1 or less, summed with SKED's terms of order 1 (method/edit.py).
        "weight": UsualRange(0.1, 1000.0, "the reference's pull is outweighed by L_sil, which fills the sketch with a "
                             "grey haze; 0 turns it off", "the reference's pull drowns every other term, L_pres's hold "
                             "on the rest of the scene included"),
    }
    target: str = "hat"
    """Which known edit renders the references: the demo sphere's (demo_scene.SCENES: hat, handle,
    antenna) or a held-out benchmark scene's (objects.SCENES: vase, crate; capture.SCENES: bust). Not read
    when `primitive` names one."""
    primitive: Literal["none", "cone", "ball", "box", "hull"] = "none"
    """A target any base can take, for measuring: the frozen base's own render with this primitive set into the
    edit box, shown where it is nearer than the base's expected depth; hull: the sketches' visual hull itself, one
    colour, unlit (it fills each sketch as far as the other views allow). none: `target`'s known scene."""
    primitive_colour: Tuple[float, float, float] = (0.85, 0.15, 0.15)
    """The primitive's colour (RGB in [0, 1]), shaded by the demo scenes' fixed light (the hull: unlit)."""
    primitive_size: float = 0.8
    """The primitive's extent as a share of the edit box's along each axis (a ball's diameter: of its smallest; not
    read for the hull)."""
    primitive_centre: Tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Where the primitive's centre sits in the edit box, as shares of its extent along the model frame's axes (not
    read for the hull)."""
    weight: float = 30.0
    """Multiplier of the image MSE. At 1 the silhouette loss outweighs it and fills the sketch
    with a grey haze; at 30 the hat takes the target's shape and colour."""
    sampling: Literal["as-rendered", "pixel-centre"] = "as-rendered"
    """as-rendered: the target is sampled as the edit's render was (a splat edit's supersampled pixels are
    averages; so is the target's), as a camera integrates over each pixel; pixel-centre: one sample a pixel
    whatever the render (how sked_ns 0.2 and older sampled it)."""

    def check(self) -> None:
        if self.primitive == "none":
            reference_scene(self.target)  # an unknown target is refused before the edit writes anything
        else:
            check_primitive(self)
        if not (isinstance(self.weight, (int, float)) and math.isfinite(self.weight) and self.weight >= 0):
            raise SkedUserError(f"--pipeline.model.guidance.weight {self.weight!r}: a loss weight must be a finite "
                                "number >= 0.")
        super().check()


class ReferenceGuidance(Guidance):
    config: ReferenceGuidanceConfig
    needs_base_render = True

    def prepare(self, prompt: Optional[str], device: str, context: Dict) -> None:
        # The analytic target lives in the data frame: cameras are mapped back from the model frame.
        self.transform = context["dataparser_transform"]
        config = self.config
        if config.primitive == "none":
            self.scene = reference_scene(config.target)
            return
        from sked_ns.demo.composite_target import target_primitive

        self.model = context["model"]  # the frozen base it renders, and the edit box the primitive stands in
        self.primitive = target_primitive(self.model, config.primitive, config.primitive_colour,
                                          config.primitive_centre, config.primitive_size)

    def target_image(self, view: RenderedView) -> tuple[Tensor, Tensor, Tensor]:
        """Sampled as the view was (samples_per_side^2 samples a pixel, averaged; a point-sampled target beside an
        area-averaged render asks a part thinner than a pixel to fill whole pixels or none), each (1, C, h, w):
        the target's colour, its colour summed over only the samples where it differs from the base scene, and the
        share of those samples."""
        _, _, height, width = view.image.shape
        factor = max(int(view.samples_per_side), 1) if self.config.sampling == "as-rendered" else 1
        # Focal lengths are in pixels, so the frame's scale does not change them.
        size = (view.focal * factor, width * factor, height * factor)
        if self.config.primitive != "none":  # the model frame's view of the frozen base, the primitive set in
            from sked_ns.demo.composite_target import composite_target, pinhole

            composite = composite_target(self.model, self.primitive, pinhole(view.camera_to_world, *size))
            target, changed = composite["rgb"], composite["changed"][..., None].float()
        else:
            pose = self.transform.invert(view.camera_to_world)
            target = self.scene.render_target(pose, *size)["rgb"]
            base = self.scene.render_base(pose, *size)["rgb"]
            changed = ((target - base).abs().amax(dim=-1, keepdim=True) > 1e-3).float()
        fine = torch.cat([target, target * changed, changed], dim=-1).permute(2, 0, 1)[None]
        pooled = (torch.nn.functional.avg_pool2d(fine, factor) if factor > 1 else fine).to(view.image)
        return pooled[:, :3], pooled[:, 3:6], pooled[:, 6:]

    def __call__(self, view: RenderedView, step: int) -> Dict[str, Tensor]:
        target, changed_colour, changed = self.target_image(view)
        if view.base_image is not None:
            # The target over each pixel's changed samples, the frozen base's render over the rest.
            target = changed_colour + (1 - changed) * view.base_image.to(target)
        return {"reference_loss": self.config.weight * (view.image - target).pow(2).mean()}


def check_primitive(config: ReferenceGuidanceConfig) -> None:
    """Refuse a primitive's colour, size or place that no edit box can hold."""
    flag = "--pipeline.model.guidance."
    if not (len(config.primitive_colour) == 3 and all(is_number(c) and 0 <= c <= 1 for c in config.primitive_colour)):
        raise SkedUserError(f"{flag}primitive-colour {config.primitive_colour!r}: three numbers in [0, 1] (red, green, "
                            "blue).")
    if not (is_number(config.primitive_size) and 0 < config.primitive_size <= 1):
        raise SkedUserError(f"{flag}primitive-size {config.primitive_size!r}: a share of the edit box in (0, 1].")
    if not (len(config.primitive_centre) == 3 and all(is_number(c) and 0 <= c <= 1 for c in config.primitive_centre)):
        raise SkedUserError(f"{flag}primitive-centre {config.primitive_centre!r}: three shares of the edit box in "
                            "[0, 1] (0.5 0.5 0.5: its centre).")


def reference_scene(name: str):
    """The known edit called `name`: a demo-sphere scene or a held-out benchmark scene."""
    from sked_ns.demo.scenes.catalogue import scene_named

    try:
        return scene_named(name)
    except ValueError as error:
        raise SkedUserError(f"--pipeline.model.guidance.target {name}: {error}") from None
