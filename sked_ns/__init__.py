"""sked_ns: SKED sketch-guided NeRF editing as a nerfstudio method."""

from sked_ns.compat import allow_numpy_in_checkpoints
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, install_excepthook
from sked_ns.nerfacc_backend import install_lazy_backend

# Runs at plugin import, which every ns-* command triggers through the method registry.
allow_numpy_in_checkpoints()
install_excepthook()  # a user error prints its message alone (SKED_TRACEBACK=1 for the traceback)
# nerfacc's kernels, for any instant-ngp pipeline a command loads: built on the first kernel call.
install_lazy_backend()

__all__ = ["SkedFileNotFoundError", "SkedUserError"]
__version__ = "0.2.0"
