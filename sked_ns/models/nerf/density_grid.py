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

import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.activations import trunc_exp
from torch import Tensor

BUILD_CHUNK = 1 << 18
"""Grid points per network call while the grid is built (bounds its transient memory)."""


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
        device = next(network.parameters()).device
        centres = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) / resolution
        # grid_sample's layout: (depth = z, height = y, width = x)
        z, y, x = torch.meshgrid(centres, centres, centres, indexing="ij")
        points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
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
