"""nerfstudio's torch hash grid, without a host-device copy per call: the same numbers, a fraction of the kernels.

nerfstudio 1.1.5's `HashEncoding.pytorch_fwd` (used wherever tiny-cuda-nn is absent) keeps its level scalings and
table offsets as plain tensor attributes, which `.to(device)` never moves, and builds the hash primes with
`torch.tensor(...)` at every corner: each call copies host memory to the device about 17 times, and each pageable
copy waits for the stream. It also hashes and gathers the eight cell corners one by one (about 100 kernels).

`FastHashEncoding` is a HashEncoding whose constants are device buffers (not saved: the checkpoint keeps
nerfstudio's layout) and whose eight corners are hashed, gathered and interpolated together. It makes the same
floating-point operations in the same order as nerfstudio's, so its outputs are nerfstudio's bit for bit; the
table's gradient is one scatter-add over all corners instead of eight, equal up to float32 summation order
(tests/models/test_hash_grid.py holds it to both). SKED's models switch their own hash grids to it
(`use_fast_hash_grids`); nerfstudio's class is never changed.
"""

from __future__ import annotations

import torch
from nerfstudio.field_components.encodings import HashEncoding
from torch import Tensor

PRIMES = (1, 2654435761, 805459861)
"""instant-ngp's spatial hash primes (nerfstudio's hash_fn)."""


class FastHashEncoding(HashEncoding):
    """HashEncoding with device-resident constants and the corners evaluated together (torch implementation)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.prepare()

    def prepare(self) -> "FastHashEncoding":
        """Register the constants as buffers on the table's device (a HashEncoding switched to this class calls it)."""
        device = self.hash_table.device
        levels = self.scalings.shape[0]
        self.register_buffer("level_scalings", self.scalings.reshape(levels, 1).float().to(device), persistent=False)
        self.register_buffer("level_offsets", torch.as_tensor(self.hash_offset).long().to(device), persistent=False)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.long, device=device), persistent=False)
        return self

    def pytorch_fwd(self, in_tensor: Tensor) -> Tensor:
        scaled = in_tensor[..., None, :] * self.level_scalings  # [..., L, 3]
        ceil, floor = torch.ceil(scaled).type(torch.int32), torch.floor(scaled).type(torch.int32)
        offset = scaled - floor
        # Per axis the ceiling's and the floor's hash terms: [2 (ceil, floor), ..., L] each.
        terms = torch.stack([ceil, floor]) * self.primes
        batch = terms.shape[1:-2]
        tx = terms[..., 0].reshape(2, 1, 1, *batch, -1)
        ty = terms[..., 1].reshape(1, 2, 1, *batch, -1)
        tz = terms[..., 2].reshape(1, 1, 2, *batch, -1)
        # Corners ordered (x, y, z) with ceil first: ccc ccf cfc cff fcc fcf ffc fff (nerfstudio's 0 4 1 5 3 7 2 6).
        hashed = torch.bitwise_xor(torch.bitwise_xor(tx, ty), tz).reshape(8, *batch, -1)
        hashed = hashed % self.hash_table_size + self.level_offsets
        features = self.hash_table[hashed]  # [8, ..., L, F]
        # nerfstudio's lerps in its order: x pairs (0,3) (4,7) (1,2) (5,6), then y, then z.
        ox, oy, oz = offset[..., 0:1], offset[..., 1:2], offset[..., 2:3]
        along_x = features[:4] * ox + features[4:] * (1 - ox)  # f03 f47 f12 f56
        along_y = along_x[:2] * oy + along_x[2:] * (1 - oy)  # f0312 f4756
        encoded = along_y[0] * oz + along_y[1] * (1 - oz)
        return torch.flatten(encoded, start_dim=-2, end_dim=-1)


def use_fast_hash_grids(*modules: torch.nn.Module) -> int:
    """Switch the torch-implementation HashEncodings inside `modules` to FastHashEncoding (the same weights and
    numbers; tiny-cuda-nn grids are left as they are). Returns how many were switched."""
    switched = 0
    for module in modules:
        if module is None:
            continue
        for encoding in module.modules():
            if type(encoding) is HashEncoding and encoding.tcnn_encoding is None:
                encoding.__class__ = FastHashEncoding
                encoding.prepare()
                switched += 1
    return switched
