"""Gaussian splatting: one stateless `rasterize` function with torch and gsplat backends, and the SH basis."""
from .sh import eval_sh, sh_basis
from .splat import rasterize

__all__ = ["eval_sh", "rasterize", "sh_basis"]
