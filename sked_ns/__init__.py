"""sked_ns: SKED sketch-guided NeRF editing as a nerfstudio method."""

from sked_ns.compat import allow_numpy_in_checkpoints

# Runs at plugin import, which every ns-* command triggers through the method registry.
allow_numpy_in_checkpoints()

__version__ = "0.2.0"
