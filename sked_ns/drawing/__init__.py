"""sked-sketch, its viewer panel, the hull check and the authors' importer."""
