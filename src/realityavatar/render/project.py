"""EWA projection of 3D Gaussians to screen space with gsplat 1.5's culling rules (pure torch, any device)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from realityavatar.geometry import (
    quat_to_matrix as quat_to_rotmat,  # one quaternion convention (wxyz) project-wide
)

ALPHA_THRESHOLD = 1.0 / 255.0


@dataclass
class Projection:
    means2d: torch.Tensor  # [C,N,2] pixels (0 where culled)
    conics: torch.Tensor  # [C,N,3] upper triangle (a, b, c) of the inverse blurred 2D covariance
    depths: torch.Tensor  # [C,N] camera-space z (0 where culled)
    opacities: torch.Tensor  # [C,N] opacity used for compositing (times compensation when antialiased)
    radii_xy: torch.Tensor  # [C,N,2] int32 pixel half-extents, 0 = culled
    visible: torch.Tensor  # [C,N] bool
    compensations: torch.Tensor | None  # [C,N] antialiasing factor, None in classic mode


def project_gaussians(
    means: torch.Tensor,  # [N,3]
    quats: torch.Tensor,  # [N,4]
    scales: torch.Tensor,  # [N,3]
    opacities: torch.Tensor,  # [N]
    viewmats: torch.Tensor,  # [C,4,4]
    Ks: torch.Tensor,  # [C,3,3]
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    antialiased: bool = False,
) -> Projection:
    R = viewmats[:, :3, :3]  # [C,3,3]
    t = viewmats[:, :3, 3]  # [C,3]
    means_c = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C,N,3]
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N,3,3] = R_q S
    cov = M @ M.transpose(-1, -2)  # [N,3,3]
    cov_c = torch.einsum("cij,njk,clk->cnil", R, cov, R)  # [C,N,3,3]

    x, y, z = means_c.unbind(-1)  # [C,N]
    in_range = (z >= near) & (z <= far)
    z = torch.where(in_range, z, torch.ones_like(z))  # keeps culled entries finite (no NaN gradients)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C,1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    rz = 1.0 / z
    # The Jacobian is evaluated at a point clamped to 1.3x the frustum, as in gsplat's persp_proj.
    tx = z * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
    ty = z * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
    zero = torch.zeros_like(z)
    J = torch.stack(
        [fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1
    ).reshape(*z.shape, 2, 3)  # [C,N,2,3]
    cov2d = J @ cov_c @ J.transpose(-1, -2)  # [C,N,2,2]
    mean2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C,N,2]

    a, b, c = cov2d[..., 0, 0], 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]), cov2d[..., 1, 1]
    det_orig = a * c - b * b
    a = a + eps2d
    c = c + eps2d
    det = a * c - b * b
    visible = in_range & (det > 0)
    det = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)  # [C,N,3]

    compensations = None
    opac = opacities[None, :].expand(z.shape)
    if antialiased:
        compensations = torch.sqrt(torch.clamp(det_orig / det, min=0.0))
        opac = opac * compensations

    with torch.no_grad():
        o = opac.detach()
        visible = visible & (o >= ALPHA_THRESHOLD)
        extend = torch.clamp(torch.sqrt(2.0 * torch.log(torch.clamp(o, min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD)), max=3.33)
        rx = torch.ceil(extend * torch.sqrt(torch.clamp(a.detach(), min=0.0)))
        ry = torch.ceil(extend * torch.sqrt(torch.clamp(c.detach(), min=0.0)))
        visible = visible & (~((rx <= radius_clip) & (ry <= radius_clip)))
        mx, my = mean2d.detach().unbind(-1)
        visible = visible & (~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height)))
        # A non-finite Gaussian is culled here, so the rasterizer never sees one (training checks its inputs only on
        # log steps; a non-finite loss stops the run there).
        visible = visible & torch.isfinite(rx) & torch.isfinite(ry) & torch.isfinite(mx) & torch.isfinite(my)
        radii_xy = torch.stack([rx, ry], dim=-1).nan_to_num(0.0).to(torch.int32) * visible[..., None]

    vis_f = visible[..., None]
    return Projection(
        means2d=torch.where(vis_f, mean2d, torch.zeros_like(mean2d)),
        conics=torch.where(vis_f, conics, torch.zeros_like(conics)),
        depths=torch.where(visible, means_c[..., 2], torch.zeros_like(z)),
        opacities=opac,
        radii_xy=radii_xy,
        visible=visible,
        compensations=compensations,
    )
