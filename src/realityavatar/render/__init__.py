"""Gaussian splatting: one stateless `rasterize` function with torch and gsplat backends, and the SH basis."""
