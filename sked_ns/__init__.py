"""sked_ns: SKED sketch-guided text-based 3D editing as a nerfstudio method.

Every `ns-*` command imports this package (through nerfstudio's method registry), so what runs here runs for
stock methods too. Only three things do, each because it cannot wait for a SKED class to load
(docs/development.md lists them): old module paths stay importable for saved runs (`moved`), a SKED user
error prints as one `error:` line (the hook chains to the previous one), and torch's weights-only loader
accepts the numpy scalars every nerfstudio checkpoint holds.
"""

from sked_ns import moved
from sked_ns.compat import allow_numpy_in_checkpoints
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, install_excepthook

moved.install()  # a v0.3 config.yml names classes by their old module paths
install_excepthook()  # a user error prints its message alone (SKED_TRACEBACK=1 for the traceback)
allow_numpy_in_checkpoints()  # ns-viewer / ns-render load the checkpoint before any SKED code runs

__all__ = ["SkedFileNotFoundError", "SkedUserError"]
__version__ = "0.12.0"
