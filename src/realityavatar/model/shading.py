"""Shading of the posed Gaussians by light fixed in the world (`shading=irradiance`), or none (`shading=none`).

The paper's colour MLP sees the canonical view direction, the Gaussian's feature, f_mt and a per-frame latent Z_r.
Studio light is fixed in the world, so when the body turns, a canonical point's shading changes with the body's
heading; the pose features are heading-invariant, so only Z_r can carry it, and for a frame not seen in training
(novel pose) Z_r is the mean latent. Measured on the skirt-spin scene (docs/research/2026-11-23-shading-light-fixed-in-world.md): with the scene's
directional light removed, the held-out spin frames are 1.4 dB below the rest frames instead of 3.1 dB.
"""

from __future__ import annotations

import torch
from torch import nn

from realityavatar.model.skinning import check_grid_settings, diffuse_to_grid, sample_grid
from realityavatar.render import sh_basis
from realityavatar.render.sh import _C0 as SH_C0

NORMALS = ("body", "learnt")


class NoShading(nn.Module):
    """The paper's colour as it is (`shading=none`): lighting returns the colour it is given."""

    def apply(self, rgb: torch.Tensor, x_e: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
        return rgb

    def apply_sh(self, sh: torch.Tensor, x_e: torch.Tensor) -> torch.Tensor:
        return sh

    def init_from_body(self, vertices: torch.Tensor, faces: torch.Tensor, seed: int = 0) -> None:
        return None

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {}

    built = True


class IrradianceShading(nn.Module):
    """colour x E(n_w): a diffuse irradiance map over world-space normals, shared by every Gaussian (`shading=irradiance`).

    - n_c: the body's surface normal diffused into a voxel grid over canonical space (built from the body before
      step 0, like the skinning grid), looked up at the Gaussian's deformed canonical position x_e. Where the nearby
      surface normals disagree (between the legs, far from the body) their blend is short, |n_c| < 1.
    - n_w = R n_c with R the Gaussian's canonical-to-posed rotation (LBS).
    - log E(n_w) = c_0 Y_0 + |n_w| sum_{k>=1} c_k Y_k(n_w / |n_w|), real SH up to `sh_degree` (2: the 9 coefficients
      that hold a Lambertian irradiance map to ~1 %), one set per RGB channel: E > 0, and where the normal is
      undefined (|n_c| -> 0) E falls back to the average light.
    - c starts at 0 (E = 1: the paper's colour) and trains with optim.lr.shading. Geometry gets no gradient from
      the shading (x_e and R are detached): it may not move Gaussians to where their light is better.
    - `normals="learnt"`: the normal grid is a trained parameter (group `shading_normals`), starting from the body's
      diffused normals. The photometric loss reaches it through E only (x_e stays detached), so it learns the normal
      the light needs at each canonical place a Gaussian occupies: a hanging skirt's surface outside the legs, and,
      since x_e includes the decoder's offsets, the tilted surface of the flared skirt where the flare puts it.
      Looked-up normals longer than 1 are scaled back to length 1.
    """

    def __init__(self, sh_degree: int, voxel_size: float, padding: float, k: int, smooth_iters: int,
                 smooth_ramp: float, max_voxels: int, normals: str) -> None:
        super().__init__()
        if normals not in NORMALS:
            raise ValueError(f"shading.normals: expected one of {NORMALS}, got {normals!r}")
        self.normals_from = normals
        if not 1 <= int(sh_degree) <= 3:
            raise ValueError(f"shading.sh_degree: expected 1, 2 or 3 (0 would be a constant gain), got {sh_degree}")
        check_grid_settings("shading (irradiance)", voxel_size, padding, k, smooth_iters, smooth_ramp)
        self.sh_degree = int(sh_degree)
        self.voxel_size, self.padding, self.k = float(voxel_size), float(padding), int(k)
        self.smooth_iters, self.smooth_ramp, self.max_voxels = int(smooth_iters), float(smooth_ramp), int(max_voxels)
        self.coeffs = nn.Parameter(torch.zeros((self.sh_degree + 1) ** 2, 3))
        # [1,3,D,H,W] canonical normals; resized by init_from_body (and by a checkpoint's grid on load). A parameter
        # either way (the same state_dict key as the buffer it once was), trained only with normals="learnt".
        self.grid = nn.Parameter(torch.zeros(1, 3, 2, 2, 2), requires_grad=normals == "learnt")
        self.register_buffer("lo", torch.full((3,), -1.0))
        self.register_buffer("hi", torch.full((3,), 1.0))
        self.register_buffer("built", torch.tensor(False))  # set by init_from_body; restored from a checkpoint

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "grid"
        if key in state_dict and state_dict[key].shape != self.grid.shape:
            self.grid.data = torch.empty_like(state_dict[key], device=self.grid.device, dtype=self.grid.dtype)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def init_from_body(self, vertices: torch.Tensor, faces: torch.Tensor, seed: int = 0) -> dict:
        """Fill the normal grid from the body's canonical mesh (vertices [V,3], faces [F,3])."""
        normals = vertex_normals(vertices.detach().float().cpu(), faces.cpu())
        grid, lo, hi, _, _ = diffuse_to_grid(vertices, faces, normals, self.voxel_size, self.padding, self.k,
                                             self.smooth_iters, self.smooth_ramp, self.max_voxels, seed, "shading")
        self.grid.data = grid.to(self.grid).contiguous()  # the same Parameter: an optimizer holding it stays valid
        self.lo.copy_(lo.to(self.lo))
        self.hi.copy_(hi.to(self.hi))
        self.built.fill_(True)
        return {"voxels": list(grid.shape[:1:-1]), "voxel_size": self.voxel_size}

    def normals(self, x: torch.Tensor) -> torch.Tensor:
        """Canonical normals at x [...,3] -> [...,3], length <= 1 (short where nearby surface normals disagree)."""
        n = sample_grid(self.grid, self.lo, self.hi, x)
        return _at_most_unit(n) if self.normals_from == "learnt" else n  # a trained grid may grow past unit length

    def irradiance(self, n_w: torch.Tensor) -> torch.Tensor:
        """World normals [...,3] (length <= 1) -> E [...,3] > 0."""
        length = n_w.norm(dim=-1, keepdim=True)
        Y = sh_basis(self.sh_degree, n_w)  # normalises n_w; Y[...,0] is the constant band
        log_e = Y[..., :1] * self.coeffs[0] + length * (Y[..., 1:] @ self.coeffs[1:])
        return torch.exp(log_e)

    def forward(self, x_e: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
        """x_e [B,N,3] deformed canonical positions, rot [B,N,3,3] canonical-to-posed -> factor [B,N,3]."""
        n_c = self.normals(x_e.detach())
        n_w = (rot.detach() @ n_c[..., None]).squeeze(-1)
        return self.irradiance(n_w)

    def apply(self, rgb: torch.Tensor, x_e: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
        """rgb [B,N,3] lit by the light at the Gaussians' places (x_e, rot as in forward)."""
        return rgb * self(x_e, rot)

    def apply_sh(self, sh: torch.Tensor, x_e: torch.Tensor) -> torch.Tensor:
        """SH colour coefficients sh [N,K,3] (colour = max(SH + 0.5, 0), model/color.py SHColor) of Gaussians at
        canonical places x_e [1,N,3] in the rest orientation, lit: E (view-independent, > 0) scales every band, and
        the constant band takes E's share of the +0.5 offset, so max(SH' + 0.5, 0) = E max(SH + 0.5, 0)."""
        e = self(x_e, torch.eye(3, dtype=x_e.dtype, device=x_e.device).expand(*x_e.shape, 3))[0]  # [N,3]
        lit = sh * e[:, None]
        lit[:, 0] += 0.5 * (e - 1) / SH_C0
        return lit

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"shading": [self.coeffs], **({"shading_normals": [self.grid]} if self.grid.requires_grad else {})}


def _at_most_unit(n: torch.Tensor) -> torch.Tensor:
    """Vectors [...,3] longer than 1 scaled to unit length; shorter ones (where nearby normals disagree) kept."""
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1.0)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals [V,3] (unit; zero for a vertex no face uses) of a triangle mesh."""
    tri = vertices[faces.long()]  # [F,3,3]
    fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # |fn| = 2 x area
    vn = torch.zeros_like(vertices).index_add_(0, faces.long().reshape(-1), fn.repeat_interleave(3, dim=0))
    return torch.nn.functional.normalize(vn, dim=-1)
