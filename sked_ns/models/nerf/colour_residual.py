"""A colour residual for new content: capacity the edit owns, so what is kept never pays for it.

nerfacto's (and instant-ngp's) colour comes from one small MLP shared by the whole scene. A colour
the base never shows (a red hat on a blue-and-orange sphere) needs new weights in that MLP, and
every kept point holds them (L_pres's colour term, the photo anchor), so new parts drift to the
nearest colour the head already makes. The residual adds, in logit space,

    c(x) = sigmoid(logit(c_head(x)) + (1 - w(x)) r(x)),   r = linear(hash grid over the edit box)

with r = 0 at the start (the edit starts as the base) and no effect where w = 1 (what is kept);
what it changes is measured in docs/method.md, Colour residual.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from sked_ns.models.nerf.hash_grid import FastHashEncoding

LOGIT_EPS = 1e-4
"""Colours are clamped to [eps, 1 - eps] before the logit, so a saturated head stays finite."""


class ColourResidual(torch.nn.Module):
    """r(x): a small hash grid over the edit box (padded by a tenth of its size) and a linear layer, zero at start."""

    def __init__(self, box_min: np.ndarray, box_max: np.ndarray, num_levels: int = 8, max_res: int = 128,
                 log2_hashmap_size: int = 15) -> None:
        super().__init__()
        pad = 0.1 * (np.asarray(box_max) - np.asarray(box_min))
        self.register_buffer("box_min", torch.as_tensor(np.asarray(box_min) - pad, dtype=torch.float32))
        self.register_buffer("box_size", torch.as_tensor(np.asarray(box_max) - np.asarray(box_min) + 2 * pad,
                                                         dtype=torch.float32).clamp_min(1e-6))
        # torch implementation: a few thousand samples per step, and it runs wherever the model runs. Features start
        # at +-0.1 (nerfacto's grids: 1e-3) because the linear layer starts at zero: its first gradient is the
        # features, and with both near zero the residual would sit at its saddle for many steps.
        self.encoding = FastHashEncoding(num_levels=num_levels, min_res=4, max_res=max_res,
                                     log2_hashmap_size=log2_hashmap_size, hash_init_scale=0.1,
                                     implementation="torch")
        self.linear = torch.nn.Linear(self.encoding.get_out_dim(), 3)
        torch.nn.init.zeros_(self.linear.weight)
        torch.nn.init.zeros_(self.linear.bias)

    def forward(self, positions: Tensor) -> Tensor:
        """Logit offsets (..., 3) at world positions (..., 3); constant outside the padded box."""
        unit = ((positions.float() - self.box_min) / self.box_size).clamp(0.0, 1.0)
        return self.linear(self.encoding(unit.reshape(-1, 3))).reshape(*positions.shape[:-1], 3)

    def apply(self, rgb: Tensor, positions: Tensor, preservation_weight: Tensor) -> Tensor:
        """The head's colour moved by (1 - w) r in logit space; exactly the head's colour where w = 1 or r = 0."""
        editable = (1.0 - preservation_weight.float()).clamp(0.0, 1.0)
        # Every sample, no mask: where w = 1 the offset is 0 * r and the difference below exactly 0 (value and
        # gradient), so a step launches the same kernels and never waits to learn which samples are near.
        out = rgb.float()
        logit = torch.logit(out.clamp(LOGIT_EPS, 1.0 - LOGIT_EPS))
        # Added as a difference, so a zero residual gives the head's colour bit for bit (the edit starts as the base).
        out = out + (torch.sigmoid(logit + editable * self(positions)) - torch.sigmoid(logit))
        return out.to(rgb.dtype)
