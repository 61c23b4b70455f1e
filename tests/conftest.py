"""Shared helpers for the tests (random cameras, masks and sketch views), the demo base fixtures, and the markers.

Tests live by layer, as the package does (tests/<layer>/). `pytest -m "not slow"` is the fast loop: a test is slow
when it trains or edits a scene (it uses one of SLOW_FIXTURES, or says @pytest.mark.slow); browser, slurm and cuda
mark tests that need Chromium, a Slurm cluster or a GPU (they skip without one).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from sked_ns.demo.scenes.sphere import look_at
from sked_ns.sketches.sketch_set import SketchView

# No test may reach a model hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Parallel workers share the cores: one thread each (and for the ns-* commands they start), or they thrash.
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


SLOW_FIXTURES = {
    # fixtures that train a base or run an edit
    "scene", "ngp_scene", "splat_scene", "splat_run", "edited", "resumed", "tiny_edit", "small_edit", "ngp_edited",
    "bounded_base", "silhouette_only", "silhouette_only_bulk", "sketch_viewer", "slurm",
}
def pytest_collection_modifyitems(config, items):
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
        if item.path.name == "test_browser.py":
            item.add_marker(pytest.mark.browser)
            item.add_marker(pytest.mark.slow)
        if "slurm" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slurm)
        if any(mark.name == "skipif" and "cuda" in str(mark.kwargs.get("reason", "")).lower()
               for mark in item.iter_markers()):
            item.add_marker(pytest.mark.cuda)


def random_pose(rng: np.random.Generator, radius_range=(1.5, 3.0)) -> np.ndarray:
    """A camera on a random sphere point looking at a random point near the origin."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    # Keep away from the look-at singularity at the poles.
    direction[2] = np.clip(direction[2], -0.9, 0.9)
    position = direction / np.linalg.norm(direction) * rng.uniform(*radius_range)
    return look_at(position, rng.uniform(-0.2, 0.2, size=3))


def random_blob_mask(rng: np.random.Generator, width: int, height: int, blobs: int = 2) -> np.ndarray:
    """A few random filled ellipses."""
    rows, cols = np.mgrid[0:height, 0:width]
    mask = np.zeros((height, width), dtype=bool)
    for _ in range(blobs):
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        ry, rx = rng.uniform(1, height / 4), rng.uniform(1, width / 4)
        mask |= ((rows + 0.5 - cy) / ry) ** 2 + ((cols + 0.5 - cx) / rx) ** 2 <= 1
    if not mask.any():
        mask[rng.integers(height), rng.integers(width)] = True
    return mask


def random_view(rng: np.random.Generator, width: int, height: int, name: str = "") -> SketchView:
    focal = rng.uniform(0.8, 1.5) * width
    return SketchView(
        mask=random_blob_mask(rng, width, height),
        camera_to_world=random_pose(rng),
        fl_x=focal,
        fl_y=focal * rng.uniform(0.9, 1.1),
        cx=width / 2 + rng.uniform(-3, 3),
        cy=height / 2 + rng.uniform(-3, 3),
        name=name,
    )


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    """The demo dataset, a tiny nerfacto base fitted to it (a real run folder) and hat sketches."""
    from sked_ns.demo.base import build_demo_base
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.sketches.sketch_set import save_sketch_set

    root = tmp_path_factory.mktemp("scene")
    demo_scene.write_demo_dataset(root / "data")
    run = build_demo_base(root / "data", root / "runs", steps=400, points_per_step=4096)
    save_sketch_set(demo_scene.demo_sketch_set(size=64), root / "sketches")
    return {"root": root, "data": root / "data", "base": run, "sketches": root / "sketches"}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def ngp_scene(scene):
    """The same dataset and sketches with a tiny instant-ngp base (occupancy grid 2 x 32^3)."""
    from sked_ns.demo.base import build_demo_base

    run = build_demo_base(scene["data"], scene["root"] / "ngp-runs", steps=400, points_per_step=4096,
                          method="instant-ngp")
    return {**scene, "base": run}
