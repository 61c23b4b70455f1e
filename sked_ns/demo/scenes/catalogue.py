"""Every known edit by name: the demo sphere's (tuned on), the held-out object scenes, the unbounded ones and the
capture-like one."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

from sked_ns.demo.scenes import capture, objects, sphere, unbounded
from sked_ns.demo.scenes.objects import IMAGE_SIZE, capture_poses, write_scene_dataset


def scene_named(name: str):
    """A known edit: a held-out object, unbounded or capture-like scene, or one of the demo sphere's (sphere.SCENES,
    tuned on)."""
    scenes = {**sphere.SCENES, **objects.SCENES, **unbounded.SCENES, **capture.SCENES}
    if name not in scenes:
        raise ValueError(f"no benchmark scene {name!r}; choose one of {sorted(scenes)}.")
    return scenes[name]


def write_benchmark(name: str, folder: Path, count: int = 48, size: int = IMAGE_SIZE) -> Dict[str, Path]:
    """data/ (the base's photos), target/ (the edit's ground truth at the eval cameras) and sketches/."""
    if name in unbounded.SCENES:  # their own capture: low cameras among the objects
        return unbounded.write_benchmark(name, folder, count, size)
    if name in capture.SCENES:  # photos through a lens, on an arc; `size` is the portrait frames' height
        return capture.write_benchmark(name, folder, count, size)
    return write_scene_dataset(scene_named(name), capture_poses(count), folder, size)
