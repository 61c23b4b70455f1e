"""One viewer session from the base to an edit and back: `ns-train sked` without --sketches.

`trainer.py` is the trainer nerfstudio runs for the `sked`, `sked-fast` and `sked-quality` methods (`methods.py`
registers them): an edit trainer that opens a session when the sketches are to be drawn in its viewer. `rounds.py`
holds the session (the viewer, the rounds, each a run folder), `panel.py` its folder in the viewer.
"""
