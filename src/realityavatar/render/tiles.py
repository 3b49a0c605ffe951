"""Tiled front-to-back compositing in pure torch: tile lists, padded chunks and a recomputing autograd Function.

Per-pixel rules follow gsplat's rasterize_to_pixels kernels: pixel centres at +0.5, alpha = min(alpha_max,
o*exp(-sigma)), skip alpha < 1/255 or sigma < 0, stop before the Gaussian that would push transmittance to <= 1e-4.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .project import ALPHA_THRESHOLD

T_MIN = 1e-4


@dataclass
class Chunk:
    tiles: torch.Tensor  # [B] global tile ids (camera * tiles_per_image + tile)
    gidx: torch.Tensor  # [B,L] flat Gaussian ids (camera * N + n) in depth order; G (a dummy) pads
    centre: torch.Tensor  # [B,2] tile centre in pixels; coordinates are made tile-local for float32 accuracy


@dataclass
class Plan:
    chunks: list[Chunk]
    feats: torch.Tensor  # [P,6] tile-local pixel features (1, x, y, x^2, xy, y^2)
    num_tiles: int  # C * tiles_y * tiles_x
    tile_size: int
    pairs: int  # tile-Gaussian pairs kept
    elements: int  # padded pixel-Gaussian pairs evaluated per pass


def _tile_cull(mx, my, A, B, Cc, o, x0, y0, x1, y1):
    """Keep a tile-Gaussian pair only if alpha >= 1/255 somewhere in the box of its pixel centres.

    The minimum of the quadratic form over the box is exact (interior or one of the four edges), so pruning never
    changes the image. All arguments [M] tensors; the box is [x0,x1] x [y0,y1].
    """
    inside = (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)
    best = torch.full_like(mx, float("inf"))
    for xe in (x0, x1):  # vertical edges: dx fixed, minimise over dy
        dx = mx - xe
        dy = torch.clamp(-B * dx / Cc, my - y1, my - y0)
        best = torch.minimum(best, 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy)
    for ye in (y0, y1):
        dy = my - ye
        dx = torch.clamp(-B * dy / A, mx - x1, mx - x0)
        best = torch.minimum(best, 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy)
    best = torch.where(inside, torch.zeros_like(best), best)
    # small slack: a conservative test only costs work, a strict one could drop a contributing pair
    return best <= torch.log(torch.clamp(o, min=1e-30) / ALPHA_THRESHOLD) + 1e-3


@torch.no_grad()
def build_plan(
    means2d: torch.Tensor,  # [C,N,2]
    conics: torch.Tensor,  # [C,N,3]
    opacities: torch.Tensor,  # [C,N]
    depths: torch.Tensor,  # [C,N]
    radii_xy: torch.Tensor,  # [C,N,2] int, 0 = culled
    width: int,
    height: int,
    tile_size: int = 8,
    chunk_elements: int = 1 << 18,
    tile_cull: bool = True,
) -> Plan:
    dev = means2d.device
    C, N = depths.shape
    ts = int(tile_size)
    tx_n, ty_n = -(-width // ts), -(-height // ts)
    T = tx_n * ty_n
    loc = torch.arange(ts, device=dev, dtype=means2d.dtype) + 0.5 - 0.5 * ts  # pixel centres around tile centre
    py, px = torch.meshgrid(loc, loc, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    feats = torch.stack([torch.ones_like(px), px, py, px * px, px * py, py * py], dim=-1)  # [P,6]

    m = means2d.detach().reshape(C * N, 2)
    r = radii_xy.reshape(C * N, 2).to(m.dtype)
    vis = (radii_xy > 0).all(-1).reshape(C * N)
    tx0 = torch.clamp(torch.floor((m[:, 0] - r[:, 0]) / ts), 0, tx_n).long()
    tx1 = torch.clamp(torch.ceil((m[:, 0] + r[:, 0]) / ts), 0, tx_n).long()
    ty0 = torch.clamp(torch.floor((m[:, 1] - r[:, 1]) / ts), 0, ty_n).long()
    ty1 = torch.clamp(torch.ceil((m[:, 1] + r[:, 1]) / ts), 0, ty_n).long()
    w_t, h_t = (tx1 - tx0) * vis, (ty1 - ty0) * vis
    counts = w_t * h_t  # [C*N]
    total = int(counts.sum())
    empty = Plan([], feats, C * T, ts, 0, 0)
    if total == 0:
        return empty

    gid = torch.repeat_interleave(torch.arange(C * N, device=dev), counts)  # [M]
    start = torch.cumsum(counts, 0) - counts
    k = torch.arange(total, device=dev) - start[gid]
    wg = w_t[gid]
    tx = tx0[gid] + k % wg
    ty = ty0[gid] + torch.div(k, wg, rounding_mode="floor")
    cam = torch.div(gid, N, rounding_mode="floor")
    tile = cam * T + ty * tx_n + tx  # [M]

    if tile_cull:
        con = conics.detach().reshape(C * N, 3)[gid]
        x0 = (tx * ts).to(m.dtype) + 0.5
        y0 = (ty * ts).to(m.dtype) + 0.5
        x1 = torch.clamp(x0 + ts - 1, max=width - 0.5)
        y1 = torch.clamp(y0 + ts - 1, max=height - 0.5)
        mg = m[gid]
        keep = _tile_cull(
            mg[:, 0], mg[:, 1], con[:, 0], con[:, 1], con[:, 2],
            opacities.detach().reshape(C * N)[gid], x0, y0, x1, y1,
        )
        gid, tile = gid[keep], tile[keep]
        if gid.numel() == 0:
            return empty

    # depth rank inside each camera, so one integer sort orders pairs by (tile, depth)
    order = torch.argsort(depths.detach(), dim=1, stable=True)  # [C,N]
    rank = torch.empty_like(order)
    rank.scatter_(1, order, torch.arange(N, device=dev).expand(C, N))
    key = tile * N + rank.reshape(-1)[gid]
    key, perm = torch.sort(key)
    gid = gid[perm]
    tile_sorted = torch.div(key, N, rounding_mode="floor")
    tcount = torch.bincount(tile_sorted, minlength=C * T)  # [C*T]
    tstart = torch.cumsum(tcount, 0) - tcount

    # chunks of tiles with similar list lengths (longest first), each under the element budget
    nonempty = torch.nonzero(tcount > 0).squeeze(1)
    lens = tcount[nonempty]
    lens, o2 = torch.sort(lens, descending=True)
    tiles_desc = nonempty[o2]
    lens_cpu = lens.tolist()
    P = ts * ts
    chunks: list[Chunk] = []
    i, nt, elements = 0, len(lens_cpu), 0
    G = C * N
    while i < nt:
        L = lens_cpu[i]
        b = max(1, min(nt - i, chunk_elements // (L * P)))
        tl = tiles_desc[i : i + b]
        ar = torch.arange(L, device=dev)
        idx = tstart[tl][:, None] + ar[None, :]
        valid = ar[None, :] < tcount[tl][:, None]
        gidx = torch.where(valid, gid[torch.clamp(idx, max=gid.numel() - 1)], torch.full_like(idx, G))
        t_in = tl % T
        cx = ((t_in % tx_n) * ts).to(m.dtype) + 0.5 * ts
        cy = (torch.div(t_in, tx_n, rounding_mode="floor") * ts).to(m.dtype) + 0.5 * ts
        chunks.append(Chunk(tl, gidx, torch.stack([cx, cy], -1)))
        elements += b * L * P
        i += b
    return Plan(chunks, feats, C * T, ts, int(gid.numel()), elements)


def _log_alpha_coeffs(mx, my, A, B, Cc, o):
    """Q [B,6,L] with log(o) - sigma(px,py) = feats @ Q for tile-local pixels; inputs [B,L].

    Folding log(o) and the sign into Q turns o*exp(-sigma) into one matmul and one exp over [B,P,L].
    """
    logo = torch.log(torch.clamp(o, min=1e-30))  # padding rows (o = 0) end up far below 1/255
    return torch.stack(
        [logo - (0.5 * A * mx * mx + 0.5 * Cc * my * my + B * mx * my), A * mx + B * my, Cc * my + B * mx,
         -0.5 * A, -B, -0.5 * Cc],
        dim=1,
    )


def _gather(ch: Chunk, m2, con, op, col):
    g = ch.gidx
    xy = m2[g]  # [B,L,2]
    mx = xy[..., 0] - ch.centre[:, 0:1]
    my = xy[..., 1] - ch.centre[:, 1:2]
    cg = con[g]  # [B,L,3]
    return mx, my, cg[..., 0], cg[..., 1], cg[..., 2], op[g], col[g]


def _alphas(feats, Q, alpha_max, thr_below):
    """Per-pixel alpha and weights, gsplat's rules. feats [P,6], Q [B,6,L] -> dict of [B,P,L] tensors."""
    alpha = torch.matmul(feats, Q).exp_()  # o * exp(-sigma)
    alpha.clamp_(max=alpha_max)
    torch.nn.functional.threshold_(alpha, thr_below, 0.0)  # keeps alpha >= 1/255 (thr_below is just under it)
    om = 1.0 - alpha
    t = torch.cumprod(om, dim=-1)
    # gsplat stops before the Gaussian that takes T to <= 1e-4: zeroing T_incl there zeroes its weight and all later
    torch.nn.functional.threshold_(t, T_MIN, 0.0)
    t.div_(om)  # transmittance in front of each Gaussian (0 once terminated)
    w = alpha * t
    return alpha, om, t, w


class _Composite(torch.autograd.Function):
    """Tiled compositing; saves only its inputs and recomputes per chunk in backward (bounded memory)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, plan: Plan, alpha_max: float):
        # means2d [G,2], conics [G,3], opacities [G], colors [G,D]; row G is appended as a transparent dummy
        D = colors.shape[1]
        m2, con, op, col = _pad(means2d, conics, opacities, colors)
        col = torch.cat([col, torch.ones_like(col[:, :1])], dim=1)  # ones column: bmm also yields alpha
        thr_below = _just_below(ALPHA_THRESHOLD, means2d.dtype)
        out = means2d.new_zeros(plan.num_tiles, plan.tile_size**2, D + 1)
        for ch in plan.chunks:
            mx, my, A, Bc, Cc, o, c = _gather(ch, m2, con, op, col)
            _, _, _, w = _alphas(plan.feats, _log_alpha_coeffs(mx, my, A, Bc, Cc, o), alpha_max, thr_below)
            out[ch.tiles] = torch.bmm(w, c)
        ctx.save_for_backward(means2d, conics, opacities, colors)
        ctx.plan, ctx.alpha_max = plan, alpha_max
        return out[..., :D], out[..., D]

    @staticmethod
    def backward(ctx, g_img, g_acc):
        means2d, conics, opacities, colors = ctx.saved_tensors
        plan, alpha_max = ctx.plan, ctx.alpha_max
        G, D = colors.shape
        m2, con, op, col = _pad(means2d, conics, opacities, colors)
        col = torch.cat([col, torch.ones_like(col[:, :1])], dim=1)
        gout_all = torch.cat([g_img, g_acc[..., None]], dim=-1)  # [tiles,P,D+1]
        thr_below = _just_below(ALPHA_THRESHOLD, means2d.dtype)
        gm = means2d.new_zeros(G + 1, 2)
        gc = means2d.new_zeros(G + 1, 3)
        go = means2d.new_zeros(G + 1)
        gcol = means2d.new_zeros(G + 1, D + 1)
        featsT = plan.feats.t().contiguous()  # [6,P]
        for ch in plan.chunks:
            mx, my, A, Bc, Cc, o, c = _gather(ch, m2, con, op, col)
            alpha, om, t, w = _alphas(plan.feats, _log_alpha_coeffs(mx, my, A, Bc, Cc, o), alpha_max, thr_below)
            gout = gout_all[ch.tiles]  # [B,P,D+1]
            flat = ch.gidx.reshape(-1)
            gcol.index_add_(0, flat, torch.bmm(w.transpose(1, 2), gout).reshape(-1, D + 1))
            gw = torch.bmm(gout, c.transpose(1, 2))  # dL/dw [B,P,L] (colour and alpha terms)
            # dL/dalpha_i = (gw_i T_incl_i - sum_{k>i} gw_k w_k) / (1 - alpha_i); both terms vanish once terminated
            gww = gw * w
            suffix = torch.cumsum(gww, dim=-1).neg_().add_(gww.sum(-1, keepdim=True))
            ga = gw.mul_(t).sub_(suffix.div_(om))
            # d alpha / d(log o - sigma) = alpha, except where clamped at alpha_max or skipped (alpha = 0)
            torch.nn.functional.threshold_(alpha.neg_(), -alpha_max, 0.0)
            gQ = torch.matmul(featsT, ga.mul_(alpha)).neg_()  # [B,6,L] gradient wrt Q
            q0, q1, q2, q3, q4, q5 = gQ.unbind(1)
            # Q = [log o - 0.5A mx^2 - 0.5C my^2 - B mx my, A mx + B my, C my + B mx, -A/2, -B, -C/2]
            g_mx = -q0 * (A * mx + Bc * my) + q1 * A + q2 * Bc
            g_my = -q0 * (Cc * my + Bc * mx) + q1 * Bc + q2 * Cc
            g_A = -0.5 * q0 * mx * mx + q1 * mx - 0.5 * q3
            g_B = -q0 * mx * my + q1 * my + q2 * mx - q4
            g_C = -0.5 * q0 * my * my + q2 * my - 0.5 * q5
            g_o = torch.where(o > 0, q0 / torch.where(o > 0, o, torch.ones_like(o)), torch.zeros_like(o))
            gm.index_add_(0, flat, torch.stack([g_mx, g_my], -1).reshape(-1, 2))
            gc.index_add_(0, flat, torch.stack([g_A, g_B, g_C], -1).reshape(-1, 3))
            go.index_add_(0, flat, g_o.reshape(-1))
        return gm[:G], gc[:G], go[:G], gcol[:G, :D], None, None


def _just_below(x: float, dtype: torch.dtype) -> float:
    """Largest value of `dtype` below x, so that F.threshold (keeps > t) keeps values >= x."""
    return float(torch.nextafter(torch.tensor(x, dtype=dtype), torch.tensor(0.0, dtype=dtype)))


def _pad(means2d, conics, opacities, colors):
    z = means2d.new_zeros
    return (
        torch.cat([means2d.detach(), z(1, 2)]),
        torch.cat([conics.detach(), z(1, 3)]),
        torch.cat([opacities.detach(), z(1)]),
        torch.cat([colors.detach(), z(1, colors.shape[1])]),
    )


def composite_tiles(
    means2d: torch.Tensor,  # [C,N,2]
    conics: torch.Tensor,  # [C,N,3]
    opacities: torch.Tensor,  # [C,N]
    colors: torch.Tensor,  # [C,N,D]
    plan: Plan,
    width: int,
    height: int,
    alpha_max: float = 0.999,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns premultiplied colours [C,H,W,D] and alphas [C,H,W,1] (no background)."""
    C, N, D = colors.shape
    img, acc = _Composite.apply(
        means2d.reshape(C * N, 2), conics.reshape(C * N, 3), opacities.reshape(C * N),
        colors.reshape(C * N, D), plan, float(alpha_max),
    )
    ts = plan.tile_size
    tx_n, ty_n = -(-width // ts), -(-height // ts)
    img = img.reshape(C, ty_n, tx_n, ts, ts, D).permute(0, 1, 3, 2, 4, 5).reshape(C, ty_n * ts, tx_n * ts, D)
    acc = acc.reshape(C, ty_n, tx_n, ts, ts).permute(0, 1, 3, 2, 4).reshape(C, ty_n * ts, tx_n * ts, 1)
    return img[:, :height, :width], acc[:, :height, :width]
