"""SKED presets (installed as the package `sked_ns.configs`); each YAML file is one `ns-train` method."""
