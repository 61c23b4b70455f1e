"""The reference guidance samples its target as the edit's render was sampled (splat supersampling)."""

import numpy as np
import pytest
import torch

from sked_ns.demo.reference_guidance import ReferenceGuidanceConfig
from sked_ns.demo.scenes.catalogue import scene_named
from sked_ns.demo.scenes.objects import CAMERA_RADIUS
from sked_ns.demo.scenes.sphere import orbit_pose
from sked_ns.guidance import RenderedView

SIZE = 24


class _Identity:
    """A dataparser transform that leaves poses as they are (the model frame is the data frame)."""

    @staticmethod
    def invert(camera_to_world):
        return camera_to_world


def _guidance(sampling="as-rendered"):
    guidance = ReferenceGuidanceConfig(target="vase", sampling=sampling).setup()
    guidance.prepare(None, "cpu", {"dataparser_transform": _Identity()})
    return guidance


def _view(samples_per_side, image=None, base_image=None):
    pose = orbit_pose(30.0, 20.0, CAMERA_RADIUS)
    image = torch.zeros(1, 3, SIZE, SIZE) if image is None else image
    return RenderedView(image=image, camera_to_world=pose, focal=1.1 * SIZE, direction="front",
                        base_image=base_image, samples_per_side=samples_per_side)


def _plain_target(factor):
    """A plain reference: the analytic target and base at factor x the size, each pixel the mean of its block."""
    scene, pose = scene_named("vase"), orbit_pose(30.0, 20.0, CAMERA_RADIUS)
    size = (1.1 * SIZE * factor, SIZE * factor, SIZE * factor)
    target, base = scene.render_target(pose, *size)["rgb"], scene.render_base(pose, *size)["rgb"]
    colour, changed_colour, changed = (torch.zeros(SIZE, SIZE, 3), torch.zeros(SIZE, SIZE, 3),
                                       torch.zeros(SIZE, SIZE, 1))
    for y in range(SIZE):
        for x in range(SIZE):
            for dy in range(factor):
                for dx in range(factor):
                    sample, under = target[y * factor + dy, x * factor + dx], base[y * factor + dy, x * factor + dx]
                    differs = float((sample - under).abs().max() > 1e-3)
                    colour[y, x] += sample / factor ** 2
                    changed_colour[y, x] += differs * sample / factor ** 2
                    changed[y, x] += differs / factor ** 2
    return [value.permute(2, 0, 1)[None] for value in (colour, changed_colour, changed)]


@pytest.mark.parametrize("factor", [1, 3])
def test_target_is_the_mean_of_its_samples(factor):
    produced = _guidance().target_image(_view(factor))
    for fast, plain in zip(produced, _plain_target(factor)):
        assert fast.shape == plain.shape and torch.allclose(fast, plain, atol=1e-5)


def test_a_supersampled_view_gets_a_part_thinner_than_a_pixel_as_a_share_of_it():
    """The vase's stem is under a 24 px pixel wide: sampled once, each pixel shows it whole or not at all."""
    _, _, point_share = _guidance("pixel-centre").target_image(_view(4))
    _, _, area_share = _guidance().target_image(_view(4))
    assert set(point_share.unique().tolist()) <= {0.0, 1.0}  # pixel-centre ignores how the view was sampled
    partial = (area_share > 0.05) & (area_share < 0.95)
    assert int(partial.sum()) >= 5
    assert torch.equal(_guidance("pixel-centre").target_image(_view(4))[0], _guidance().target_image(_view(1))[0])


def test_loss_is_zero_at_the_target_composed_with_the_base_render():
    """Each pixel's reference: the target over its changed samples, the frozen base's render over the rest."""
    guidance = _guidance()
    base_image = torch.rand(1, 3, SIZE, SIZE)
    _, changed_colour, changed = guidance.target_image(_view(4))
    expected = changed_colour + (1 - changed) * base_image
    assert float(guidance(_view(4, expected, base_image), 0)["reference_loss"]) < 1e-10
    moved = expected + 0.1 * changed  # only where the part is: the loss must see it
    assert float(guidance(_view(4, moved, base_image), 0)["reference_loss"]) > 1e-5
    # Without a base render the analytic target is the reference everywhere.
    target, _, _ = guidance.target_image(_view(4))
    assert float(guidance(_view(4, target), 0)["reference_loss"]) < 1e-10
    assert np.isfinite(float(guidance(_view(4, torch.ones(1, 3, SIZE, SIZE), base_image), 0)["reference_loss"]))


# ---- the composite target: a primitive set into any base's render, depth-tested ----------------------------------
class _AnalyticBase:
    """Stands in for a SKED model's frozen base: `render_base` sphere-traces the vase scene's base along the rays."""

    config = type("Config", (), {"eval_num_rays_per_chunk": 1 << 20})()
    device = torch.device("cpu")

    def __init__(self, edit_box):
        from sked_ns.demo.scenes.objects import SCENES, union

        self.edit_box = edit_box
        self.sdf, self.albedo = union(SCENES["vase"].base_parts)

    def _collide(self, rays):
        return rays

    def render_base(self, rays):
        from sked_ns.demo.scenes.capture import trace_rays
        from sked_ns.demo.scenes.objects import SCENES

        traced = trace_rays(SCENES["vase"].base_parts, rays.origins, rays.directions)
        depth = (traced["points"] - rays.origins).norm(dim=-1, keepdim=True)
        return {"rgb": traced["rgb"], "accumulation": traced["hit"][..., None].float(), "expected_depth": depth}


def _box(low, high):
    from sked_ns.method.edit_box import EditBox

    return EditBox(min=np.asarray(low, dtype=np.float64), max=np.asarray(high, dtype=np.float64))


VASE_VIEW = orbit_pose(0.0, 10.0, CAMERA_RADIUS)  # from -y: the vase (x -0.15, y 0.05) is in front of what is behind it


def _composite(primitive_box, kind="ball", size=1.0):
    from sked_ns.demo.composite_target import Primitive, composite_target, pinhole, render_base_with_depth

    model = _AnalyticBase(primitive_box)
    primitive = Primitive.in_edit_box(kind, (0.1, 0.9, 0.1), (0.5, 0.5, 0.5), size, primitive_box)
    result = composite_target(model, primitive, pinhole(VASE_VIEW, 1.1 * 64, 64, 64))
    base = render_base_with_depth(model, pinhole(VASE_VIEW, 1.1 * 64, 64, 64))
    silhouette = primitive.cast(base["origins"].double(), base["directions"].double())
    return result, base, silhouette


def test_the_composite_is_the_base_render_outside_the_primitive_silhouette():
    result, base, silhouette = _composite(_box((0.1, -0.5, 0.3), (0.5, -0.1, 0.7)))  # a ball in the open, in front
    assert silhouette["hit"].sum() > 20 and torch.equal(result["changed"], silhouette["hit"])  # nothing in front of it
    assert torch.equal(result["silhouette"], silhouette["hit"])
    outside = ~silhouette["hit"]
    assert torch.equal(result["rgb"][outside], base["rgb"][outside])
    assert torch.equal(result["base"], base["rgb"])
    colour = result["rgb"][result["changed"]]
    assert (colour[:, 1] > colour[:, 0] + 0.2).all()  # the primitive's green, shaded


def test_nearer_base_content_hides_the_primitive():
    """A ball behind the vase: where the vase stands in front of it, the composite shows the vase."""
    result, base, silhouette = _composite(_box((-0.1, 0.25, 0.2), (0.2, 0.55, 0.5)))
    hidden = silhouette["hit"] & (base["accumulation"] >= 0.5) & (base["depth"] < silhouette["distance"].float())
    assert hidden.sum() > 10 and not result["changed"][hidden].any()
    assert torch.equal(result["rgb"][hidden], base["rgb"][hidden])
    assert result["changed"].sum() > 5  # the part beside the vase still shows
    assert torch.equal(result["changed"], silhouette["hit"] & ~hidden)


def test_reference_guidance_takes_the_composite_as_its_target_and_its_changed_share():
    from sked_ns.demo.composite_target import Primitive, composite_target, pinhole

    edit_box = _box((0.1, -0.5, 0.3), (0.5, -0.1, 0.7))
    model = _AnalyticBase(edit_box)
    guidance = ReferenceGuidanceConfig(primitive="cone", primitive_colour=(0.9, 0.1, 0.8), primitive_size=0.7).setup()
    guidance.prepare(None, "cpu", {"dataparser_transform": _Identity(), "model": model})
    view = RenderedView(image=torch.zeros(1, 3, SIZE, SIZE), camera_to_world=VASE_VIEW, focal=1.1 * SIZE,
                        direction="front")
    target, changed_colour, changed = guidance.target_image(view)
    primitive = Primitive.in_edit_box("cone", (0.9, 0.1, 0.8), (0.5, 0.5, 0.5), 0.7, edit_box)
    expected = composite_target(model, primitive, pinhole(VASE_VIEW, 1.1 * SIZE, SIZE, SIZE))
    assert torch.equal(changed[0, 0].bool(), expected["changed"]) and expected["changed"].sum() > 5
    assert torch.allclose(target[0].permute(1, 2, 0), expected["rgb"])
    base_image = expected["base"].permute(2, 0, 1)[None]
    reached = RenderedView(image=target, camera_to_world=VASE_VIEW, focal=1.1 * SIZE, direction="front",
                           base_image=base_image)
    assert float(guidance(reached, 0)["reference_loss"]) < 1e-10


@pytest.mark.parametrize("setting, flag", [
    ({"primitive_colour": (1.2, 0.0, 0.0)}, "primitive-colour"),
    ({"primitive_size": 0.0}, "primitive-size"),
    ({"primitive_centre": (0.5, 1.5, 0.5)}, "primitive-centre"),
])
def test_a_primitive_no_edit_box_holds_is_refused_in_one_line(setting, flag):
    from sked_ns.errors import SkedUserError

    with pytest.raises(SkedUserError, match=rf"^--pipeline\.model\.guidance\.{flag} [^\n]+$"):
        ReferenceGuidanceConfig(primitive="ball", target="no such scene", **setting).check()
    ReferenceGuidanceConfig(primitive="ball", target="no such scene").check()  # the known scenes are not asked


# ---- the sketches' hull as the target's solid ----------------------------------------------------------------------
class _HullBase(_AnalyticBase):
    """`_AnalyticBase` whose sketches' hull is a ball in the edit box (`in_sketch_hull`, as SkedEdit's, on points)."""

    def __init__(self, edit_box, centre, radius):
        super().__init__(edit_box)
        self.centre, self.radius = torch.tensor(centre), radius

    def in_sketch_hull(self, positions):
        return (positions - self.centre.to(positions)).norm(dim=-1) <= self.radius


def test_the_hull_target_is_the_model_s_hull_test_ray_cast():
    """Hit where the hull test holds along the ray, at its first point to the marcher's halvings; against the
    analytic ball the test is."""
    from sked_ns.demo.composite_target import SketchHull, pinhole, render_base_with_depth, target_primitive

    edit_box, centre, radius = _box((0.1, -0.5, 0.3), (0.5, -0.1, 0.7)), (0.3, -0.3, 0.5), 0.15
    model = _HullBase(edit_box, centre, radius)
    hull = target_primitive(model, "hull", (0.2, 0.3, 0.9), (0.5, 0.5, 0.5), 0.8)
    assert isinstance(hull, SketchHull)
    rays = render_base_with_depth(model, pinhole(VASE_VIEW, 1.1 * 64, 64, 64))
    origins, directions = rays["origins"].double(), rays["directions"].double()
    cast = hull.cast(origins, directions)
    # The analytic ball: |o + t d - c|^2 = r^2 (unit directions).
    offset = origins - torch.tensor(centre, dtype=torch.float64)
    b = (offset * directions).sum(dim=-1)
    disc = b * b - ((offset * offset).sum(dim=-1) - radius ** 2)
    sure = disc > 1e-3 * radius ** 2  # rays grazing the ball may miss it between two samples
    assert sure.sum() > 50 and bool(cast["hit"][sure].all()) and not bool(cast["hit"][disc < 0].any())
    exact = -b - disc.clamp_min(0).sqrt()
    step = float(np.linalg.norm(edit_box.max - edit_box.min))
    assert torch.allclose(cast["distance"][sure], exact[sure], atol=1e-3 * step)
    assert torch.equal(cast["rgb"][cast["hit"]], torch.tensor([0.2, 0.3, 0.9], dtype=torch.float64).expand(
        int(cast["hit"].sum()), 3))


def test_the_reference_guidance_takes_the_hull_as_its_primitive():
    from sked_ns.demo.composite_target import SketchHull

    model = _HullBase(_box((0.1, -0.5, 0.3), (0.5, -0.1, 0.7)), (0.3, -0.3, 0.5), 0.15)
    guidance = ReferenceGuidanceConfig(primitive="hull").setup()
    guidance.config.check()
    guidance.prepare(None, "cpu", {"dataparser_transform": _Identity(), "model": model})
    assert isinstance(guidance.primitive, SketchHull)
    view = RenderedView(image=torch.zeros(1, 3, SIZE, SIZE), camera_to_world=VASE_VIEW, focal=1.1 * SIZE,
                        direction="front")
    _, _, changed = guidance.target_image(view)
    assert 5 < int(changed.sum()) < SIZE * SIZE
