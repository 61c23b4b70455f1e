"""The embedded demo and the benchmark scenes: analytic scenes with known edits, their tiny bases,
`sked-demo`, and reference guidance (renders of a known target). The method never imports from
here; reference guidance is registered as a guidance component through the entry point
`sked_ns.guidance: reference` (pyproject.toml)."""

BASES = ("nerfacto", "splatfacto")
"""The demo's base kinds (`sked-demo --base`)."""
