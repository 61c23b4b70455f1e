"""Sketch sets, cameras, the data frame and random views: what an edit is given.

`sked_ns.sketches` was once one module, now `sked_ns.sketches.sketch_set`: its public names are still
answered here (on first use, so importing a submodule loads nothing else), for scripts and saved runs that name them.
"""


def __getattr__(name: str):
    if not name.startswith("_") and name not in _SUBMODULES:  # a submodule not yet imported is imported, not asked
        import importlib

        sketch_set = importlib.import_module("sked_ns.sketches.sketch_set")
        if hasattr(sketch_set, name):
            return getattr(sketch_set, name)
    raise AttributeError(f"module 'sked_ns.sketches' has no attribute {name!r}")


_SUBMODULES = {"cameras", "data_frame", "placement", "random_views", "sketch_set"}
