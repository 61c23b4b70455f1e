"""The frozen base's proposal densities sampled once on a grid: a step reads them with one interpolation.

Kept space is sampled as the base sampled it (field_edit.held_density_fn): at every proposal sample of every
render the frozen base's proposal network was evaluated beside the edit's, about as many samples again as the
edit's own proposals. The base never changes, so its proposal density is a fixed function of position: sampled
once per edit at the cell centres of a grid over the network's own normalised space (contracted space for an
unbounded nerfacto), it is then one trilinear lookup per sample. Exact at the grid's points and interpolated
between them, at the resolution of the network's finest hash level (capped by the edit's `base_proposal_grid`).
It moves where kept space is sampled, never what is rendered there (the field outputs at kept samples are the
base's own); docs/benchmarks.md (Step census) says what it changes.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.activations import trunc_exp
from torch import Tensor

BUILD_CHUNK = 1 << 18
"""Grid points per network call while the grid is built (bounds its transient memory)."""
MISSED_OPACITY = 0.01
"""AddedMassGrid: the most opacity a ray through the whole box may cross in cells left off (instant-ngp's per-cell
threshold, spread over the ray's lattice steps)."""
LOG_SCALE_BOUND = 10.0
"""HullProposal: |s| is read at most this (e^10 times the hull's density is opaque over any proposal step)."""
PROPOSAL_RATE = 5.0
"""HullProposal: s is this times its stored grid, so a step moves s this many times the hash grids' rate (docs/method.md,
Local edit: Sampling)."""


def cell_centres(resolution: int, device) -> Tensor:
    """The centres of a resolution^3 grid over [0, 1]^3, (N, 3) in grid_sample's order (z slowest, x fastest)."""
    centres = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) / resolution
    z, y, x = torch.meshgrid(centres, centres, centres, indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)


def normalised_positions(network: torch.nn.Module, positions: Tensor) -> Tensor:
    """Positions as nerfstudio's HashMLPDensityField.get_density feeds its grid: [0, 1]^3 inside its space."""
    if network.spatial_distortion is not None:
        return (network.spatial_distortion(positions) + 2.0) / 4.0
    return SceneBox.get_normalized_positions(positions, network.aabb)


class BaseDensityGrid(torch.nn.Module):
    """A frozen proposal network's density at the centres of a resolution^3 grid, read trilinearly."""

    def __init__(self, network: torch.nn.Module, resolution: int) -> None:
        super().__init__()
        self.network_space = _NetworkSpace(network)
        self.register_buffer("grid", self._sample(network, int(resolution)), persistent=False)

    @staticmethod
    @torch.no_grad()
    def _sample(network: torch.nn.Module, resolution: int) -> Tensor:
        points = cell_centres(resolution, next(network.parameters()).device)
        values = [density_at_normalised(network, chunk) for chunk in points.split(BUILD_CHUNK)]
        return torch.cat(values).reshape(1, 1, resolution, resolution, resolution)

    def forward(self, positions: Tensor, times=None) -> Tensor:
        """Density (..., 1) at world positions (..., 3), 0 outside the network's space as the network's."""
        unit = self.network_space(positions.detach()).float()
        inside = ((unit > 0.0) & (unit < 1.0)).all(dim=-1, keepdim=True)
        coordinates = (unit * 2.0 - 1.0).reshape(1, 1, 1, -1, 3)
        density = torch.nn.functional.grid_sample(self.grid, coordinates, mode="bilinear", padding_mode="border",
                                                  align_corners=False)
        return (density.reshape(*positions.shape[:-1], 1) * inside).to(positions.dtype)


class _NetworkSpace(torch.nn.Module):
    """The network's position normalisation, holding its distortion and box (not its weights)."""

    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.spatial_distortion = network.spatial_distortion
        self.register_buffer("aabb", network.aabb.detach().clone(), persistent=False)

    def forward(self, positions: Tensor) -> Tensor:
        return normalised_positions(self, positions)


def density_at_normalised(network: torch.nn.Module, unit: Tensor) -> Tensor:
    """HashMLPDensityField.get_density's tail at normalised positions (N, 3) strictly inside [0, 1]^3."""
    if not network.use_linear:
        before_activation = network.mlp_base(unit).to(unit)
    else:
        before_activation = network.linear(network.encoding(unit).to(unit))
    return network.average_init_density * trunc_exp(before_activation)


class AddedMassGrid(torch.nn.Module):
    """Where a local edit added mass to its base over its box: 1 in the cells it did, 0 elsewhere, read trilinearly.

    A LocalField edit keeps the base's proposal networks (nothing of them is trained or saved), which never saw the new
    content: the sampler adds a density on this grid's cells (nerfacto.py), so new mass is sampled where it is. Built
    from the field as it is (`refresh`) for a render outside training (training samples the whole hull); all 0
    at a fresh edit, so the edit's samples start as the base's bit for bit. A cell is on where, at any point of a
    lattice twice as fine, the excess of the edited density over the base's has an optical depth over one lattice step
    above `MISSED_OPACITY`'s share of the box's diagonal (in lattice steps), so the cells left off add up to at most
    that opacity along any ray (instant-ngp's 0.01 a step left the new part's faint rim unsampled: docs/method.md,
    Local edit). The sampler's density there is a fixed one, not the excess, whose steep values would end a
    proposal's ray at the cell's front face and hide what lies behind it.
    """

    def __init__(self, low: Tensor, high: Tensor, resolution: int) -> None:
        super().__init__()
        self.register_buffer("box", torch.stack([low, high]).float(), persistent=False)
        self.register_buffer("grid", torch.zeros(1, 1, resolution, resolution, resolution, device=low.device),
                             persistent=False)
        self.version: Optional[int] = None  # the field's parameter versions at the last refresh; None: never built

    @torch.no_grad()
    def refresh(self, added_density, version: int) -> None:
        """`added_density(positions (N, 3)) -> (N, 1)`: the edited density's excess over the base's."""
        fine = 2 * self.grid.shape[-1]
        points = self.box[0] + cell_centres(fine, self.box.device) * (self.box[1] - self.box[0])
        values = torch.cat([added_density(chunk) for chunk in points.split(BUILD_CHUNK)]).float()
        lattice_step = float((self.box[1] - self.box[0]).max()) / fine
        excess = torch.nn.functional.max_pool3d(values.reshape(1, 1, fine, fine, fine), 2)
        crossing = float((self.box[1] - self.box[0]).norm()) / lattice_step  # lattice steps on the box's diagonal
        self.grid = (excess * lattice_step > -math.log1p(-MISSED_OPACITY) / crossing).float()
        self.version = int(version)

    def forward(self, positions: Tensor) -> Tensor:
        """The grid (..., 1) at positions (..., 3), exactly 0 outside the box."""
        unit = (positions.detach().float() - self.box[0]) / (self.box[1] - self.box[0]).clamp_min(1e-9)
        inside = ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1, keepdim=True)
        value = torch.nn.functional.grid_sample(self.grid, (unit * 2.0 - 1.0).reshape(1, 1, 1, -1, 3),
                                                mode="bilinear", padding_mode="border", align_corners=False)
        return (value.reshape(*positions.shape[:-1], 1) * inside).to(positions.dtype)


class HullProposal(torch.nn.Module):
    """A LocalField edit's own share of its proposal density: exp(s(x)) times the hull's density, with s a dense grid
    of log scales over the edit box, 0 at a fresh edit (the hull's density as set: samples as before).

    The base's proposal networks never saw the new content and a local edit trains none of them, so without this its
    samples stay spread evenly through the hull: the field learns a haze that renders grainy wherever the samples fall
    elsewhere. nerfacto's interlevel loss trains s as nerfacto trains its proposal networks: the sampler's density
    moves to where the edit's weights are, so new content is sampled at its surface, in training and in every render.
    Adam moves a parameter by about its rate a step whatever the gradient's size, so s is `rate` times the stored grid:
    at the grids' rate alone s stayed within a few units over a whole edit, too little to leave the empty hull unsampled.
    """

    def __init__(self, low: Tensor, high: Tensor, resolution: int, rate: float = PROPOSAL_RATE) -> None:
        super().__init__()
        self.register_buffer("box", torch.stack([low, high]).float(), persistent=False)
        self.register_buffer("rate", torch.tensor(float(rate), device=low.device))  # saved: each edit reads its own
        self.log_scale = torch.nn.Parameter(torch.zeros(1, 1, resolution, resolution, resolution, device=low.device))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        if prefix + "log_scale" in state_dict:  # a saved grid without its rate (0.10's) read itself as s
            state_dict.setdefault(prefix + "rate", torch.ones(()))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, positions: Tensor) -> Tensor:
        """exp(s) (..., 1) at positions (..., 3); the border cells' value outside the box (the hull lies inside it)."""
        unit = (positions.detach().float() - self.box[0]) / (self.box[1] - self.box[0]).clamp_min(1e-9)
        value = torch.nn.functional.grid_sample(self.log_scale, (unit * 2.0 - 1.0).reshape(1, 1, 1, -1, 3),
                                                mode="bilinear", padding_mode="border", align_corners=False) * self.rate
        return torch.exp(value.reshape(*positions.shape[:-1], 1).clamp(-LOG_SCALE_BOUND, LOG_SCALE_BOUND)).to(positions.dtype)
