"""How long `sked-eval` will take, said before its long work: one small render of the edit is timed and scaled by the
pixels each part of the evaluation renders (a render's cost grows with its pixels: rays for a NeRF, tiles for splats).
On a CPU the defaults take minutes; the line names the flags that make it quicker."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, List, Tuple

from sked_ns.engine.step_time import duration

CALIBRATION_SIDE = 32
"""The timed render's longer side: enough pixels that the render's fixed cost is small beside them."""
QUICK_RESOLUTION = 128
"""--resolution and --novel-resolution of the quicker evaluation the line offers."""
OFFER_QUICKER_SECONDS = 120.0
"""Estimates above this offer the quicker resolutions."""


@dataclass
class EvalWork:
    """What an evaluation renders: each sketch and novel view with the base and the edit, the CLIP views with the edit
    (and its own base)."""

    sketch_sizes: List[Tuple[int, int]]
    novel_sizes: List[Tuple[int, int]]
    clip_views: int = 0
    clip_resolution: int = 0
    clip_base: bool = False

    def pixels(self) -> int:
        views = sum(w * h for w, h in self.sketch_sizes) + sum(w * h for w, h in self.novel_sizes)
        return 2 * views + (2 if self.clip_base else 1) * self.clip_views * self.clip_resolution ** 2

    def scaled(self, resolution: int, novel_resolution: int, old_resolution: int, old_novel: int) -> "EvalWork":
        """The same views at other resolutions (longer sides)."""
        def resize(sizes, new, old):
            return [(max(1, round(w * new / old)), max(1, round(h * new / old))) for w, h in sizes]
        return EvalWork(resize(self.sketch_sizes, resolution, old_resolution),
                        resize(self.novel_sizes, novel_resolution, old_novel),
                        self.clip_views, self.clip_resolution, self.clip_base)

    def describe(self, resolution: int, novel_resolution: int) -> str:
        parts = [f"{len(self.sketch_sizes)} sketch views at {resolution} px"]
        if self.novel_sizes:
            parts.append(f"{len(self.novel_sizes)} novel views at {novel_resolution} px")
        text = " and ".join(parts) + ", each with the base and the edit"
        if self.clip_views:
            text += f", then {self.clip_views} CLIP views at {self.clip_resolution} px if CLIP's weights load"
        return text


def seconds_per_pixel(render: Callable[[int], Tuple[int, int]]) -> float:
    """`render(side)` renders the edit at a longer side and returns the image's (width, height); the first call warms
    the model up (lazy set-up, kernels), the second is timed."""
    render(CALIBRATION_SIDE // 4)
    started = time.perf_counter()
    width, height = render(CALIBRATION_SIDE)
    return (time.perf_counter() - started) / (width * height)


def estimate_line(work: EvalWork, per_pixel: float, device: str, resolution: int, novel_resolution: int) -> str:
    """`sked-eval: about 7 min on cpu for ...`, with the quicker resolutions when it is long and they are lower."""
    seconds = work.pixels() * per_pixel
    line = (f"sked-eval: about {duration(seconds)} on {device} for {work.describe(resolution, novel_resolution)}")
    quick = (min(resolution, QUICK_RESOLUTION), min(novel_resolution, QUICK_RESOLUTION))
    if seconds > OFFER_QUICKER_SECONDS and quick != (resolution, novel_resolution):
        quicker = work.scaled(*quick, resolution, novel_resolution).pixels() * per_pixel
        line += (f"; --resolution {quick[0]} --novel-resolution {quick[1]} takes about {duration(quicker)} "
                 "(--cameras none skips the novel views)")
    return line
