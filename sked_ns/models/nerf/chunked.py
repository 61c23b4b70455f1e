"""Field evaluations in chunks, gradient-checkpointed while training: the NeRF side of a step at a fraction of its
memory.

Autograd keeps every activation of a field's forward pass (the hash grids' corner indices and
weights, the MLPs' layers) until the backward pass, and a step's backward comes only after the
guidance: over a kilobyte per sample, hundreds of samples per ray (nerfacto's proposals), tens of
thousands of rays. Checkpointed, a chunk keeps only its inputs and outputs (a few floats per
sample) and is evaluated again, one chunk at a time, when the backward pass reaches it. The
gradients are those of the plain evaluation (the same operations on the same samples). Without
autograd (the frozen base) chunks bound the evaluation's transient tensors, which for a hash grid
over a whole step's samples are gigabytes too.
"""

from __future__ import annotations

import contextlib
import math
from typing import Callable, Dict, Sequence, Union

import torch
from nerfstudio.utils.tensor_dataclass import TensorDataclass
from torch import Tensor
from torch.utils.checkpoint import checkpoint

Outputs = Union[Tensor, Dict]


def _batch_shape(batch: Union[Tensor, TensorDataclass]) -> tuple:
    # Positions are (..., 3); RaySamples carry their batch shape.
    return tuple(batch.shape[:-1]) if isinstance(batch, Tensor) else tuple(batch.shape)


def _cat(pieces: Sequence[Outputs]) -> Outputs:
    if isinstance(pieces[0], Tensor):
        return torch.cat(list(pieces))
    return {key: None if value is None else torch.cat([piece[key] for piece in pieces]) for key, value in pieces[0].items()}


@contextlib.contextmanager
def _modes(modules: Sequence[torch.nn.Module], training: Sequence[bool]):
    # The backward pass re-runs a chunk after the caller has restored its modules' modes (the average appearance
    # of random views): the re-run must see the modes of the first run.
    before = [module.training for module in modules]
    for module, mode in zip(modules, training):
        module.train(mode)
    try:
        yield
    finally:
        for module, mode in zip(modules, before):
            module.train(mode)


def chunked(function: Callable[..., Outputs], samples_per_chunk: Union[int, Callable[[], int]],
            modules: Sequence[torch.nn.Module] = ()) -> Callable[..., Outputs]:
    """`function(batch, *rest)` evaluated in gradient-checkpointed chunks of about `samples_per_chunk` samples
    along the batch's first axis (whole rows: a row of (rays, samples) is one ray), outputs concatenated.

    `batch` is positions (..., 3) or RaySamples; the outputs a tensor or a dict of tensors with the batch's leading
    axis. Without autograd (the frozen base, evaluation) the chunks are plain calls; with `samples_per_chunk` 0 it
    is `function` itself. A callable `samples_per_chunk` is read at each call (the model's config). `modules`:
    whose train/eval mode the function depends on (restored for the backward pass's re-run).
    """
    size = samples_per_chunk if callable(samples_per_chunk) else (lambda: samples_per_chunk)

    def evaluate(batch, *rest):
        chunk, shape = size(), _batch_shape(batch)
        if chunk <= 0 or len(shape) == 0 or shape[0] == 0:
            return function(batch, *rest)
        rows = max(1, chunk // max(1, math.prod(shape[1:])))
        gradients = torch.is_grad_enabled()
        if not gradients and rows >= shape[0]:
            return function(batch, *rest)
        training = [module.training for module in modules]

        def run(piece, *piece_rest):
            with _modes(modules, training):
                return function(piece, *piece_rest)

        pieces = []
        for start in range(0, shape[0], rows):
            piece_rest = [value[start:start + rows] if isinstance(value, Tensor) else value for value in rest]
            piece = batch[start:start + rows]
            pieces.append(checkpoint(run, piece, *piece_rest, use_reentrant=False) if gradients
                          else function(piece, *piece_rest))
        return pieces[0] if len(pieces) == 1 else _cat(pieces)

    return evaluate
