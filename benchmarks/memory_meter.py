"""Exact peak of the bytes torch allocates in a block of code, on any device: torch.profiler's memory events.

Every allocation and free of torch's allocators is an event with its size; the running sum of
them, from the block's start, is what the block holds at each moment, and its maximum the block's
own peak (memory alive before the block, weights say, is not counted: add `live_tensor_bytes`).
This counts tensors only (not Python objects, not the allocator's cache), which is what a GPU's
`torch.cuda.max_memory_allocated` counts too.
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Tuple

import torch
from torch.profiler import ProfilerActivity, profile, record_function

GB = 2**30


@dataclass
class Peaks:
    """What a metered block allocated: its own peak, what it still held at its end, and each named part's peak
    above what was held when the part started (`part` blocks inside it)."""

    peak_bytes: int = 0
    end_bytes: int = 0
    parts: Dict[str, int] = field(default_factory=dict)
    parts_held_at_start: Dict[str, int] = field(default_factory=dict)

    def gb(self) -> Dict[str, float]:
        return {"peak_gb": self.peak_bytes / GB, "end_gb": self.end_bytes / GB,
                **{f"{name}_gb": value / GB for name, value in self.parts.items()}}


PART_PREFIX = "sked-part:"


@contextmanager
def part(name: str) -> Iterator[None]:
    """Marks a named part inside a `metered` block (a no-op outside one)."""
    with record_function(PART_PREFIX + name):
        yield


@contextmanager
def metered(device: str = "cpu") -> Iterator[Peaks]:
    """Meter the block's allocations on DEVICE ("cpu" or "cuda"); the Peaks are filled in when it ends."""
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    peaks = Peaks()
    gc.collect()
    with profile(activities=activities, profile_memory=True) as profiler:
        yield peaks
    events = profiler.profiler.kineto_results.events()
    wanted = "cpu" if device == "cpu" else "cuda"
    memory: List[Tuple[int, int]] = []
    spans: List[Tuple[str, int, int]] = []
    for event in events:
        name = event.name()
        if name == "[memory]":
            if str(event.device_type()).lower().endswith(wanted):
                memory.append((event.start_ns(), event.nbytes()))
        elif name.startswith(PART_PREFIX):
            spans.append((name[len(PART_PREFIX):], event.start_ns(), event.start_ns() + event.duration_ns()))
    memory.sort()
    running, times, totals = 0, [], []
    for time, nbytes in memory:
        running += nbytes
        times.append(time)
        totals.append(running)
    peaks.peak_bytes = max([0, *totals])
    peaks.end_bytes = running
    for name, start, end in spans:
        before = _held_at(times, totals, start)
        inside = [total for time, total in zip(times, totals) if start <= time <= end]
        peaks.parts[name] = max(peaks.parts.get(name, 0), max([before, *inside]) - before)
        peaks.parts_held_at_start[name] = before


def _held_at(times: List[int], totals: List[int], moment: int) -> int:
    held = 0
    for time, total in zip(times, totals):
        if time > moment:
            break
        held = total
    return held


def live_tensor_bytes(*roots: object) -> int:
    """Bytes of the distinct storages of every tensor reachable from ROOTS (modules, optimisers, dicts, lists);
    with no roots, of every tensor the garbage collector sees."""
    seen: Dict[int, int] = {}

    def add(tensor: torch.Tensor) -> None:
        storage = tensor.untyped_storage()
        seen[storage.data_ptr()] = storage.nbytes()

    def walk(value: object, depth: int = 0) -> None:
        if depth > 6:
            return
        if isinstance(value, torch.Tensor):
            add(value)
            if value.grad is not None:
                add(value.grad)
        elif isinstance(value, torch.nn.Module):
            for tensor in list(value.parameters()) + list(value.buffers()):
                walk(tensor, depth + 1)
        elif isinstance(value, torch.optim.Optimizer):
            for group in value.param_groups:
                walk(group["params"], depth + 1)
            walk(list(value.state.values()), depth + 1)
        elif isinstance(value, dict):
            for item in value.values():
                walk(item, depth + 1)
        elif isinstance(value, (list, tuple)):
            for item in value:
                walk(item, depth + 1)

    if roots:
        for root in roots:
            walk(root)
    else:
        for value in gc.get_objects():
            if isinstance(value, torch.Tensor):
                add(value)
    return sum(seen.values())


def optional_gb(value: Optional[int]) -> Optional[float]:
    return None if value is None else value / GB
