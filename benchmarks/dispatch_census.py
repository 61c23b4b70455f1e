"""A census of what a block of torch code dispatches: compute ops and host-device syncs, counted on the CPU.

A TorchDispatchMode sits below autograd, so it sees every kernel the block would launch on a GPU (the backward
pass's too) one call at a time. On a CPU nothing synchronises, so the syncs are counted by what would synchronise
a CUDA stream:

- a scalar read of a device tensor (`.item()`, `bool(t)`, `if t.any():`, `float(t)`): `aten._local_scalar_dense`;
- an op whose output size depends on the data (`nonzero`, boolean-mask indexing `t[mask]` and `t[mask] = v`,
  `masked_select`, `unique`, `repeat_interleave` without an output size);
- a host tensor moved to the device (a pageable copy waits for the stream) or a device tensor read back
  (`.cpu()`, `.numpy()`, `.tolist()`). On a CPU `.to(device)` is a no-op that dispatches nothing, so the census
  also watches the calls themselves (a TorchFunctionMode) and tracks where each tensor lives: tensors held before
  the block (a model's parameters and buffers, passed to the census) and every op's output with a device input are
  on the device; tensors built from Python data (`torch.tensor([...])`: `aten.lift_fresh`), outputs of ops on host
  tensors only and tensors the census was not told about (plain attributes such as nerfstudio's HashEncoding
  `scalings`) are on the host. `.to(...)` of a host tensor is one copy, and its result is on the device. A host
  tensor with more than one element used directly by an op with device inputs (which a GPU would refuse) is counted
  as a copy too; one-element host tensors are passed to kernels by value and are not.

Each sync is recorded with the source line (outside torch and nerfstudio's internals when possible) that caused it.
Compute ops exclude views, metadata and factory calls that launch no kernel (`view`, `reshape` of a contiguous
tensor, `detach`, `empty`, ...).
"""

from __future__ import annotations

import collections
import contextlib
import traceback
from dataclasses import dataclass, field
from typing import Dict, Iterable, Iterator, List, Optional

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torch.utils.weak import WeakIdKeyDictionary

aten = torch.ops.aten

# Ops that launch no kernel: views, metadata, allocation without a fill.
NO_KERNEL = {
    "view", "_unsafe_view", "reshape", "expand", "permute", "transpose", "t", "squeeze", "unsqueeze", "select", "slice",
    "as_strided", "detach", "alias", "unbind", "split", "split_with_sizes", "chunk", "narrow", "diagonal", "unfold",
    "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "lift_fresh", "_reshape_alias",
    "view_as_real", "view_as_complex", "_local_scalar_dense", "is_same_size", "sym_size", "sym_stride", "sym_numel",
    "sym_storage_offset", "set_", "resize_", "_to_copy_noop", "numpy_T", "movedim", "mT", "flatten", "unflatten",
    "expand_as", "view_as", "_neg_view", "_conj", "conj", "resolve_conj", "resolve_neg", "is_nonzero",
}
# Ops whose output size depends on the data: the host waits for the device to learn it.
DATA_DEPENDENT = {"nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim", "unique_consecutive",
                  "nonzero_numpy", "argwhere"}
SKIP_FRAMES = ("/torch/", "/jaxtyping/", "/typeguard/", "dispatch_census.py", "step_census.py", "harness.py",
               "/contextlib.py", "/functools.py")


def _name(func) -> str:
    return func._schema.name.split("::")[-1]


def _tensors(values) -> List[torch.Tensor]:
    return [value for value in tree_flatten(values)[0] if isinstance(value, torch.Tensor)]


def _source_line() -> str:
    """The innermost frame of the caller's own code (not torch's, not nerfstudio's internals where a user frame
    calls them): 'path:line (function)'."""
    frames = traceback.extract_stack()[:-3]
    for frame in reversed(frames):
        if not any(skip in frame.filename for skip in SKIP_FRAMES):
            return f"{_short(frame.filename)}:{frame.lineno} ({frame.name})"
    for frame in reversed(frames):
        if "dispatch_census.py" not in frame.filename and "/torch/" not in frame.filename:
            return f"{_short(frame.filename)}:{frame.lineno} ({frame.name})"
    return "?"


def _short(path: str) -> str:
    for marker in ("/sked_ns/", "/nerfstudio/", "/benchmarks/", "/tests/", "/gsplat/", "/nerfacc/"):
        if marker in path:
            return marker.strip("/") + "/" + path.split(marker, 1)[1]
    return path


@dataclass
class Census:
    """What a block dispatched, in total and per phase."""

    compute_ops: int = 0
    syncs: int = 0
    sync_lines: Dict[str, int] = field(default_factory=collections.Counter)
    """Source line -> syncs caused there."""
    sync_kinds: Dict[str, int] = field(default_factory=collections.Counter)
    """'scalar read', 'data-dependent <op>', 'host-to-device copy' -> count."""
    op_names: Dict[str, int] = field(default_factory=collections.Counter)
    phases: Dict[str, Dict[str, int]] = field(default_factory=dict)
    """Phase -> {"compute_ops", "syncs"} (phases are named with DispatchCensus.phase)."""

    def as_dict(self, top: int = 25) -> Dict:
        return {"compute_ops": self.compute_ops, "syncs": self.syncs,
                "sync_kinds": dict(self.sync_kinds),
                "sync_lines": dict(collections.Counter(self.sync_lines).most_common(top)),
                "top_ops": dict(collections.Counter(self.op_names).most_common(top)),
                "phases": self.phases}


class DispatchCensus(TorchDispatchMode):
    """Count compute ops and would-be syncs of the code run inside `with DispatchCensus(device_tensors):`.

    `device_tensors`: the tensors held on the device before the block (parameters, buffers, cached rays); every
    other tensor from before the block counts as a host tensor.
    """

    def __init__(self, device_tensors: Iterable[torch.Tensor] = ()) -> None:
        super().__init__()
        self.census = Census()
        # By identity: a tensor's == is elementwise.
        self._device = WeakIdKeyDictionary()
        self._built_here = WeakIdKeyDictionary()
        self._phase: Optional[str] = None
        self.mark_device(device_tensors)

    def __enter__(self):
        self._moves = _Moves(self)
        self._moves.__enter__()
        return super().__enter__()

    def __exit__(self, *exc):
        result = super().__exit__(*exc)
        self._moves.__exit__(*exc)
        return result

    def moved(self, source: torch.Tensor, result, to_device: bool) -> None:
        """`source.to(device)` (to_device) or `source.cpu()`-like (not) was called, giving `result`."""
        if to_device:
            if not self._on_device(source):
                self._sync("host-to-device copy")
            for tensor in _tensors(result):
                self._device[tensor] = True
        elif self._on_device(source):
            self._sync("device-to-host copy")

    def mark_device(self, tensors: Iterable[torch.Tensor]) -> None:
        for tensor in tensors:
            if isinstance(tensor, torch.Tensor):
                self._device[tensor] = True
                if tensor.grad is not None:
                    self._device[tensor.grad] = True

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Count what runs inside under `name` too (phases nest: the innermost one counts)."""
        before, self._phase = self._phase, name
        try:
            yield
        finally:
            self._phase = before

    def _on_device(self, tensor: torch.Tensor) -> bool:
        return tensor in self._device

    def _sync(self, kind: str) -> None:
        census = self.census
        census.syncs += 1
        census.sync_kinds[kind] = census.sync_kinds.get(kind, 0) + 1
        line = _source_line()
        census.sync_lines[line] = census.sync_lines.get(line, 0) + 1
        if self._phase is not None:
            entry = census.phases.setdefault(self._phase, {"compute_ops": 0, "syncs": 0})
            entry["syncs"] += 1

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = _name(func)
        inputs = _tensors((args, kwargs))
        device_inputs = [t for t in inputs if self._on_device(t)]
        host_inputs = [t for t in inputs if not self._on_device(t)]
        if name == "_local_scalar_dense" and device_inputs:
            self._sync("scalar read")
        elif name in DATA_DEPENDENT and device_inputs:
            self._sync(f"data-dependent {name}")
        elif name in ("index", "index_put", "index_put_", "_index_put_impl_") and device_inputs:
            indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (indices or ())):
                self._sync(f"boolean-mask {name}")
        elif name == "repeat_interleave" and device_inputs and kwargs.get("output_size") is None and len(args) < 3:
            self._sync("data-dependent repeat_interleave")
        if device_inputs:
            for tensor in host_inputs:
                if tensor.numel() > 1 and name not in ("detach", "alias", "lift_fresh"):
                    self._sync("host tensor in a device op")
                    if tensor in self._built_here:
                        self._device[tensor] = True  # built inside the block: copied once, then on the device
        if name not in NO_KERNEL:
            self.census.compute_ops += 1
            self.census.op_names[name] = self.census.op_names.get(name, 0) + 1
            if self._phase is not None:
                entry = self.census.phases.setdefault(self._phase, {"compute_ops": 0, "syncs": 0})
                entry["compute_ops"] += 1
        outputs = func(*args, **kwargs)
        generator = kwargs.get("generator")
        host_factory = name == "lift_fresh" or (generator is not None and generator.device.type == "cpu")
        on_device = bool(device_inputs) or (not inputs and not host_factory)
        for tensor in _tensors(outputs):
            if on_device:
                self._device[tensor] = True
            else:
                self._built_here[tensor] = True
        return outputs


_TO_HOST = {torch.Tensor.cpu, torch.Tensor.numpy, torch.Tensor.tolist}


class _Moves(TorchFunctionMode):
    """Sees `.to(...)`, `.cuda()`, `.cpu()`, `.numpy()`, `.tolist()` even where they dispatch nothing."""

    def __init__(self, census: DispatchCensus) -> None:
        super().__init__()
        self.census = census

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        result = func(*args, **kwargs)
        source = args[0] if args and isinstance(args[0], torch.Tensor) else None
        if source is not None:
            if func is torch.Tensor.cuda or (func is torch.Tensor.to and _names_a_device(args[1:], kwargs)):
                self.census.moved(source, result, to_device=True)
            elif func in _TO_HOST:
                self.census.moved(source, result, to_device=False)
        return result


def _names_a_device(args, kwargs) -> bool:
    """Whether `.to(*args, **kwargs)` names a device (a device, a device string or another tensor), not only a
    dtype."""
    return "device" in kwargs or any(isinstance(a, (torch.device, str, torch.Tensor)) for a in args)


def module_tensors(*modules: torch.nn.Module) -> List[torch.Tensor]:
    """Parameters and buffers of modules: what `.to(device)` moves."""
    tensors: List[torch.Tensor] = []
    for module in modules:
        if module is None:
            continue
        tensors += list(module.parameters()) + list(module.buffers())
    return tensors
