"""Gaussian splatting: splatfacto edits and their rasterizer."""
