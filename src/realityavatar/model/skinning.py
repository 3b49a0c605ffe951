"""Learned skinning: an MLP field of weights over the 24 bones, LBS of Gaussians, and the skinning loss."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import matrix_to_quat, quat_multiply, sample_surface
from realityavatar.model.encodings import FrequencyEncoding

NUM_BONES = 24


class SkinningField(nn.Module):
    """MLP on a (canonical-space) position -> softmax weights over the 24 bones.

    Positions are mapped to [-1,1] with `center`/`half_extent` before a frequency encoding, so the field does
    not depend on the body's units as long as the box covers it.
    """

    def __init__(
        self,
        hidden_dim: int = 128,
        num_layers: int = 4,
        num_freqs: int = 4,
        center: tuple[float, float, float] = (0.0, -0.3, 0.0),
        half_extent: float = 1.2,
        num_bones: int = NUM_BONES,
    ) -> None:
        super().__init__()
        self.encoding = FrequencyEncoding(num_freqs)
        # Persistent so a checkpoint carries the normalisation the weights were trained with.
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32))
        self.register_buffer("half_extent", torch.tensor(float(half_extent)))
        layers: list[nn.Module] = []
        d = self.encoding.out_dim
        for _ in range(num_layers):
            layers += [nn.Linear(d, hidden_dim), nn.ReLU(inplace=True)]
            d = hidden_dim
        layers.append(nn.Linear(d, num_bones))
        self.mlp = nn.Sequential(*layers)
        self.num_bones = num_bones

    @torch.no_grad()
    def fit_bounds(self, points: torch.Tensor, padding: float = 0.1) -> None:
        """Centre the input box on points [P,3] (e.g. the canonical Gaussians) with a relative padding."""
        lo, hi = points.min(0).values, points.max(0).values
        self.center.copy_((lo + hi) / 2)
        self.half_extent.fill_(float((hi - lo).max()) / 2 * (1 + padding))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [...,3] -> weights [...,24] (rows sum to 1)."""
        u = (x - self.center) / self.half_extent
        return torch.softmax(self.mlp(self.encoding(u)), dim=-1)


def skinning_loss(field: nn.Module, points: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Mean over points of ||field(x) - w||^2 (the paper's L_skin); points [P,3], weights [P,24]."""
    return ((field(points) - weights) ** 2).sum(-1).mean()


def pretrain_skinning(
    field: SkinningField,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    weights: torch.Tensor,
    steps: int = 300,
    batch: int = 4096,
    lr: float = 3e-3,
    seed: int = 0,
) -> float:
    """Fit the field to the body's barycentric skin weights on its canonical surface; returns the final loss."""
    gen = torch.Generator().manual_seed(seed)
    field.fit_bounds(vertices)
    pts, w = sample_surface(vertices, faces, weights, max(batch * 8, 32768), gen)
    opt = torch.optim.Adam(field.parameters(), lr=lr)
    loss = torch.tensor(float("nan"))
    for _ in range(steps):
        idx = torch.randint(0, pts.shape[0], (batch,), generator=gen).to(pts.device)
        loss = skinning_loss(field, pts[idx], w[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return float(loss.detach())


def _polar_rotation(M: torch.Tensor, iters: int = 6) -> torch.Tensor:
    """Rotation factor of the polar decomposition of M [...,3,3] by Newton's iteration X <- (X + X^-T)/2.

    X^-T is the cofactor matrix over the determinant, so this stays elementwise (no batched solver) and
    differentiable. Converges quadratically for any non-singular M with det > 0, which holds for blends of
    rotations unless two bones with nearly opposite rotations share a point.
    """
    X = M
    for _ in range(iters):
        r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
        cof = torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], -2)
        det = (r0 * cof[..., 0, :]).sum(-1)[..., None, None]
        det = torch.where(det.abs() < 1e-8, torch.full_like(det, 1e-8), det)
        X = 0.5 * (X + cof / det)
    return X


def lbs_gaussians(
    means: torch.Tensor, quats: torch.Tensor, weights: torch.Tensor, A: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linear blend skinning of Gaussians (paper eqs. for T, R_o, x_o).

    means [B,N,3] or [N,3], quats [B,N,4] or [N,4] (wxyz), weights [B,N,24] or [N,24], A [B,24,4,4]
    (canonical -> posed bone transforms) -> means_o [B,N,3], quats_o [B,N,4], rot [B,N,3,3] (R_T below; its
    transpose takes posed view directions back to canonical space for the colour model).
    Positions use the blended matrix T exactly (x_o = T x_e). The blended 3x3 block is generally not a
    rotation (it shrinks between bones that disagree); the Gaussian's rotation uses its polar rotation factor
    R_T, so R_o = R_T R_e and the Gaussian keeps its own scales (the renderer takes quaternion + scale, not a
    full covariance; the shrink/shear part of T is dropped for the covariance only).
    """
    if A.ndim != 4 or A.shape[-2:] != (4, 4):
        raise ValueError(f"lbs_gaussians: A must be [B,24,4,4], got {tuple(A.shape)}")
    B = A.shape[0]
    if means.ndim == 2:
        means = means.expand(B, -1, -1)
    if quats.ndim == 2:
        quats = quats.expand(B, -1, -1)
    if weights.ndim == 2:
        weights = weights.expand(B, -1, -1)
    R = A[:, :, :3, :3].reshape(B, A.shape[1], 9)  # [B,24,9]
    t = A[:, :, :3, 3]  # [B,24,3]
    RT = torch.bmm(weights, R).reshape(B, -1, 3, 3)  # [B,N,3,3]
    tT = torch.bmm(weights, t)  # [B,N,3]
    means_o = (RT @ means[..., None]).squeeze(-1) + tT
    rot = _polar_rotation(RT)
    quats_o = quat_multiply(matrix_to_quat(rot), F.normalize(quats, dim=-1))
    return means_o, quats_o, rot
