"""Analytic scenes (signed distance fields) for the demo, tests and benchmarks."""
