"""NeRF representations: nerfacto and instant-ngp edits."""
