"""Rendering saved runs, the paper's metrics, novel views and sked-eval."""
