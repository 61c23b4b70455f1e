"""The weights a NeRF edit trains, from its options: a local edit's grid and networks, or its base's (a whole copy).

The memory plan (memory_plan.py) holds them with Adam's two moments; benchmarks/edit_size.py measured them at
nerfstudio's sizes, and tests/engine/test_memory_plan.py holds the count to that measurement.
"""

from __future__ import annotations

from sked_ns.models.registry import representation_named


def is_local(representation: str, options) -> bool:
    """Whether the edit trains a local field or residual (local_field.py) rather than a copy of its base."""
    from sked_ns.models.nerf.local_field import LOCAL, LOCAL_RESIDUAL

    return (representation_named(representation).renders == "rays"
            and getattr(options, "nerf_edit_field", None) in (LOCAL, LOCAL_RESIDUAL))


def trained_bytes(representation: str, base_bytes: float, options) -> float:
    """Bytes of the weights an edit trains: a local edit's grid at its largest table (local_field.local_grid_shape:
    the base's levels and features, its table capped) with its copies of the base's MLPs (LocalField) or its head
    (LocalResidual), else the base's (a whole copy; a splat edit's Gaussians)."""
    from sked_ns.models.nerf.local_field import HIDDEN, LOCAL_RESIDUAL, MAX_LOG2_TABLE, OUTPUTS

    if not is_local(representation, options):
        return base_bytes
    levels, features = int(getattr(options, "num_levels", 16)), int(getattr(options, "features_per_level", 2))
    table = 2 ** min(MAX_LOG2_TABLE, int(getattr(options, "log2_hashmap_size", MAX_LOG2_TABLE)))
    if options.nerf_edit_field == LOCAL_RESIDUAL:
        networks = levels * features * HIDDEN + HIDDEN + HIDDEN * OUTPUTS + OUTPUTS
    else:  # the MLPs' copies, the colour residual, and where samples follow proposals its hull proposal's grid
        networks = _copied_mlp_parameters(levels * features, options) + _colour_residual_parameters(options)
        if representation_named(representation).samples_from_proposals:
            networks += max(int(getattr(options, "hull_proposal_grid", 0)), 0) ** 3
    return 4.0 * (levels * table * features + networks)


def _colour_residual_parameters(options) -> int:
    """The colour residual's parameters (colour_residual.py builds it at one size whatever the box)."""
    from sked_ns.models.nerf.colour_residual import ColourResidual

    if not options.colour_residual:
        return 0
    return sum(parameter.numel() for parameter in ColourResidual([0.0] * 3, [1.0] * 3).parameters())


def _copied_mlp_parameters(grid_features: int, options) -> int:
    """Parameters of a NerfactoField's density MLP and colour MLP (nerfstudio's widths and depths; instant-ngp's
    config, which has no appearance_embed_dim, builds its field with the defaults and an appearance embedding 32 wide
    when use_appearance_embedding is off)."""
    def mlp(widths):  # torch Linear layers with biases
        return sum(a * b + b for a, b in zip(widths[:-1], widths[1:]))

    hidden, colour_hidden, geometry = int(getattr(options, "hidden_dim", 64)), int(getattr(options, "hidden_dim_color", 64)), 15
    if hasattr(options, "appearance_embed_dim"):  # nerfacto's config
        appearance = int(options.appearance_embed_dim) if options.use_appearance_embedding else 0
    else:
        hidden = colour_hidden = 64
        appearance = 0 if options.use_appearance_embedding else 32
    directions = 16  # spherical harmonics of degree 4
    return mlp([grid_features, hidden, 1 + geometry]) + mlp([directions + geometry + appearance, colour_hidden,
                                                             colour_hidden, 3])
