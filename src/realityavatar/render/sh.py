"""Real spherical-harmonics basis up to degree 3 with the constants and sign convention of 3DGS / gsplat."""
from __future__ import annotations

import torch

from realityavatar.geometry import unit
from realityavatar.runtime import Table, constant

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def _monomial(*axes: int) -> int:
    """Column of the monomial prod(d[axes]) in sh_basis's features [1, d (3), d⊗d (9), d⊗d⊗d (27)]."""
    return (0, 1, 4, 13)[len(axes)] + sum(a * 3 ** (len(axes) - 1 - i) for i, a in enumerate(axes))


_X, _Y, _Z = 0, 1, 2
# Each basis function as a polynomial in (x, y, z): {band: [(coefficient, axes of the monomial)]}, gsplat's signs.
_POLYNOMIALS = {
    0: [(_C0, ())],
    1: [(-_C1, (_Y,))], 2: [(_C1, (_Z,))], 3: [(-_C1, (_X,))],
    4: [(_C2[0], (_X, _Y))], 5: [(_C2[1], (_Y, _Z))],
    6: [(2 * _C2[2], (_Z, _Z)), (-_C2[2], (_X, _X)), (-_C2[2], (_Y, _Y))],
    7: [(_C2[3], (_X, _Z))], 8: [(_C2[4], (_X, _X)), (-_C2[4], (_Y, _Y))],
    9: [(3 * _C3[0], (_X, _X, _Y)), (-_C3[0], (_Y, _Y, _Y))],
    10: [(_C3[1], (_X, _Y, _Z))],
    11: [(4 * _C3[2], (_Y, _Z, _Z)), (-_C3[2], (_X, _X, _Y)), (-_C3[2], (_Y, _Y, _Y))],
    12: [(2 * _C3[3], (_Z, _Z, _Z)), (-3 * _C3[3], (_X, _X, _Z)), (-3 * _C3[3], (_Y, _Y, _Z))],
    13: [(4 * _C3[4], (_X, _Z, _Z)), (-_C3[4], (_X, _X, _X)), (-_C3[4], (_X, _Y, _Y))],
    14: [(_C3[5], (_X, _X, _Z)), (-_C3[5], (_Y, _Y, _Z))],
    15: [(_C3[6], (_X, _X, _X)), (-3 * _C3[6], (_X, _Y, _Y))],
}
_BASIS = torch.zeros(40, 16, dtype=torch.float64)  # monomial features -> basis: one matmul instead of ~40 ops
for _band, _terms in _POLYNOMIALS.items():
    for _c, _axes in _terms:
        _BASIS[_monomial(*_axes), _band] += _c
_BASIS_BY_DEGREE = [_BASIS[: (1, 4, 13, 40)[d], : (d + 1) ** 2].contiguous() for d in range(4)]
# the constant monomial's row (a bias: the basis is one addmm of the other monomials, no column of ones) and the rest
_CONSTANT_BY_DEGREE = [Table(b[0]) for b in _BASIS_BY_DEGREE]
_LINEAR_BY_DEGREE = [Table(b[1:]) for b in _BASIS_BY_DEGREE]


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """dirs: [...,3] (normalised here) -> basis [...,(degree+1)^2], gsplat's ordering and signs.

    The monomials of the normalised direction up to `degree` times one constant matrix (_POLYNOMIALS), the constant
    monomial's row added as a bias: a handful of tensor operations (each a kernel launch on a GPU, and a node of the
    backward) for any degree."""
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"realityavatar/render/sh.py: `degree` must be in 0..3, got {degree}")
    if dirs.shape[-1] != 3:
        raise ValueError(f"realityavatar/render/sh.py: `dirs` expected [...,3], got {tuple(dirs.shape)}")
    degree = int(degree)
    if degree == 0:
        return constant(_CONSTANT_BY_DEGREE[0], dirs).expand(dirs.shape[:-1] + (1,))
    d = unit(dirs)
    feats = [d]
    for _ in range(2, degree + 1):  # d⊗d, d⊗d⊗d
        feats.append((feats[-1][..., :, None] * d[..., None, :]).flatten(-2))
    m = torch.cat(feats, -1) if degree > 1 else d
    basis = torch.addmm(constant(_CONSTANT_BY_DEGREE[degree], m), m.reshape(-1, m.shape[-1]),
                        constant(_LINEAR_BY_DEGREE[degree], m))
    return basis.reshape(m.shape[:-1] + (basis.shape[-1],))


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """coeffs: [...,K,3] with K >= (degree+1)^2 (extra bands ignored), dirs: [...,3] -> raw SH value [...,3].

    Like gsplat's `spherical_harmonics`: no +0.5 offset and no clamp here (`rasterize` adds both).
    """
    k = (int(degree) + 1) ** 2
    if coeffs.dim() < 2 or coeffs.shape[-1] != 3 or coeffs.shape[-2] < k:
        raise ValueError(
            f"realityavatar/render/sh.py: `coeffs` expected [...,K>={k},3] for degree {degree}, "
            f"got {tuple(coeffs.shape)}"
        )
    basis = sh_basis(degree, dirs)  # [...,k]
    return (basis.unsqueeze(-1) * coeffs[..., :k, :]).sum(-2)
