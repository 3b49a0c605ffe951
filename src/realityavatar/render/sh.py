"""Real spherical-harmonics basis up to degree 3 with the constants and sign convention of 3DGS / gsplat."""
from __future__ import annotations

import torch

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


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """dirs: [...,3] (normalised here) -> basis [...,(degree+1)^2], gsplat's ordering and signs."""
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"realityavatar/render/sh.py: `degree` must be in 0..3, got {degree}")
    if dirs.shape[-1] != 3:
        raise ValueError(f"realityavatar/render/sh.py: `dirs` expected [...,3], got {tuple(dirs.shape)}")
    d = torch.nn.functional.normalize(dirs, dim=-1)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            _C2[0] * xy,
            _C2[1] * yz,
            _C2[2] * (2.0 * zz - xx - yy),
            _C2[3] * xz,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3.0 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4.0 * zz - xx - yy),
            _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            _C3[4] * x * (4.0 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


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
