"""The edit's own capacity, only where it may act: a residual on the frozen base over the editable region's box.

Everywhere a sample's preservation weight is above keep_threshold the edit *is* the base (held_field.py), so a
trainable copy of the whole field (every hash level over the whole scene, the MLPs, the proposal networks, and
Adam's two moments for each) can change nothing there. The local edit trains only a small field over the box that
bounds the points with w <= keep_threshold (the edit box padded as the preservation falloff reaches):

    sigma_e(x) = max(0, sigma_o(x) (1 + e (m(x) - 1)) + e a(x)),   m = 2 sigmoid(d(x)),   a = s (exp(g(x)) - 1)
    c_e(x)     = sigmoid(logit(c_o(x)) + e r(x)),                     e = 1 - w(x)

with (d, g, r) a multiresolution hash grid in box coordinates and a small MLP whose last layer starts at zero, so
m = 1, a = 0, r = 0: the edit starts as the base bit for bit. m carves (it takes the base's density to 0) and a adds
mass in empty space, growing by a factor each step as nerfacto's own exp density does; s is a density per box
diagonal (the caller's choice; docs/method.md, Local edit, says why this one). Scaled by 1 - w, the residual fades to
nothing where the edit is held (w -> 1), so the edit meets the kept base without a seam and the band around the
sketches changes only as far as it may. Outside the box every output is the base's (a `torch.where` on the in-box
test, no data-dependent shape). Below 0 the clamp passes only gradients asking for more density, so emptied space
can be filled again. The grid's resolution follows the box, not the scene (`local_grid_shape`); docs/method.md,
Local edit, gives the rule and what it costs.
"""

from __future__ import annotations

import copy
import math
from typing import Dict, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.rays import RaySamples
from nerfstudio.field_components.activations import trunc_exp
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import get_normalized_directions
from torch import Tensor

from sked_ns.models.nerf.colour_residual import LOGIT_EPS
from sked_ns.models.nerf.density_grid import normalised_positions
from sked_ns.models.nerf.hash_grid import FastHashEncoding

LOCAL, LOCAL_RESIDUAL, FULL_COPY = "local", "local-residual", "full-copy"
"""The NeRF edit's representations: the base's networks moved over the box (LocalField), a residual on the base's
outputs over the box (LocalResidual: 0.8's local edit, and an edit of a local edit), or a trainable copy of the whole
base."""
MIN_LOG2_TABLE, MAX_LOG2_TABLE = 12, 15
"""Bounds of the local grid's table: at 2^15 entries a level, an edit of nerfstudio's default nerfacto (2^19) holds
a sixteenth of its base's grid."""
HIDDEN = 32
"""Width of the MLP head (nerfacto's proposal networks: 16)."""
OUTPUTS = 5
"""d (density scale), g (added density), r (three colour logits)."""
HASH_INIT_SCALE = 0.1
"""The local grid's features start uniform in +-this (docs/method.md, Local edit: Rates)."""
LOG_DENSITY_CAP = 30.0
"""LocalField's cap on the log density: e^30 is opaque over any step a renderer takes, and its products with steps and
weights stay far inside float32 (a base's own density above it, which no trained base shows, would start capped)."""
GROWTH_CAP = 15.0
"""g's ceiling in a = s (exp(g) - 1): s e^15 is opaque over any step, and exp(g) past float32's range is inf, whose
product with a kept point's 1 - w = 0 is NaN (as nerfacto's trunc_exp caps its own)."""


def local_grid_shape(base_encoding: torch.nn.Module, base_extent: float, box_size: np.ndarray) -> Dict[str, int]:
    """The local grid's levels and table from the base's grid (`base_encoding`: nerfstudio's MLPWithHashEncoding or
    HashEncoding settings; docs/method.md, Local edit).

    Resolution: as many finest cells across the box's longest side as the base's finest level has across the whole
    space its grid covers (`base_extent`), so the box's finest cell is the base's scaled by box / scene: a box a tenth
    of the scene gets ten times the base's detail there. Table: enough entries for a surface across the box at the
    base's own resolution of it (pi n^2 cells, n the base's finest cells across the box), as a power of two within
    [2^12, 2^15] and never above the base's.
    """
    levels, finest = int(base_encoding.num_levels), int(base_encoding.max_res)
    across = finest * float(np.max(box_size)) / max(base_extent, 1e-9)  # the base's finest cells across the box
    wanted = math.ceil(math.log2(max(math.pi * across * across, 1.0)))
    log2 = min(max(wanted, MIN_LOG2_TABLE), MAX_LOG2_TABLE, int(base_encoding.log2_hashmap_size))
    return {"num_levels": levels, "min_res": int(base_encoding.min_res), "max_res": max(finest, int(base_encoding.min_res)),
            "log2_hashmap_size": log2, "features_per_level": int(base_encoding.features_per_level)}


def box_grid_shape(base_encoding: torch.nn.Module, base_extent: float, box_size: np.ndarray) -> Dict[str, int]:
    """`local_grid_shape` with its coarsest level as coarse over the box as the base's is: a few cells across it, so
    one step moves the whole box's density (at the base's coarsest resolution scaled to the box the edit filled thin
    parts far faster than with as many cells across the box as the base has across the scene)."""
    shape = local_grid_shape(base_encoding, base_extent, box_size)
    share = float(np.max(box_size)) / max(base_extent, 1e-9)
    return {**shape, "min_res": min(max(2, round(int(base_encoding.min_res) * share)), shape["max_res"])}


def splits_grid_and_mlp(field: torch.nn.Module) -> bool:
    """Whether a nerfstudio field's density network is a torch hash grid followed by a torch MLP, and its colour head
    a torch MLP: `LocalField` reads the grid's features and copies the MLPs (tiny-cuda-nn fuses them)."""
    model = getattr(getattr(field, "mlp_base", None), "model", None)
    head = getattr(field, "mlp_head", None)
    return (isinstance(model, torch.nn.Sequential) and len(model) == 2 and isinstance(model[0], HashEncoding)
            and model[0].tcnn_encoding is None and getattr(model[1], "tcnn_encoding", True) is None
            and head is not None and getattr(head, "tcnn_encoding", True) is None)


def base_grid_extent(field: torch.nn.Module) -> float:
    """The model-frame width of the space a nerfstudio field's hash grid spans: its box, or for a contracted
    (unbounded) field the contraction's [-2, 2], which is the model frame inside the unit ball."""
    if getattr(field, "spatial_distortion", None) is not None:
        return 4.0
    aabb = field.aabb.detach().float().cpu()
    return float((aabb[1] - aabb[0]).max())


class LocalResidual(torch.nn.Module):
    """(d, g, r) over a box: a torch hash grid in box coordinates and an MLP head that starts at zero."""

    def __init__(self, low: np.ndarray, high: np.ndarray, shape: Dict[str, int], density_scale: float) -> None:
        super().__init__()
        bounds = np.stack([np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)])
        self.register_buffer("box", torch.as_tensor(bounds, dtype=torch.float32))
        self.shape = dict(shape)
        # Features at +-0.1 (nerfacto's 1e-3): with the head's last layer at zero the grid's first gradient is that
        # layer's, which its input's scale sets (as the colour residual). At +-1 the box filled faster but hazier.
        self.encoding = FastHashEncoding(**shape, hash_init_scale=HASH_INIT_SCALE, implementation="torch")
        self.head = torch.nn.Sequential(torch.nn.Linear(self.encoding.get_out_dim(), HIDDEN), torch.nn.ReLU(),
                                        torch.nn.Linear(HIDDEN, OUTPUTS))
        torch.nn.init.zeros_(self.head[-1].weight)
        torch.nn.init.zeros_(self.head[-1].bias)
        self.density_scale = float(density_scale)

    def forward(self, positions: Tensor) -> Tuple[Tensor, Tensor]:
        """(inside (..., 1) bool, raw outputs (..., 5)) at model-frame positions (..., 3)."""
        points = positions.detach().float()
        low, high = self.box[0], self.box[1]
        inside = ((points >= low) & (points <= high)).all(dim=-1, keepdim=True)
        unit = ((points - low) / (high - low).clamp_min(1e-9)).clamp(0.0, 1.0)
        raw = self.head(self.encoding(unit.reshape(-1, 3)).float())
        return inside, raw.reshape(*positions.shape[:-1], OUTPUTS)

    def density(self, base: Tensor, inside: Tensor, raw: Tensor, editable: Tensor) -> Tensor:
        """max(0, sigma_o m + a) (`_FloorAtZero`), each term scaled by `editable` = 1 - w; the base's density outside
        the box."""
        sigma = base.float()
        scale = 1.0 + editable * (2.0 * torch.sigmoid(raw[..., 0:1]) - 1.0)
        total = sigma * scale + editable * (self.density_scale * torch.expm1(raw[..., 1:2].clamp_max(GROWTH_CAP)))
        total = total.clamp_max(torch.finfo(base.dtype).max)  # finite in the base's precision (fp16 under autocast)
        return torch.where(inside, _FloorAtZero.apply(total), sigma).to(base.dtype)

    def colour(self, base: Tensor, inside: Tensor, raw: Tensor, editable: Tensor) -> Tensor:
        """The base's colour moved by (1 - w) r in logit space, added as a difference (r = 0 gives the base bit for
        bit)."""
        rgb = base.float()
        logit = torch.logit(rgb.clamp(LOGIT_EPS, 1.0 - LOGIT_EPS))
        moved = rgb + (torch.sigmoid(logit + editable * raw[..., 2:5]) - torch.sigmoid(logit))
        return torch.where(inside, moved, rgb).to(base.dtype)

    def density_at(self, base: Tensor, positions: Tensor, editable: Tensor) -> Tensor:
        """The edited density at positions given the base's there (samplers, occupancy grids)."""
        inside, raw = self(positions)
        return self.density(base, inside, raw, editable)

    def extra_repr(self) -> str:
        return ", ".join(f"{key}={value}" for key, value in self.shape.items())


class _FloorAtZero(torch.autograd.Function):
    """max(0, x), whose gradient below 0 still passes where it asks for more density: emptied space can be filled
    again, and a loss asking for less than empty does not drive the residual on without end."""

    @staticmethod
    def forward(ctx, total: Tensor) -> Tensor:
        ctx.save_for_backward(total)
        return total.clamp_min(0.0)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (total,) = ctx.saved_tensors
        return grad * ((total >= 0) | (grad < 0)).to(grad.dtype)


class LocalField(torch.nn.Module):
    """The base's own networks over the box: its grid's features plus a grid of changes, through trainable copies of
    its density and colour MLPs (docs/method.md, Local edit).

        h_e(x) = h_o(x) + delta(x),   (sigma_e, geo_e) = MLP_sigma'(h_e),   c_e = MLP_c'(d, geo_e, appearance)

    with h_o the frozen base's hash features, delta a hash grid in box coordinates that starts at zero and the primed
    MLPs copies of the base's that start as they are: the edit starts as the base bit for bit, and a step moves it as
    a step moves a trained copy of the whole field (the copy's MLP turns a small change of features into several
    units of log density), but only inside the box. Outside it every output is the base's (`torch.where`).
    """

    def __init__(self, low: np.ndarray, high: np.ndarray, shape: Dict[str, int], field: torch.nn.Module) -> None:
        super().__init__()
        bounds = np.stack([np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)])
        self.register_buffer("box", torch.as_tensor(bounds, dtype=torch.float32))
        self.shape = dict(shape)
        self.encoding = FastHashEncoding(**shape, implementation="torch")
        torch.nn.init.zeros_(self.encoding.hash_table)  # the base's features unchanged; its MLP copy is live already
        self.density_mlp = copy.deepcopy(field.mlp_base.model[1]).requires_grad_(True)
        self.colour_mlp = copy.deepcopy(field.mlp_head).requires_grad_(True)

    @torch.no_grad()
    def take_base_networks(self, field: torch.nn.Module) -> None:
        """The MLP copies <- the base's weights as loaded (a fresh edit; a resumed one then loads its own)."""
        self.density_mlp.load_state_dict(field.mlp_base.model[1].state_dict())
        self.colour_mlp.load_state_dict(field.mlp_head.state_dict())

    def _inside(self, positions: Tensor) -> Tuple[Tensor, Tensor]:
        points = positions.detach().float()
        low, high = self.box[0], self.box[1]
        inside = ((points >= low) & (points <= high)).all(dim=-1, keepdim=True)
        return inside, ((points - low) / (high - low).clamp_min(1e-9)).clamp(0.0, 1.0)

    def density(self, field: torch.nn.Module, positions: Tensor, added: bool = False) -> Tuple[Tensor, Tensor, Tensor]:
        """(density (..., 1), geometry features, inside (..., 1)) at positions: NerfactoField.get_density with the
        base's features moved by delta and the density MLP's copy. `added`: the density's excess over the base's
        (the base's MLP on the base's features) instead."""
        density, geometry, inside, base = self._density(field, positions, with_base=added)
        if added:
            density = (density - base[0]).clamp_min(0.0) * inside
        return density, geometry, inside

    def _density(self, field: torch.nn.Module, positions: Tensor,
                 with_base: bool) -> Tuple[Tensor, Tensor, Tensor, Optional[Tuple[Tensor, Tensor]]]:
        """`density`'s (density, geometry, inside) and, `with_base`, the base's own (density, geometry) from the same
        features (NerfactoField.get_density's, bit for bit: its log density uncapped), without gradient."""
        unit = normalised_positions(field, positions.detach())
        selector = ((unit > 0.0) & (unit < 1.0)).all(dim=-1, keepdim=True)
        unit = (unit * selector).reshape(-1, 3)
        with torch.no_grad():
            features = field.mlp_base.model[0](unit)
        inside, in_box = self._inside(positions)
        moved = features + self.encoding(in_box.reshape(-1, 3)) * inside.reshape(-1, 1)
        density, geometry = self._activate(field, self.density_mlp(moved), positions, selector)
        base = None
        if with_base:
            with torch.no_grad():
                base = self._activate(field, field.mlp_base.model[1](features), positions, selector, cap=False)
        return density, geometry, inside, base

    @staticmethod
    def _activate(field: torch.nn.Module, out: Tensor, positions: Tensor, selector: Tensor,
                  cap: bool = True) -> Tuple[Tensor, Tensor]:
        out = out.reshape(*positions.shape[:-1], -1)
        before_activation, geometry = torch.split(out, [1, out.shape[-1] - 1], dim=-1)
        # nerfstudio's trunc_exp truncates its gradient only: capped, a runaway grid of changes stays finite.
        before_activation = before_activation.to(positions)
        before_activation = before_activation.clamp_max(LOG_DENSITY_CAP) if cap else before_activation
        return field.average_init_density * trunc_exp(before_activation) * selector, geometry

    def forward(self, field: torch.nn.Module, ray_samples: RaySamples,
                with_base: bool = False) -> Tuple[Dict, Tensor, Optional[Dict]]:
        """(density and colour at the samples, inside (..., 1), and `with_base` the base's own there: NerfactoField's
        outputs from the same grid features and direction encoding, bit for bit, without gradient; else None):
        NerfactoField's outputs with the copies."""
        density, geometry, inside, base = self._density(field, ray_samples.frustums.get_positions(), with_base)
        directions = get_normalized_directions(ray_samples.frustums.directions).reshape(-1, 3)
        head_in = [field.direction_encoding(directions), geometry.reshape(directions.shape[0], -1)]
        if field.embedding_appearance is not None:  # a photo's while training, else the average or zeros (as set)
            if field.training:
                appearance = field.embedding_appearance(ray_samples.camera_indices.reshape(-1))
            else:
                appearance = field.embedding_appearance.mean(dim=0).expand(directions.shape[0], -1)
                appearance = appearance if field.use_average_appearance_embedding else torch.zeros_like(appearance)
            head_in.append(appearance)
        rgb = self.colour_mlp(torch.cat(head_in, dim=-1)).reshape(*density.shape[:-1], 3).to(directions)
        outputs = {FieldHeadNames.DENSITY: density, FieldHeadNames.RGB: rgb}
        if base is None:
            return outputs, inside, None
        base_density, base_geometry = base
        with torch.no_grad():
            head_in[1] = base_geometry.reshape(directions.shape[0], -1)
            base_rgb = field.mlp_head(torch.cat(head_in, dim=-1)).reshape(*density.shape[:-1], 3).to(directions)
        return outputs, inside, {FieldHeadNames.DENSITY: base_density, FieldHeadNames.RGB: base_rgb}

    def extra_repr(self) -> str:
        return ", ".join(f"{key}={value}" for key, value in self.shape.items())
