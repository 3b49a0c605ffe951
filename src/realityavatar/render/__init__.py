"""Gaussian splatting: one stateless `rasterize` function with numba (compiled CPU), pure-torch
and gsplat (CUDA) backends, the slow reference it is tested against, and the SH basis."""
from .sh import eval_sh, sh_basis
from .splat import rasterize

__all__ = ["eval_sh", "rasterize", "sh_basis"]
