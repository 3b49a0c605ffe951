"""Slow, obviously correct projection and dense compositing (every Gaussian x every pixel), written from the
equations and independent of project.py, and the human-shaped Gaussian scene (`human_scene`) that the renderer's
tests and benchmarks draw."""
from __future__ import annotations

import math

import torch

from .project import ALPHA_THRESHOLD, Projection
from .tiles import T_MIN


def rotation_from_quat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (w, x, y, z) [N,4] -> rotation [N,3,3], the textbook formula (Shoemake 1985)."""
    w, x, y, z = torch.nn.functional.normalize(q, dim=-1).unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def project_reference(means, quats, scales, opacities, viewmat, K, width, height, near=0.01, far=1e10,
                      eps2d=0.3, antialiased=False) -> Projection:
    """EWA splatting (Zwicker et al. 2001) for one camera, one Gaussian at a time, as gsplat 1.5 states it.

    Σ = R S Sᵀ Rᵀ; camera point t = W x + w; Σ' = J W Σ Wᵀ Jᵀ + eps2d I with J the perspective Jacobian at t
    (clamped to 1.3x the field of view); conic = Σ'⁻¹; extent 3σ-ish from the opacity (gsplat's radius rule).
    Returns a Projection with a leading camera axis of 1.
    """
    N = means.shape[0]
    W, w = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    dt, dev = means.dtype, means.device
    m2d = torch.zeros(N, 2, dtype=dt, device=dev)
    con = torch.zeros(N, 3, dtype=dt, device=dev)
    dep = torch.zeros(N, dtype=dt, device=dev)
    opa = opacities.clone()
    comp = torch.ones(N, dtype=dt, device=dev)
    radii = torch.zeros(N, 2, dtype=torch.int32, device=dev)
    vis = torch.zeros(N, dtype=torch.bool, device=dev)
    Rq = rotation_from_quat(quats)
    for i in range(N):
        t = W @ means[i] + w
        if not (near <= float(t[2]) <= far):
            continue
        M = Rq[i] @ torch.diag(scales[i])
        cov3 = W @ (M @ M.T) @ W.T
        # the Jacobian is taken at t clamped to the image plus 0.3 tan(fov/2) on each side (gsplat's persp_proj)
        mx, my = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
        tx = t[2] * torch.clamp(t[0] / t[2], -(cx / fx + mx), (width - cx) / fx + mx)
        ty = t[2] * torch.clamp(t[1] / t[2], -(cy / fy + my), (height - cy) / fy + my)
        J = torch.stack([torch.stack([fx / t[2], 0 * fx, -fx * tx / t[2] ** 2]),
                         torch.stack([0 * fy, fy / t[2], -fy * ty / t[2] ** 2])])
        cov2 = J @ cov3 @ J.T
        det0 = torch.det(cov2)
        cov2 = cov2 + eps2d * torch.eye(2, dtype=dt, device=dev)
        det = torch.det(cov2)
        if float(det) <= 0:
            continue
        o = opacities[i]
        if antialiased:
            comp[i] = torch.sqrt(torch.clamp(det0 / det, min=0.0))
            o = o * comp[i]
        opa[i] = o
        if float(o) < ALPHA_THRESHOLD:
            continue
        ext = min(3.33, math.sqrt(2 * math.log(float(o) / ALPHA_THRESHOLD)))
        r = [math.ceil(ext * math.sqrt(float(cov2[0, 0]))), math.ceil(ext * math.sqrt(float(cov2[1, 1])))]
        u = torch.stack([fx * t[0] / t[2] + cx, fy * t[1] / t[2] + cy])
        if r[0] <= 0 and r[1] <= 0:
            continue
        if float(u[0]) + r[0] <= 0 or float(u[0]) - r[0] >= width or float(u[1]) + r[1] <= 0 or float(u[1]) - r[1] >= height:
            continue
        inv = torch.linalg.inv(cov2)
        m2d[i], con[i], dep[i], vis[i] = u, torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]), t[2], True
        radii[i] = torch.tensor(r, dtype=torch.int32)
    return Projection(means2d=m2d[None], conics=con[None], depths=dep[None], opacities=opa[None],
                      radii_xy=radii[None], visible=vis[None], compensations=comp[None] if antialiased else None)


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
    projs = [project_reference(means, quats, scales, opacities, viewmats[c], Ks[c], width, height, near, far,
                               antialiased=rasterize_mode == "antialiased") for c in range(viewmats.shape[0])]
    proj = Projection(**{k: (torch.cat([getattr(p, k) for p in projs]) if getattr(projs[0], k) is not None else None)
                         for k in Projection.__dataclass_fields__})
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


def human_scene(n: int, size: int, seed: int = 0, device: str = "cpu", dtype=torch.float32):
    """N Gaussians on a 1.7 m body-like shape (head, torso, arms, legs), one camera 3 m away filling the image.

    World is z-up, the person stands at the origin facing -y; scales 5-15 mm, opacities mostly high.
    Returns the positional arguments of `rasterize` minus width/height.
    """
    g = torch.Generator().manual_seed(seed)
    # (centre xyz, radii xyz) of ellipsoids; points are sampled on their surfaces in proportion to area
    parts = [
        ((0.0, 0.0, 1.62), (0.09, 0.10, 0.12)),  # head
        ((0.0, 0.0, 1.47), (0.05, 0.05, 0.06)),  # neck
        ((0.0, 0.0, 1.18), (0.18, 0.11, 0.27)),  # torso
        ((0.0, 0.0, 0.92), (0.17, 0.11, 0.12)),  # hips
        ((-0.09, 0.0, 0.45), (0.07, 0.07, 0.42)),  # legs
        ((0.09, 0.0, 0.45), (0.07, 0.07, 0.42)),
        ((-0.24, 0.0, 1.08), (0.045, 0.045, 0.33)),  # arms
        ((0.24, 0.0, 1.08), (0.045, 0.045, 0.33)),
        ((-0.09, -0.05, 0.03), (0.05, 0.11, 0.03)),  # feet
        ((0.09, -0.05, 0.03), (0.05, 0.11, 0.03)),
    ]
    centre = torch.tensor([p[0] for p in parts])
    radii = torch.tensor([p[1] for p in parts])
    # approximate ellipsoid area (Knud Thomsen) for the sampling weights
    a, b, c = radii.unbind(-1)
    pw = 1.6075
    area = 4 * math.pi * (((a * b) ** pw + (a * c) ** pw + (b * c) ** pw) / 3) ** (1 / pw)
    part = torch.multinomial(area / area.sum(), n, replacement=True, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    shell = 1.0 + 0.03 * torch.randn(n, 1, generator=g)  # a little thickness, like cloth over skin
    means = centre[part] + radii[part] * d * shell
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.005), math.log(0.015), generator=g))
    quats = torch.randn(n, 4, generator=g)
    opac = torch.where(torch.rand(n, generator=g) < 0.75, torch.empty(n).uniform_(0.6, 1.0, generator=g),
                       torch.empty(n).uniform_(0.05, 0.6, generator=g))
    colors = torch.rand(n, 3, generator=g)
    # OpenCV camera at (0,-3,0.85) looking along +y: x_cam = x, y_cam = -z, z_cam = y
    R = torch.tensor([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    campos = torch.tensor([0.0, -3.0, 0.85])
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ campos
    f = 0.92 * size * 3.0 / 1.7  # the 1.7 m person spans ~92% of the image height
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    out = [means, quats, scales, opac, colors, vm[None], K[None]]
    return [t.to(device=device, dtype=dtype) for t in out]
