"""Sketch sets, cameras, the data frame and random views: what an edit is given."""
