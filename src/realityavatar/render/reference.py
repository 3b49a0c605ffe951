"""Slow, obviously correct dense compositing (every Gaussian x every pixel) used by the tests and the benchmark."""
from __future__ import annotations

import torch

from .project import ALPHA_THRESHOLD, project_gaussians
from .tiles import T_MIN


def composite_dense_loop(means2d, conics, opacities, colors, visible, width, height, alpha_max=0.999):
    """gsplat's per-pixel kernel written literally, vectorised over pixels only. Inputs [N,...] of one camera.

    Returns premultiplied colours [H,W,D] and alphas [H,W,1].
    """
    dev, dt = means2d.device, means2d.dtype
    ys, xs = torch.meshgrid(torch.arange(height, device=dev, dtype=dt) + 0.5,
                            torch.arange(width, device=dev, dtype=dt) + 0.5, indexing="ij")
    D = colors.shape[-1]
    T = torch.ones(height, width, device=dev, dtype=dt)
    out = torch.zeros(height, width, D, device=dev, dtype=dt)
    done = torch.zeros(height, width, dtype=torch.bool, device=dev)
    # gsplat's order: increasing depth among visible Gaussians (ties keep input order)
    for i in torch.nonzero(visible).squeeze(1).tolist():
        dx = means2d[i, 0] - xs
        dy = means2d[i, 1] - ys
        a, b, c = conics[i]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opacities[i] * torch.exp(-sigma), max=alpha_max)
        use = (~done) & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
        next_T = T * (1 - alpha)
        stop = use & (next_T <= T_MIN)
        done = done | stop
        use = use & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(T))
        out = out + w[..., None] * colors[i]
        T = torch.where(use, next_T, T)
    return out, (1 - T)[..., None]


def pixel_centres(width, height, device=None, dtype=torch.float64):
    """[H*W,2] pixel centres (x+0.5, y+0.5) in row-major order."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype) + 0.5,
                            torch.arange(width, device=device, dtype=dtype) + 0.5, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)


def composite_dense_rows(means2d, conics, opacities, colors, visible, pix, alpha_max=0.999):
    """Pixels pix [P,2] against every Gaussian (depth-sorted [N,...]) as a [P,N] matrix with cumprod."""
    dx = means2d[None, :, 0] - pix[:, 0:1]  # [P,N]
    dy = means2d[None, :, 1] - pix[:, 1:2]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=alpha_max)
    ok = visible & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    alpha = alpha * ok
    t_incl = torch.cumprod(1 - alpha, dim=-1)
    alpha = alpha * (t_incl > T_MIN)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=-1)
    w = alpha * t_excl
    return w @ colors, w.sum(-1, keepdim=True)


def composite_dense_matrix(means2d, conics, opacities, colors, visible, width, height, alpha_max=0.999,
                           pixel_chunk=1024):
    """Same rules as the loop, a chunk of pixels at a time (every Gaussian x every pixel)."""
    pix = pixel_centres(width, height, means2d.device, means2d.dtype)
    outs, alphas = [], []
    for s in range(0, pix.shape[0], pixel_chunk):
        o, a = composite_dense_rows(means2d, conics, opacities, colors, visible, pix[s : s + pixel_chunk],
                                    alpha_max)
        outs.append(o)
        alphas.append(a)
    return torch.cat(outs).reshape(height, width, -1), torch.cat(alphas).reshape(height, width, 1)


def rasterize_reference(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near=0.01,
                        far=1e10, rasterize_mode="classic", backgrounds=None, alpha_max=0.999, method="loop",
                        pixel_chunk=1024):
    """Dense reference for RGB-style colours [N,D] or [C,N,D]; returns colours [C,H,W,D], alphas [C,H,W,1]."""
    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                             antialiased=rasterize_mode == "antialiased")
    C = viewmats.shape[0]
    cols = colors if colors.dim() == 3 else colors[None].expand(C, *colors.shape)
    imgs, alphas = [], []
    for c in range(C):
        order = torch.argsort(proj.depths[c], stable=True)
        args = (proj.means2d[c][order], proj.conics[c][order], proj.opacities[c][order], cols[c][order],
                proj.visible[c][order], width, height, alpha_max)
        if method == "loop":
            img, a = composite_dense_loop(*args)
        else:
            img, a = composite_dense_matrix(*args, pixel_chunk=pixel_chunk)
        if backgrounds is not None:
            img = img + (1 - a) * backgrounds[c]
        imgs.append(img)
        alphas.append(a)
    return torch.stack(imgs), torch.stack(alphas), proj
