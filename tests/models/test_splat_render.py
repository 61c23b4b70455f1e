"""The CPU splat rasterizer against a brute-force per-pixel reference, and gsplat's conventions it must keep."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
from reference import splat_render_brute_force

from sked_ns.models.splat import projection
from sked_ns.models.splat import torch_rasterizer as splat_render
from sked_ns.models.splat.rasterize import rasterize

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import splat_agreement  # noqa: E402  (benchmarks/: only the agreement check uses it)

INPUTS = ("means", "quats", "scales", "opacities", "colors")


def make_scene(n=200, n_cameras=2, width=40, height=28, channels=3, sh_degree=None, seed=0, scale=0.12):
    generator = torch.Generator().manual_seed(seed)
    viewmats = torch.eye(4).repeat(n_cameras, 1, 1)
    viewmats[:, 2, 3] = 3.0
    viewmats[:, 0, 3] = torch.linspace(-0.4, 0.4, n_cameras)
    if n_cameras > 1:  # a turned camera too: world and camera axes differ
        angle = 0.3
        viewmats[-1, :3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    Ks = torch.tensor([[36.0, 0, width / 2], [0, 36.0, height / 2], [0, 0, 1]]).repeat(n_cameras, 1, 1)
    if sh_degree is None:
        colors = torch.rand(n, channels, generator=generator)
    else:
        colors = (torch.rand(n, (sh_degree + 1) ** 2, 3, generator=generator) - 0.5) * 0.8
    opacities = torch.rand(n, generator=generator) * 0.9 + 0.05
    opacities[::7] = 0.9999  # some alphas clamped at 0.999 at their centre: no gradient there, as in gsplat
    return dict(
        means=torch.randn(n, 3, generator=generator) * 0.6,
        quats=torch.randn(n, 4, generator=generator),
        scales=torch.rand(n, 3, generator=generator) * scale + 0.02,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
    )


def straight_camera():
    """One camera 3 units in front of the origin, looking along +z (OpenCV axes)."""
    viewmats = torch.eye(4)[None].clone()
    viewmats[0, 2, 3] = 3.0
    return viewmats


def render_both(scene, loss_weights_seed=1, **options):
    """Render with rasterize and with the reference; backward a weighted loss through both."""
    results = []
    for render_fn in (rasterize, splat_render_brute_force):
        leaves = {k: scene[k].clone().requires_grad_() for k in INPUTS}
        extra = {k: v.clone().requires_grad_() if isinstance(v, torch.Tensor) else v for k, v in options.items()}
        rest = {k: v for k, v in scene.items() if k not in INPUTS}
        render, alpha, third = render_fn(**leaves, **rest, **extra)
        means2d = third["means2d"] if isinstance(third, dict) else third
        means2d.retain_grad()
        generator = torch.Generator().manual_seed(loss_weights_seed)
        weights = torch.rand(*render.shape[:-1], render.shape[-1] + 1, generator=generator)
        (torch.cat([render, alpha], dim=-1) * weights).sum().backward()
        grads = {k: v.grad for k, v in leaves.items()}
        grads.update({k: v.grad for k, v in extra.items() if isinstance(v, torch.Tensor)})
        grads["means2d"] = torch.where((means2d.grad != 0).any(-1, keepdim=True), means2d.grad, torch.zeros_like(means2d.grad))
        results.append((render.detach(), alpha.detach(), grads))
    return results


def assert_close(ours, theirs, name, rtol=1e-3):
    if theirs is None:  # an input the mode does not use (colours in "D")
        assert ours is None or not ours.any(), name
        return
    scale = theirs.abs().max().item() if theirs.numel() else 0.0
    error = (ours - theirs).abs().max().item() if theirs.numel() else 0.0
    assert error <= rtol * scale + 1e-5, f"{name}: max error {error:.3g} (scale {scale:.3g})"


def assert_same_as_reference(scene, check_grads=True, **options):
    (render, alpha, grads), (ref_render, ref_alpha, ref_grads) = render_both(scene, **options)
    assert render.shape == ref_render.shape and alpha.shape == ref_alpha.shape
    assert ref_alpha.max() > 0.3, "the scene must cover part of the image"
    assert_close(render, ref_render, "render", rtol=1e-4)
    assert_close(alpha, ref_alpha, "alpha", rtol=1e-4)
    for key in ref_grads if check_grads else ():
        assert_close(grads[key], ref_grads[key], f"grad {key}")
    return render, alpha, grads


def test_rgb_several_cameras_with_backgrounds():
    scene = make_scene()
    render, _, grads = assert_same_as_reference(scene, backgrounds=torch.rand(2, 3))
    assert render.shape == (2, 28, 40, 3)
    # every input gets a gradient, and info["means2d"].grad (retain_grad) is dL/d(projected mean)
    assert all(g.abs().max() > 0 for g in grads.values())


@pytest.mark.parametrize("sh_degree", [1, 3])
def test_spherical_harmonics(sh_degree):
    scene = make_scene(sh_degree=sh_degree, seed=2)
    assert_same_as_reference(scene, sh_degree=sh_degree)


def test_sh_degree_below_the_coefficients_given_and_per_camera_coefficients():
    scene = make_scene(sh_degree=3, seed=3)
    assert_same_as_reference(scene, sh_degree=1)
    scene["colors"] = (torch.rand(2, 200, 4, 3, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.8
    assert_same_as_reference(scene, sh_degree=1)


def test_wrong_shapes_are_refused():
    scene = make_scene(n=10, sh_degree=1)
    with pytest.raises(ValueError, match="colors has shape"):
        rasterize(**scene, sh_degree=2)  # degree 2 needs 9 coefficients, 4 given
    scene["opacities"] = scene["opacities"][:, None]
    with pytest.raises(ValueError, match=r"opacities has shape \(10, 1\)"):
        rasterize(**scene, sh_degree=1)


def test_four_channels_and_per_camera_colours():
    # the edit model renders [rgb, 1 - w] in one pass
    scene = make_scene(channels=4, seed=4)
    assert_same_as_reference(scene, backgrounds=torch.rand(2, 4))
    scene["colors"] = torch.rand(2, 200, 4, generator=torch.Generator().manual_seed(5))
    assert_same_as_reference(scene)


@pytest.mark.parametrize("render_mode", ["D", "ED", "RGB+D", "RGB+ED"])
def test_depth_modes(render_mode):
    scene = make_scene(seed=6)
    render, _, _ = assert_same_as_reference(scene, render_mode=render_mode, backgrounds=torch.rand(2, 3))
    assert render.shape[-1] == (1 if render_mode in ("D", "ED") else 4)


def test_antialiased_mode():
    scene = make_scene(seed=7)
    assert_same_as_reference(scene, rasterize_mode="antialiased")


def test_many_chunks_and_blocks(monkeypatch):
    # tiny budgets: many chunks of tiles, lists walked a few Gaussians at a time, tiles dropping out
    monkeypatch.setattr(splat_render, "PAIR_BUDGET", 4000)
    monkeypatch.setattr(splat_render, "K_BLOCK", 9)
    scene = make_scene(n=120, width=50, height=37, seed=8)
    assert_same_as_reference(scene, backgrounds=torch.rand(2, 3))


def test_transmittance_cut_off_and_early_stop(monkeypatch):
    """Opaque layers in front of bright ones: what lies behind T <= 1e-4 must not show (gsplat's stop rule)."""
    monkeypatch.setattr(splat_render, "K_BLOCK", 8)
    n_front, n_back = 40, 40
    generator = torch.Generator().manual_seed(9)
    means = torch.cat([torch.rand(n_front, 3, generator=generator) * 0.2 - 0.1, torch.rand(n_back, 3, generator=generator) * 0.2 - 0.1])
    means[:n_front, 2] -= 1.0  # nearer the camera
    scene = make_scene(n=n_front + n_back, n_cameras=1, width=16, height=16, seed=9)
    scene.update(
        viewmats=straight_camera(),
        means=means,
        scales=torch.full((n_front + n_back, 3), 0.5),
        opacities=torch.cat([torch.full((n_front,), 0.5), torch.full((n_back,), 0.9)]),
        colors=torch.cat([torch.zeros(n_front, 3), torch.full((n_back, 3), 1000.0)]),
    )
    # (the gradients here are float32 noise around 0: the bright layers sit behind T ~ 1e-4)
    render, alpha, _ = assert_same_as_reference(scene, check_grads=False)
    # 40 layers of alpha 0.5 reach T < 1e-4 after 14: nothing of the bright layers behind may show
    assert render.max() < 1e-3
    assert torch.all(alpha > 0.9998)


def test_front_to_back_order():
    """A red Gaussian in front of a blue one shows red, whatever their order in the arrays."""
    scene = make_scene(n=2, n_cameras=1, width=16, height=16)
    scene.update(
        viewmats=straight_camera(),
        means=torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]),  # the second is nearer the camera at z = -3
        quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
        scales=torch.full((2, 3), 0.3),
        opacities=torch.tensor([0.99, 0.99]),
        colors=torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    )
    render, _, _ = assert_same_as_reference(scene)
    centre = render[0, 8, 8]
    assert centre[0] > 0.95 and centre[2] < 0.05


def test_gsplat_tile_rule_bounds_a_gaussian():
    """A Gaussian reaches no pixel outside the 16x16 tiles of its 3-sigma square, even where its alpha >= 1/255.

    Centre at x = 20 with radius 12: gsplat's tiles end at pixel 31; pixel 32 (12.5 px away) would get
    alpha ~ 0.007 > 1/255 without the rule.
    """
    sigma_px = math.sqrt(15.57)  # 2D variance + eps2d 0.3 + gsplat's 0.1 puts 3 sqrt(v1) just under 12
    scene = make_scene(n=1, n_cameras=1, width=48, height=16)
    scene.update(
        viewmats=straight_camera(),
        Ks=torch.tensor([[[40.0, 0, 20.0], [0, 40.0, 8.0], [0, 0, 1]]]),
        means=torch.zeros(1, 3),
        quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), sigma_px * 3.0 / 40.0),
        opacities=torch.tensor([0.99]),
    )
    render, alpha, info = rasterize(**scene)
    assert int(info["radii"][0, 0]) == 12
    assert 0.99 * math.exp(-0.5 * 12.5**2 / (sigma_px**2 + 0.3)) > 1 / 255
    assert alpha[0, 8, 31, 0] > 1 / 255 and alpha[0, 8, 32, 0] == 0
    assert_same_as_reference(scene)


def test_means2d_gradient_matches_finite_differences():
    """The compositor's analytic backward (means2d, conics, colours, opacities) against central differences."""
    scene = make_scene(n=12, n_cameras=1, width=20, height=20, seed=10, scale=0.3)
    radii, means2d, depths, conics, opacities = projection.project(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"], scene["Ks"], 20, 20
    )
    colors = scene["colors"][None]
    plan = splat_render._bin_tiles(means2d, radii, depths, conics, opacities, 20, 20)
    inputs = [t.detach().double().requires_grad_() for t in (means2d, conics, colors, opacities)]

    def composite(m, q, c, o):
        return splat_render._Composite.apply(m, q, c, o, plan, False)

    assert torch.autograd.gradcheck(composite, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_absgrad_sums_per_pixel_magnitudes():
    """means2d.absgrad (what splatfacto's densification reads) = sum over pixels of |per-pixel gradient|."""
    scene = make_scene(n=80, n_cameras=1, seed=12)
    pixels = [(10, 12), (14, 20), (5, 30)]
    per_pixel = []
    for row, col in pixels:
        render, _, info = rasterize(*(scene[k].clone().requires_grad_() for k in INPUTS), scene["viewmats"], scene["Ks"], 40, 28)
        info["means2d"].retain_grad()
        render[0, row, col].sum().backward()
        per_pixel.append(info["means2d"].grad.abs())
    render, _, info = rasterize(*(scene[k].clone().requires_grad_() for k in INPUTS), scene["viewmats"], scene["Ks"], 40, 28, absgrad=True)
    sum(render[0, row, col].sum() for row, col in pixels).backward()
    expected = sum(per_pixel)
    assert expected.max() > 0
    assert torch.allclose(info["means2d"].absgrad, expected, rtol=1e-4, atol=1e-7)


def test_hidden_gaussians_are_ignored():
    """Gaussians behind the camera, beyond the far plane or off the image change nothing and get no gradient."""
    scene = make_scene(n=60, n_cameras=1, seed=13)
    scene["viewmats"] = straight_camera()
    (render, alpha, _), _ = render_both(scene)
    # behind, on the camera's plane (z = 0: gsplat's torch projection divides by it), off the image, too far
    hidden = torch.tensor([[0.0, 0.0, -3.5], [0.1, 0.0, -3.0], [0.0, 0.0, -6.0], [40.0, 0.0, 0.0], [0.0, -30.0, 1.0], [0.0, 0.0, 200.0]])
    extended = dict(scene)
    n_hidden = len(hidden)
    extended.update(
        means=torch.cat([scene["means"], hidden]),
        quats=torch.cat([scene["quats"], torch.tensor([[1.0, 0, 0, 0]] * n_hidden)]),
        scales=torch.cat([scene["scales"], torch.full((n_hidden, 3), 0.3)]),
        opacities=torch.cat([scene["opacities"], torch.full((n_hidden,), 0.9)]),
        colors=torch.cat([scene["colors"], torch.ones(n_hidden, 3)]),
    )
    leaves = {k: extended[k].clone().requires_grad_() for k in INPUTS}
    render2, alpha2, info = rasterize(**leaves, viewmats=scene["viewmats"], Ks=scene["Ks"], width=40, height=28, far_plane=100.0)
    (render2.sum() + alpha2.sum()).backward()
    assert torch.equal(info["radii"][0, -n_hidden:], torch.zeros(n_hidden, dtype=torch.int32))
    assert torch.allclose(render2, render, atol=1e-6) and torch.allclose(alpha2, alpha, atol=1e-6)
    for key, leaf in leaves.items():
        assert torch.isfinite(leaf.grad).all(), key
        assert torch.all(leaf.grad[-n_hidden:] == 0), key


def test_no_gaussians_gives_the_background():
    scene = make_scene(n=0, n_cameras=2, seed=14)
    backgrounds = torch.tensor([[0.2, 0.4, 0.6], [1.0, 0.0, 0.5]])
    render, alpha, info = rasterize(**scene, backgrounds=backgrounds)
    assert render.shape == (2, 28, 40, 3) and alpha.shape == (2, 28, 40, 1)
    assert torch.equal(render, backgrounds[:, None, None, :].expand(-1, 28, 40, -1))
    assert torch.all(alpha == 0)
    assert info["radii"].shape == (2, 0)
    render, _, _ = rasterize(**scene)
    assert torch.all(render == 0)


def test_info_carries_what_gsplat_strategy_reads():
    """gsplat's DefaultStrategy (as splatfacto drives it, absgrad on) runs on the CPU path's info."""
    from gsplat.strategy import DefaultStrategy

    scene = make_scene(n=100, n_cameras=1, seed=15)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(scene[k].clone()) for k in INPUTS})
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    strategy = DefaultStrategy(absgrad=True, refine_start_iter=10**6, reset_every=10**6, verbose=False)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    render, alpha, info = rasterize(**{k: params[k] for k in INPUTS}, viewmats=scene["viewmats"], Ks=scene["Ks"], width=40, height=28, absgrad=True)
    assert info["radii"].dtype == torch.int32 and info["radii"].shape == (1, 100)
    assert info["means2d"].shape == (1, 100, 2) and info["depths"].shape == (1, 100)
    assert info["gaussian_ids"] is None and (info["width"], info["height"], info["n_cameras"]) == (40, 28, 1)
    strategy.step_pre_backward(params, optimizers, state, step=0, info=info)
    render.sum().backward()
    strategy.step_post_backward(params, optimizers, state, step=0, info=info, packed=False)
    visible = info["radii"][0] > 0
    assert torch.all(state["count"][visible] == 1) and torch.all(state["count"][~visible] == 0)
    assert state["grad2d"][visible].max() > 0


def test_radius_clip_drops_small_gaussians():
    scene = make_scene(n=100, n_cameras=1, seed=16)
    _, _, info = rasterize(**scene)
    clip = float(info["radii"].float().median())
    _, _, clipped = rasterize(**scene, radius_clip=clip)
    kept = info["radii"] > clip
    assert torch.equal(clipped["radii"] > 0, kept) and 0 < kept.sum() < 100


def test_cpu_tensors_never_reach_gsplat_cuda(monkeypatch):
    import gsplat.cuda._wrapper as wrapper
    import gsplat.rendering

    def refuse(*args, **kwargs):
        raise AssertionError("the CPU path called gsplat's CUDA wrapper")

    monkeypatch.setattr(gsplat.rendering, "rasterization", refuse)
    for name in dir(wrapper):
        if not name.startswith("_") and callable(getattr(wrapper, name)):
            monkeypatch.setattr(wrapper, name, refuse)
    scene = make_scene(n=50, sh_degree=2, seed=17)
    scene.update({k: scene[k].requires_grad_() for k in INPUTS})
    render, alpha, _ = rasterize(**scene, sh_degree=2, absgrad=True)
    (render.sum() + alpha.sum()).backward()


def test_cuda_tensors_go_to_gsplat(monkeypatch):
    """On CUDA tensors rasterize is gsplat's rasterization with packed=False (checked with a stand-in)."""
    import gsplat.rendering

    calls = []

    def stand_in(*args, **kwargs):
        calls.append(kwargs)
        return "render", "alpha", {}

    monkeypatch.setattr(gsplat.rendering, "rasterization", stand_in)

    class FakeCuda(torch.Tensor):
        is_cuda = True

    scene = make_scene(n=5, n_cameras=1)
    means = scene.pop("means").as_subclass(FakeCuda)
    assert rasterize(means, **scene, sh_degree=None, absgrad=True)[0] == "render"
    assert calls[0]["packed"] is False and calls[0]["absgrad"] is True


def test_compare_with_gsplat_runs(monkeypatch):
    """gpu_check's comparison, with the CPU path standing in for gsplat: every difference is 0."""
    import gsplat.rendering

    monkeypatch.setattr(gsplat.rendering, "rasterization", lambda *a, packed=True, **k: splat_render.rasterize_torch_defaults(*a, **k))
    result = splat_agreement.compare_with_gsplat("cpu", n_gaussians=300, width=32, height=24)
    assert {"image", "alpha", "grad_means", "grad_means2d", "absgrad", "grad_colors"} <= set(result)
    assert all(value == 0 for key, value in result.items() if not key.endswith("_scale"))
    assert result["image_scale"] > 0 and result["grad_means_scale"] > 0

    def one_percent_brighter(*args, packed=True, **kwargs):
        render, alpha, info = splat_render.rasterize_torch_defaults(*args, **kwargs)
        return render * 1.01, alpha, info

    monkeypatch.setattr(gsplat.rendering, "rasterization", one_percent_brighter)
    result = splat_agreement.compare_with_gsplat("cpu", n_gaussians=300, width=32, height=24)
    assert result["image"] > 0.005 and result["grad_means"] > 0 and result["alpha"] == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: compares with gsplat's kernels")
def test_cpu_path_matches_gsplat_cuda():
    result = splat_agreement.compare_with_gsplat("cuda")
    for key in ("image", "alpha", "grad_means", "grad_colors", "grad_opacities", "grad_means2d"):
        assert result[key] <= 1e-3 * result[f"{key}_scale"] + 1e-4, (key, result)
