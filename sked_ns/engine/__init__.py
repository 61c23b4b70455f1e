"""nerfstudio glue: presets, trainer, pipeline, datamanager, the base scene, resume."""
