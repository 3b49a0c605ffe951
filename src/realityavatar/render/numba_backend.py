"""Compiled CPU renderer (Numba): EWA projection, tile binning and compositing, each with its backward.

Same per-pixel rules as tiles.py and gsplat's rasterize_to_pixels: pixel centres at +0.5, alpha = min(alpha_max,
o*exp(-sigma)), skip sigma < 0 or alpha < 1/255, stop before the Gaussian that takes T to <= 1e-4. Arithmetic is
float64 inside the kernels whatever the input dtype; exp is glibc's algorithm inlined (_exp_core: libm's values here).
The backward walks each pixel's list back to front from its last contributing Gaussian (gsplat's backward), so
forward keeps only the final T and that index per pixel.
Gradients go to per-pair slots (one tile = one thread, no races) and are summed per Gaussian in a second pass,
so results do not depend on the thread count. The projection follows project.py (float64 inside as well).
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

try:  # the torch backend stays the fallback where numba cannot be imported
    import numba
    from llvmlite import ir as _ir
    from numba import njit, prange
    from numba import types as _types
    from numba.extending import intrinsic

    NUMBA_ERROR: str | None = None
    # numba's OpenMP layer shares libgomp with torch: with a pool of 2 it made torch's own ops (and the kernels) 4x
    # slower in CPU time at 1 thread here. The workqueue layer does not interfere. NUMBA_THREADING_LAYER still wins.
    if "NUMBA_THREADING_LAYER" not in __import__("os").environ:
        numba.config.THREADING_LAYER = "workqueue"
except Exception as exc:  # noqa: BLE001 - ImportError or a broken llvmlite: any means fall back
    numba = None
    NUMBA_ERROR = f"{type(exc).__name__}: {exc}"

    def njit(*args, **kwargs):  # keeps the module importable; the kernels are never called
        return (lambda f: f) if not args or not callable(args[0]) else args[0]

    prange = range
    intrinsic = njit

ALPHA_THRESHOLD = 1.0 / 255.0
T_MIN = 1e-4
# sigma above log(255*o) + slack means alpha < 1/255 whatever the rounding, so exp() is skipped there;
# pixels below it still take the exact alpha test.
_SIGMA_SLACK = 1e-6
_PIX_EPS = 1e-3  # pixels: row/column bounds of an ellipse are widened by this much against rounding


# ---- exp inline: glibc's algorithm, so the values are libm's while the compositing loops avoid a call per pixel ----
# A call to libm's exp inside the pixel loops cost more than the exp itself (every live value spilled around it).
# _exp_core is glibc's exp (ARM optimized-routines, e_exp.c with EXP_TABLE_BITS = 7): x = k*ln2/128 + r,
# exp(x) = 2^(k/128) * (1 + tail_k + r + r^2*poly(r)), with the FMAs of the x86-64 FMA build; it matched math.exp
# bit for bit on 5e7 random arguments in [-745, 710] here. Valid for |x| < 700 (callers check), NaN-safe in _exp_sigma.


@intrinsic
def _fma(typingctx, a, b, c):
    """a*b + c rounded once (llvm.fma)."""
    sig = _types.float64(_types.float64, _types.float64, _types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@intrinsic
def _as_f64(typingctx, x):
    """The float64 whose bits are the int64 x."""
    sig = _types.float64(_types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], _ir.DoubleType())

    return sig, codegen


def _exp_table() -> tuple[np.ndarray, np.ndarray]:
    """2^(i/128) = scale_i * (1 + tail_i): tail_i and the bits of scale_i less i << 45 (so adding k << 45 puts k's
    whole part into the exponent), from 60-digit decimal arithmetic."""
    from decimal import Decimal, localcontext

    tail, sbits = np.empty(128, np.float64), np.empty(128, np.int64)
    with localcontext() as ctx:
        ctx.prec = 60
        for i in range(128):
            v = Decimal(2) ** (Decimal(i) / 128)
            s = float(v)
            tail[i] = float((v - Decimal(s)) / Decimal(s))
            sbits[i] = int(np.float64(s).view(np.int64)) - (i << 45)
    return tail, sbits


_EXP_TAIL, _EXP_SBITS = _exp_table()
_EXP_INVLN2N = float.fromhex("0x1.71547652b82fep0") * 128
_EXP_NEGLN2HIN = -float.fromhex("0x1.62e42fefa0000p-8")
_EXP_NEGLN2LON = -float.fromhex("0x1.cf79abc9e3b3ap-47")
_EXP_SHIFT = float.fromhex("0x1.8p52")
_EXP_C2 = float.fromhex("0x1.ffffffffffdbdp-2")
_EXP_C3 = float.fromhex("0x1.555555555543cp-3")
_EXP_C4 = float.fromhex("0x1.55555cf172b91p-5")
_EXP_C5 = float.fromhex("0x1.1111167a4d017p-7")
_EXP_FAST_LIMIT = 700.0  # _exp_core is used for arguments in [-700, 0]; a Gaussian with thr >= this takes math.exp


@njit(cache=True, inline="always")
def _exp_core(x):
    """exp(x) for finite |x| < 700, no branches (the batch loop vectorises)."""
    kd = _fma(x, _EXP_INVLN2N, _EXP_SHIFT) - _EXP_SHIFT  # k = round(x*128/ln2), exact
    k = np.int64(kd)
    r = _fma(kd, _EXP_NEGLN2LON, _fma(kd, _EXP_NEGLN2HIN, x))
    i = k & 127
    r2 = r * r
    tmp = _fma(r2 * r2, _fma(r, _EXP_C5, _EXP_C4), _fma(_fma(r, _EXP_C3, _EXP_C2), r2, _EXP_TAIL[i] + r))
    scale = _as_f64(_EXP_SBITS[i] + (k << 45))
    return _fma(scale, tmp, scale)


@njit(cache=True, inline="always")
def _exp_sigma(bdx, bdy, n, A, B, Cc, thr, ev):
    """ev[i] = exp(-sigma) for one Gaussian's pixels at offsets (bdx, bdy)[i], i < n; -1.0 where the sigma test
    fails (sigma < 0 or > thr): its alpha, o*ev < 0 (o > 0: _prep drops the rest), fails the 1/255 test. NaN passes
    through as math.exp's does.

    The fast loop runs to n rounded up to whole 8-wide vectors (buffers padded, the pad zeroed): these batches are
    short (~40 pixels), so a scalar remainder loop took a good part of the time.
    """
    if thr < _EXP_FAST_LIMIT:  # every argument that passes the test lies in [-700, 0]
        n8 = (n + 7) & -8
        for i in range(n, n8):
            bdx[i] = bdy[i] = 0.0
        for i in range(n8):
            dx, dy = bdx[i], bdy[i]
            sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
            ok = (sigma >= 0.0) & (sigma <= thr)
            e = _exp_core(-sigma if ok else 0.0)
            ev[i] = e if ok else (sigma if sigma != sigma else -1.0)  # noqa: PLR0124 (NaN test)
    else:
        for i in range(n):
            dx, dy = bdx[i], bdy[i]
            sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
            ev[i] = -1.0 if sigma < 0.0 or sigma > thr else math.exp(-sigma)


@njit(cache=True, inline="always")
def _keep_pair(mx, my, A, B, Cc, lim, x0, y0, x1, y1):
    """tiles._tile_cull for one pair: the exact minimum of sigma over the box of pixel centres vs lim = log(255*o)+1e-3."""
    if mx >= x0 and mx <= x1 and my >= y0 and my <= y1:
        best = 0.0
    else:
        best = np.inf
        for e in range(2):
            xe = x0 if e == 0 else x1
            dx = mx - xe
            dy = min(max(-B * dx / Cc, my - y1), my - y0)
            best = min(best, 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy)
        for e in range(2):
            ye = y0 if e == 0 else y1
            dy = my - ye
            dx = min(max(-B * dy / A, mx - x1), mx - x0)
            best = min(best, 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy)
    return best <= lim


@njit(cache=True, inline="always")
def _tile_box(mx, my, rx, ry, ts, tx_n, ty_n):
    """Tiles [tx0, tx1) x [ty0, ty1) that the radii box of a Gaussian touches."""
    tx0 = int(min(max(math.floor((mx - rx) / ts), 0), tx_n))
    tx1 = int(min(max(math.ceil((mx + rx) / ts), 0), tx_n))
    ty0 = int(min(max(math.floor((my - ry) / ts), 0), ty_n))
    ty1 = int(min(max(math.ceil((my + ry) / ts), 0), ty_n))
    return tx0, tx1, ty0, ty1


@njit(cache=True)
def _bin(means2d, radii, conics, opac, order, C, N, width, height, ts, tile_cull):
    """Tile lists in depth order. means2d [G,2], radii [G,2] int32, conics [G,3], opac [G], order [C,N].

    Returns starts [C*T+1] int64 (list of tile t is ids[starts[t]:starts[t+1]]) and ids [pairs] int32 (G ids).
    Visiting Gaussians in depth order and appending makes every list depth-sorted without a sort: the kept pairs
    are recorded once in that order (the culling test runs once per candidate), then scattered by tile (stable).
    """
    tx_n = (width + ts - 1) // ts
    ty_n = (height + ts - 1) // ts
    T = tx_n * ty_n
    cap = 0  # candidate pairs: an upper bound on the kept ones
    for g in range(C * N):
        if radii[g, 0] <= 0 or radii[g, 1] <= 0:
            continue
        tx0, tx1, ty0, ty1 = _tile_box(float(means2d[g, 0]), float(means2d[g, 1]), radii[g, 0], radii[g, 1], ts,
                                       tx_n, ty_n)
        cap += max(tx1 - tx0, 0) * max(ty1 - ty0, 0)
    pair_t = np.empty(cap, np.int64)
    pair_g = np.empty(cap, np.int32)
    counts = np.zeros(C * T + 1, np.int64)
    m = 0
    for cam in range(C):
        for j in range(N):
            g = cam * N + order[cam, j]
            rx, ry = radii[g, 0], radii[g, 1]
            if rx <= 0 or ry <= 0:
                continue
            mx, my = float(means2d[g, 0]), float(means2d[g, 1])
            tx0, tx1, ty0, ty1 = _tile_box(mx, my, rx, ry, ts, tx_n, ty_n)
            A, B, Cc = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
            lim = math.log(max(float(opac[g]), 1e-30) / ALPHA_THRESHOLD) + 1e-3
            for ty in range(ty0, ty1):
                y0 = ty * ts + 0.5
                y1 = min(y0 + ts - 1, height - 0.5)
                for tx in range(tx0, tx1):
                    x0 = tx * ts + 0.5
                    x1 = min(x0 + ts - 1, width - 0.5)
                    if tile_cull and not _keep_pair(mx, my, A, B, Cc, lim, x0, y0, x1, y1):
                        continue
                    t = cam * T + ty * tx_n + tx
                    counts[t + 1] += 1
                    pair_t[m] = t
                    pair_g[m] = g
                    m += 1
    for t in range(C * T):
        counts[t + 1] += counts[t]
    ids = np.empty(counts[C * T], np.int32)
    fill = counts.copy()
    for i in range(m):
        t = pair_t[i]
        ids[fill[t]] = pair_g[i]
        fill[t] += 1
    return counts, ids


@njit(cache=True, error_model="numpy")
def _prep(conics, opac, out):
    """Per-Gaussian constants of the pixel loops, out [G,4]: thr, 1/A, q = B^2 - A*Cc and the row half-extent.

    sigma <= thr = log(255*o) + slack is necessary for alpha >= 1/255. min over dx of sigma is
    0.5*dy^2*(A*Cc - B^2)/A, so only rows with |dy| <= sqrt(2*A*thr/-q) can hold such pixels. ry < 0: no pixel can;
    ry = inf: not a positive-definite conic, every pixel takes the exact test.
    """
    for g in range(opac.shape[0]):  # serial (~6 ns a Gaussian): at 10k, less than a launch of the parallel layer
        A, B, Cc, o = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]), float(opac[g])
        q = B * B - A * Cc
        if not o > 0.0:
            out[g, 0], out[g, 1], out[g, 2], out[g, 3] = -1.0, 0.0, q, -1.0
            continue
        thr = math.log(o / ALPHA_THRESHOLD) + _SIGMA_SLACK
        out[g, 0] = thr
        if A > 0.0 and q < 0.0:
            out[g, 1] = 1.0 / A
            out[g, 2] = q
            out[g, 3] = math.sqrt(2.0 * A * thr / -q) + _PIX_EPS if thr >= 0.0 else -1.0
        else:
            out[g, 1], out[g, 2], out[g, 3] = 0.0, q, np.inf


@njit(cache=True, inline="always")
def _rows(my, ry, oy, ny):
    """Tile rows [lo, hi) within ry of the Gaussian's centre."""
    if ry == np.inf:
        return 0, ny
    lo = max(my - oy - 0.5 - ry, 0.0)
    hi = min(max(my - oy - 0.5 + ry + 1.0, 0.0), float(ny))
    return math.ceil(lo), int(hi)


@njit(cache=True, inline="always")
def _cols(mx, dy, A, B, inv_a, q, thr, ox, nx, ry):
    """Tile columns [lo, hi) of one row where sigma <= thr can hold (the parabola in dx has its minimum at -B*dy/A).

    A small margin (_PIX_EPS pixels) absorbs rounding; every pixel inside still takes the exact test.
    """
    if ry == np.inf:
        return 0, nx
    disc = 2.0 * A * thr + dy * dy * q
    if disc < 0.0:
        return 0, 0
    hw = math.sqrt(disc) * inv_a + _PIX_EPS
    cx = mx + B * dy * inv_a - ox - 0.5
    lo = max(cx - hw, 0.0)
    hi = min(max(cx + hw + 1.0, 0.0), float(nx))
    return math.ceil(lo), int(hi)


@njit(cache=True, inline="always")
def _u(i):
    """i (>= 0) as an index numba does not wrap around: the negative-index select kept these loops scalar."""
    return np.uint64(i)


@njit(cache=True, inline="always")
def _list_pixels(mx, my, A, B, inv_a, q, thr, ry, ox, oy, nx, ny, ts, row_key, key, xl, xh, pix, bdx, bdy):
    """One Gaussian's pixels in a tile, row-major: its rows' column ranges (_rows, _cols), in rows with
    row_key[y] >= key. pix, bdx, bdy get the pixel index and its offsets from the centre; returns their count.

    The column ranges are worked out first, in a loop of their own: the listing loop waiting on each row's sqrt was
    ~20% slower. Both loops run to whole 8-wide vectors (row_key, xl, xh and the pixel buffers padded by 8): rows
    are short (~6 pixels, ~7 rows a Gaussian), so scalar remainders took most of the time.
    """
    y_lo, y_hi = _rows(my, ry, oy, ny)
    for y in range(y_lo, y_lo + ((y_hi - y_lo + 7) & -8)):
        x_lo, x_hi = _cols(mx, my - (oy + y + 0.5), A, B, inv_a, q, thr, ox, nx, ry)
        xl[_u(y)] = x_lo
        xh[_u(y)] = x_hi if row_key[_u(y)] >= key else x_lo
    n = 0
    for y in range(y_lo, y_hi):
        dy = my - (oy + y + 0.5)
        x_lo, w = xl[_u(y)], xh[_u(y)] - xl[_u(y)]
        for j in range((w + 7) & -8):
            pix[_u(n + j)] = y * ts + x_lo + j
            bdx[_u(n + j)] = mx - (ox + x_lo + j + 0.5)
            bdy[_u(n + j)] = dy
        n += max(w, 0)
    return n


@njit(cache=True, parallel=True, error_model="numpy")
def _forward(parallel, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max,
             img, alpha_out, t_final, last):
    """img [C,H,W,D], alpha_out [C,H,W] (input dtype); t_final [C,H,W] float64, last [C,H,W] int64 (-1: none)."""
    n = C * ((width + ts - 1) // ts) * ((height + ts - 1) // ts)
    if parallel:
        for t in prange(n):  # prange's index is uint64: as int64, one compiled _forward_tile serves both branches
            _forward_tile(np.int64(t), means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts,
                          alpha_max, img, alpha_out, t_final, last)
    else:  # one thread: not through numba's parallel layer, whose every launch took ~0.1 ms here
        for t in range(n):
            _forward_tile(t, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max, img,
                          alpha_out, t_final, last)


@njit(cache=True, error_model="numpy")
def _forward_tile(t, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max, img,
                  alpha_out, t_final, last):
    """Tile t of _forward."""
    tx_n = (width + ts - 1) // ts
    ty_n = (height + ts - 1) // ts
    T = tx_n * ty_n
    P = ts * ts
    D = colors.shape[1]
    cam = t // T
    ti = t - cam * T
    oy = (ti // tx_n) * ts
    ox = (ti - (ti // tx_n) * tx_n) * ts
    nx = min(ts, width - ox)  # edge tiles: only pixels inside the image
    ny = min(ts, height - oy)
    Tp = np.ones(P)
    acc = np.zeros(P * D)
    lastp = np.full(P, -1, np.int64)
    done = np.zeros(P, np.bool_)
    n_left = nx * ny
    row_left = np.full(ts + 8, nx, np.int64)  # pixels of each row still compositing (+8: _list_pixels)
    pix = np.empty(P + 8, np.int64)  # one Gaussian's pixels in row-major order (+8: _exp_sigma's padding)
    bdx = np.empty(P + 8)  # their offsets from the centre
    bdy = np.empty(P + 8)
    ev = np.empty(P + 8)  # exp(-sigma)
    xl = np.empty(ts + 8, np.int64)  # column range of each row
    xh = np.empty(ts + 8, np.int64)
    for k in range(starts[t], starts[t + 1]):
        if n_left == 0:
            break
        g = ids[k]
        thr, inv_a, q, ry = prep[g, 0], prep[g, 1], prep[g, 2], prep[g, 3]
        if ry < 0.0:
            continue
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        A, B, Cc, o = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]), float(opac[g])
        if D == 3:
            c0, c1, c2 = float(colors[g, 0]), float(colors[g, 1]), float(colors[g, 2])
        else:
            c0 = c1 = c2 = 0.0
        # Three passes per Gaussian: list its pixels, sigma and exp of all of them in one vector loop, composite.
        # Pixels of one Gaussian are independent, so this is the per-pixel order of the single loop, value for
        # value. Finished pixels are listed too and skipped in the last pass (no test per pixel in the listing).
        n = _list_pixels(mx, my, A, B, inv_a, q, thr, ry, ox, oy, nx, ny, ts, row_left, 1, xl, xh, pix, bdx, bdy)
        _exp_sigma(bdx, bdy, n, A, B, Cc, thr, ev)
        for i in range(n):
            p = pix[i]
            if done[p]:
                continue
            alpha = min(alpha_max, o * ev[i])
            if alpha < ALPHA_THRESHOLD:
                continue
            tp = Tp[p]
            next_T = tp * (1.0 - alpha)
            if next_T <= T_MIN:
                done[p] = True
                n_left -= 1
                row_left[p // ts] -= 1
                continue
            w = alpha * tp
            if D == 3:
                acc[3 * p] += w * c0
                acc[3 * p + 1] += w * c1
                acc[3 * p + 2] += w * c2
            else:
                for d in range(D):
                    acc[p * D + d] += w * float(colors[g, d])
            Tp[p] = next_T
            lastp[p] = k
    for y in range(ny):
        for x in range(nx):
            p = y * ts + x
            for d in range(D):
                img[cam, oy + y, ox + x, d] = acc[p * D + d]
            alpha_out[cam, oy + y, ox + x] = 1.0 - Tp[p]
            t_final[cam, oy + y, ox + x] = Tp[p]
            last[cam, oy + y, ox + x] = lastp[p]


@njit(cache=True, parallel=True, error_model="numpy")
def _backward(parallel, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max,
              t_final, last, g_img, g_alpha, pair_grad):
    """pair_grad [pairs, 6+D] float64 (means2d x,y, conic a,b,c, opacity, colour...), one row per tile-list slot."""
    n = C * ((width + ts - 1) // ts) * ((height + ts - 1) // ts)
    if parallel:
        for t in prange(n):  # as in _forward
            _backward_tile(np.int64(t), means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts,
                           alpha_max, t_final, last, g_img, g_alpha, pair_grad)
    else:  # one thread: not through numba's parallel layer, whose every launch took ~0.1 ms here
        for t in range(n):
            _backward_tile(t, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max,
                           t_final, last, g_img, g_alpha, pair_grad)


@njit(cache=True, error_model="numpy")
def _backward_tile(t, means2d, conics, opac, colors, prep, starts, ids, C, width, height, ts, alpha_max,
                   t_final, last, g_img, g_alpha, pair_grad):
    """Tile t of _backward."""
    tx_n = (width + ts - 1) // ts
    ty_n = (height + ts - 1) // ts
    T = tx_n * ty_n
    P = ts * ts
    D = colors.shape[1]
    cam = t // T
    ti = t - cam * T
    oy = (ti // tx_n) * ts
    ox = (ti - (ti // tx_n) * tx_n) * ts
    nx = min(ts, width - ox)
    ny = min(ts, height - oy)
    Tp = np.empty(P)  # these five are set for every pixel of the image below; no other pixel is listed
    tfin = np.empty(P)
    lastp = np.empty(P, np.int64)
    go = np.empty((P, D))
    ga = np.empty(P)
    buf = np.zeros((P, D))  # sum of colour * weight of the Gaussians behind, per pixel
    col = np.empty(D)
    gcol = np.empty(D)
    kmax = -1
    row_last = np.full(ts + 8, -1, np.int64)  # last contributing slot of any pixel in the row
    pix = np.empty(P + 8, np.int64)  # as in _forward: one Gaussian's pixels, their offsets, exp(-sigma), alpha
    bdx = np.empty(P + 8)  # and 1/(1 - alpha), each pass a loop of its own
    bdy = np.empty(P + 8)
    ev = np.empty(P + 8)
    bal = np.empty(P + 8)
    bra = np.empty(P + 8)
    xl = np.empty(ts + 8, np.int64)
    xh = np.empty(ts + 8, np.int64)
    for y in range(ny):
        for x in range(nx):
            p = y * ts + x
            tfin[p] = t_final[cam, oy + y, ox + x]
            Tp[p] = tfin[p]
            lastp[p] = last[cam, oy + y, ox + x]
            row_last[y] = max(row_last[y], lastp[p])
            kmax = max(kmax, lastp[p])
            for d in range(D):
                go[p, d] = g_img[cam, oy + y, ox + x, d]
            ga[p] = g_alpha[cam, oy + y, ox + x]
    for k in range(kmax, starts[t] - 1, -1):
        g = ids[k]
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        A, B, Cc, o = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2]), float(opac[g])
        thr, inv_a, q, ry = prep[g, 0], prep[g, 1], prep[g, 2], prep[g, 3]
        if ry < 0.0:
            continue
        for d in range(D):
            col[d] = colors[g, d]
            gcol[d] = 0.0
        g_mx = g_my = g_a = g_b = g_c = g_o = 0.0
        gc0 = gc1 = gc2 = 0.0
        c0, c1, c2 = col[0], col[min(1, D - 1)], col[min(2, D - 1)]
        n = _list_pixels(mx, my, A, B, inv_a, q, thr, ry, ox, oy, nx, ny, ts, row_last, k, xl, xh, pix, bdx, bdy)
        _exp_sigma(bdx, bdy, n, A, B, Cc, thr, ev)
        for i in range(n):
            alpha = min(alpha_max, o * ev[i])
            bal[i] = alpha
            bra[i] = 1.0 / (1.0 - alpha)
        for i in range(n):
            p = pix[i]
            alpha = bal[i]
            if lastp[p] < k or alpha < ALPHA_THRESHOLD:  # behind the pixel's last Gaussian, or too faint
                continue
            vis = ev[i]
            ra = bra[i]
            Tp[p] *= ra  # transmittance in front of this Gaussian
            fac = alpha * Tp[p]
            v_alpha = tfin[p] * ra * ga[p]
            tp = Tp[p]
            if D == 3:
                go0, go1, go2 = go[p, 0], go[p, 1], go[p, 2]
                gc0 += fac * go0
                gc1 += fac * go1
                gc2 += fac * go2
                b0, b1, b2 = buf[p, 0], buf[p, 1], buf[p, 2]
                v_alpha += (c0 * tp - b0 * ra) * go0
                v_alpha += (c1 * tp - b1 * ra) * go1
                v_alpha += (c2 * tp - b2 * ra) * go2
                buf[p, 0] = b0 + c0 * fac
                buf[p, 1] = b1 + c1 * fac
                buf[p, 2] = b2 + c2 * fac
            else:
                for d in range(D):
                    gcol[d] += fac * go[p, d]
                    v_alpha += (col[d] * tp - buf[p, d] * ra) * go[p, d]
                    buf[p, d] += col[d] * fac
            if o * vis < alpha_max:  # no gradient through the clamp
                dx = bdx[i]
                dy = bdy[i]
                v_sigma = -alpha * v_alpha
                g_mx += v_sigma * (A * dx + B * dy)
                g_my += v_sigma * (B * dx + Cc * dy)
                g_a += 0.5 * v_sigma * dx * dx
                g_b += v_sigma * dx * dy
                g_c += 0.5 * v_sigma * dy * dy
                g_o += vis * v_alpha
        pair_grad[k, 0] = g_mx
        pair_grad[k, 1] = g_my
        pair_grad[k, 2] = g_a
        pair_grad[k, 3] = g_b
        pair_grad[k, 4] = g_c
        pair_grad[k, 5] = g_o
        if D == 3:
            gcol[0], gcol[1], gcol[2] = gc0, gc1, gc2
        for d in range(D):
            pair_grad[k, 6 + d] = gcol[d]


@njit(cache=True)
def _reduce(ids, pair_grad, out):
    """out[g] += pair_grad[k] for every slot k of Gaussian g = ids[k] (serial: ids repeat)."""
    for k in range(ids.shape[0]):
        g = ids[k]
        for j in range(pair_grad.shape[1]):
            out[g, j] += pair_grad[k, j]


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def set_threads() -> int:
    """Numba threads follow torch's intra-op setting (the project's `threads`; 1 is the safe shared default)."""
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


@njit(cache=True)
def _depth_order(vals, bits, width, order):
    """order[c] = stable ascending argsort of vals[c] [C,N] (torch.argsort(stable=True)'s order: -0.0 ties with 0.0,
    NaN last), from bits, vals' bit patterns (width 32 or 64) as integers. LSD radix sort on bytes, skipping the bytes
    all keys share: ~10x faster than torch's sort at 10k depths."""
    C, N = vals.shape
    nb = width // 8
    top = np.int64(1) << (width - 1)
    ones = np.int64(-1) if width == 64 else (np.int64(1) << 32) - 1
    key, key2 = np.empty(N, np.int64), np.empty(N, np.int64)
    idx, idx2 = np.empty(N, np.int64), np.empty(N, np.int64)
    cnt = np.empty((nb, 256), np.int64)
    for c in range(C):
        cnt[:] = 0
        for i in range(N):
            v, b = vals[c, i], np.int64(bits[c, i])
            if math.isnan(v):
                k = ones
            elif v == 0.0:
                k = top
            else:  # ordered as unsigned integers: negatives flipped, the sign bit set on the rest
                k = (~b if b < 0 else b | top) & ones
            key[i] = k
            idx[i] = i
            for d in range(nb):
                cnt[d, (k >> (8 * d)) & 255] += 1
        for d in range(nb):
            if cnt[d, (key[0] >> (8 * d)) & 255] == N:  # one digit value: the pass would keep the order
                continue
            pos = 0
            for j in range(256):
                pos, cnt[d, j] = pos + cnt[d, j], pos
            for i in range(N):
                k = key[i]
                j = (k >> (8 * d)) & 255
                key2[cnt[d, j]] = k
                idx2[cnt[d, j]] = idx[i]
                cnt[d, j] += 1
            key, key2 = key2, key
            idx, idx2 = idx2, idx
        for i in range(N):
            order[c, i] = idx[i]


class NumbaPlan:
    def __init__(self, starts: np.ndarray, ids: np.ndarray, C: int, width: int, height: int, tile_size: int):
        self.starts, self.ids = starts, ids
        self.C, self.width, self.height, self.tile_size = C, width, height, tile_size

    @property
    def pairs(self) -> int:
        return int(self.ids.shape[0])


def build_plan_numba(means2d, conics, opacities, depths, radii_xy, width, height, tile_size=8,
                     tile_cull=True) -> NumbaPlan:
    """Tile lists for [C,N,...] projections (the same pairs and order as tiles.build_plan)."""
    C, N = depths.shape
    set_threads()
    d = _np(depths)
    if d.dtype in (np.float32, np.float64) and N > 0:
        order = np.empty((C, N), np.int64)
        _depth_order(d, d.view(np.int32 if d.dtype == np.float32 else np.int64), d.itemsize * 8, order)
    else:
        order = _np(torch.argsort(depths.detach(), dim=1, stable=True))  # [C,N], torch's tie order
    starts, ids = _bin(_np(means2d.reshape(C * N, 2)), _np(radii_xy.reshape(C * N, 2).to(torch.int32)),
                       _np(conics.reshape(C * N, 3)), _np(opacities.reshape(C * N)), order,
                       C, N, int(width), int(height), int(tile_size), bool(tile_cull))
    return NumbaPlan(starts, ids, C, int(width), int(height), int(tile_size))


class _CompositeNumba(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, plan: NumbaPlan, alpha_max: float):
        # means2d [G,2], conics [G,3], opacities [G], colors [G,D]
        C, H, W, D = plan.C, plan.height, plan.width, colors.shape[1]
        arrs = [_np(means2d), _np(conics), _np(opacities), _np(colors)]
        img = np.empty((C, H, W, D), arrs[0].dtype)
        alpha = np.empty((C, H, W), arrs[0].dtype)
        t_final = np.empty((C, H, W), np.float64)
        last = np.empty((C, H, W), np.int64)
        prep = np.empty((arrs[0].shape[0], 4))
        par = set_threads() > 1
        _prep(arrs[1], arrs[2], prep)
        _forward(par, *arrs, prep, plan.starts, plan.ids, C, W, H, plan.tile_size, float(alpha_max), img, alpha,
                 t_final, last)
        ctx.save_for_backward(means2d, conics, opacities, colors)
        ctx.plan, ctx.alpha_max, ctx.t_final, ctx.last, ctx.prep = plan, float(alpha_max), t_final, last, prep
        return torch.from_numpy(img), torch.from_numpy(alpha)[..., None]

    @staticmethod
    def backward(ctx, g_img, g_alpha):
        means2d, conics, opacities, colors = ctx.saved_tensors
        plan = ctx.plan
        C, H, W, D = plan.C, plan.height, plan.width, colors.shape[1]
        G = means2d.shape[0]
        g_img = torch.zeros(C, H, W, D, dtype=means2d.dtype) if g_img is None else g_img
        g_alpha = torch.zeros(C, H, W, 1, dtype=means2d.dtype) if g_alpha is None else g_alpha
        pair_grad = np.zeros((plan.pairs, 6 + D), np.float64)  # slots past a tile's last pixel stay 0
        par = set_threads() > 1
        _backward(par, _np(means2d), _np(conics), _np(opacities), _np(colors), ctx.prep, plan.starts, plan.ids, C, W,
                  H, plan.tile_size, ctx.alpha_max, ctx.t_final, ctx.last, _np(g_img), _np(g_alpha[..., 0]), pair_grad)
        grad = np.zeros((G, 6 + D), np.float64)
        _reduce(plan.ids, pair_grad, grad)
        grad = torch.from_numpy(grad).to(means2d.dtype)
        return grad[:, 0:2], grad[:, 2:5], grad[:, 5], grad[:, 6:], None, None


def composite_numba(means2d, conics, opacities, colors, depths, radii_xy, width, height, *, tile_size=8,
                    alpha_max=0.999, tile_cull=True):
    """[C,N,...] projections -> premultiplied colours [C,H,W,D], alphas [C,H,W,1] and plan statistics."""
    if means2d.device.type != "cpu":
        raise ValueError("realityavatar/render/numba_backend.py: `means2d` expected CPU tensors, got "
                         f"{means2d.device}")
    dt = means2d.dtype if means2d.dtype in (torch.float32, torch.float64) else torch.float32
    C, N, D = colors.shape
    plan = build_plan_numba(means2d, conics, opacities, depths, radii_xy, width, height, tile_size, tile_cull)
    img, alpha = _CompositeNumba.apply(
        means2d.reshape(C * N, 2).to(dt), conics.reshape(C * N, 3).to(dt), opacities.reshape(C * N).to(dt),
        colors.reshape(C * N, D).to(dt), plan, float(alpha_max),
    )
    stats = {"tile_size": plan.tile_size, "tile_pairs": plan.pairs, "padded_elements": plan.pairs * tile_size**2,
             "n_chunks": 1}
    return img, alpha, stats


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel for float32 and float64; returns the seconds it took."""
    t0 = time.perf_counter()
    for dt in (torch.float32, torch.float64):
        m = torch.tensor([[[4.0, 4.0]]], dtype=dt, requires_grad=True)
        con = torch.tensor([[[0.5, 0.0, 0.5]]], dtype=dt)
        op = torch.tensor([[0.9]], dtype=dt)
        col = torch.ones(1, 1, 3, dtype=dt)
        radii = torch.tensor([[[3, 3]]], dtype=torch.int32)
        img, a, _ = composite_numba(m, con, op, col, torch.ones(1, 1, dtype=dt), radii, 8, 8)
        (img.sum() + a.sum()).backward()
    return time.perf_counter() - t0


# ---- projection (project.py's EWA rules) with a hand-written backward -------------------------------------------
# 3x3 matrices are row-major 9-tuples of scalars: LLVM keeps them in registers, where small scratch arrays kept every
# entry in memory (~2x slower). Each product sums its terms in index order, as the earlier loops did; the zero
# entries of the Jacobian are left out of the sums (no value changes: only x + 0*y terms go).


@njit(cache=True, inline="always")
def _t33(a):
    return a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]


@njit(cache=True, inline="always")
def _mul33(a, b):
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[3] + a[5] * b[6], a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
            a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@njit(cache=True, inline="always")
def _rotmat(w, x, y, z):
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@njit(cache=True, inline="always")
def _quat(w, x, y, z):
    """Unit quaternion (F.normalize), its norm with the eps clamp and whether the clamp was off."""
    raw = math.sqrt(w * w + x * x + y * y + z * z)
    nrm = max(raw, 1e-12)
    return w / nrm, x / nrm, y / nrm, z / nrm, nrm, raw > 1e-12


@njit(cache=True, inline="always")
def _scaled(r, s0, s1, s2):
    """M = Rq diag(s)."""
    return r[0] * s0, r[1] * s1, r[2] * s2, r[3] * s0, r[4] * s1, r[5] * s2, r[6] * s0, r[7] * s1, r[8] * s2


@njit(cache=True, error_model="numpy")
def _cameras(viewmats, Ks, width, height):
    """Per camera [C,20]: W (9, row-major), t (3), fx, fy, cx, cy and the Jacobian's clamp limits lim_x+/-, lim_y+/-
    (1.3x the frustum, gsplat's persp_proj)."""
    out = np.empty((viewmats.shape[0], 20))
    for c in range(viewmats.shape[0]):
        for i in range(3):
            for j in range(3):
                out[c, 3 * i + j] = viewmats[c, i, j]
            out[c, 9 + i] = viewmats[c, i, 3]
        fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
        tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
        out[c, 12], out[c, 13], out[c, 14], out[c, 15] = fx, fy, cx, cy
        out[c, 16], out[c, 17] = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
        out[c, 18], out[c, 19] = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    return out


@njit(cache=True, inline="always")
def _cam_view(cams, c):
    """Camera c of _cameras: W, its translation and (fx, fy, cx, cy, lim_x+, lim_x-, lim_y+, lim_y-)."""
    W = (cams[c, 0], cams[c, 1], cams[c, 2], cams[c, 3], cams[c, 4], cams[c, 5], cams[c, 6], cams[c, 7], cams[c, 8])
    return W, (cams[c, 9], cams[c, 10], cams[c, 11]), (cams[c, 12], cams[c, 13], cams[c, 14], cams[c, 15],
                                                         cams[c, 16], cams[c, 17], cams[c, 18], cams[c, 19])


@njit(cache=True, inline="always")
def _cam_space(m0, m1, m2, S, W, t):
    """Camera-space mean p and covariance Sc = W S W^T."""
    p = (W[0] * m0 + W[1] * m1 + W[2] * m2 + t[0], W[3] * m0 + W[4] * m1 + W[5] * m2 + t[1],
         W[6] * m0 + W[7] * m1 + W[8] * m2 + t[2])
    return p, _mul33(_mul33(W, S), _t33(W))


@njit(cache=True, inline="always")
def _jacobian(p, k, near, far):
    """J = [[j00, 0, j02], [0, j11, j12]] at the clamped point; k: _cam_view's intrinsics and limits."""
    x, y, z = p
    fx, fy, _cx, _cy, lim_xp, lim_xn, lim_yp, lim_yn = k
    in_range = z >= near and z <= far
    zz = z if in_range else 1.0
    rz = 1.0 / zz
    u, v = x * rz, y * rz
    uc, vc = min(lim_xp, max(-lim_xn, u)), min(lim_yp, max(-lim_yn, v))
    tx, ty = zz * uc, zz * vc
    u_free = u > -lim_xn and u < lim_xp  # gradient passes the clamp
    v_free = v > -lim_yn and v < lim_yp
    return in_range, zz, rz, uc, vc, tx, ty, u_free, v_free, fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz


@njit(cache=True, inline="always")
def _cov2d(j00, j02, j11, j12, Sc):
    """J Sc J^T as (a, b, c), b the mean of its two off-diagonal entries."""
    t00, t01, t02 = j00 * Sc[0] + j02 * Sc[6], j00 * Sc[1] + j02 * Sc[7], j00 * Sc[2] + j02 * Sc[8]
    t10, t11, t12 = j11 * Sc[3] + j12 * Sc[6], j11 * Sc[4] + j12 * Sc[7], j11 * Sc[5] + j12 * Sc[8]
    c01, c10 = t01 * j11 + t02 * j12, t10 * j00 + t12 * j02
    return t00 * j00 + t02 * j02, 0.5 * (c01 + c10), t11 * j11 + t12 * j12


_BLOCK = 256
_PF = 20  # per-Gaussian rows of _project_fwd's block buffer: 10 inputs to its vector loop, 10 outputs


@njit(cache=True, parallel=True, error_model="numpy")
def _project_fwd(parallel, means, quats, scales, opac, viewmats, Ks, width, height, near, far, eps2d, radius_clip,
                 antialiased, means2d, conics, depths, opac_out, comp, radii, visible):
    N = means.shape[0]
    cams = _cameras(viewmats, Ks, width, height)
    if parallel:
        for blk in prange((N + _BLOCK - 1) // _BLOCK):
            _project_fwd_block(blk * _BLOCK, min(N - blk * _BLOCK, _BLOCK), means, quats, scales, opac, cams, width,
                               height, near, far, eps2d, radius_clip, antialiased, means2d, conics, depths, opac_out,
                               comp, radii, visible)
    else:  # as in _forward
        for blk in range((N + _BLOCK - 1) // _BLOCK):
            _project_fwd_block(blk * _BLOCK, min(N - blk * _BLOCK, _BLOCK), means, quats, scales, opac, cams, width,
                               height, near, far, eps2d, radius_clip, antialiased, means2d, conics, depths, opac_out,
                               comp, radii, visible)


@njit(cache=True, error_model="numpy")
def _project_fwd_block(n0, m, means, quats, scales, opac, cams, width, height, near, far, eps2d, radius_clip,
                       antialiased, means2d, conics, depths, opac_out, comp, radii, visible):
    """Gaussians n0 .. n0+m-1 of _project_fwd. The projection kernels run their blocks through plain functions:
    numba's parallel analysis failed on the helpers' nested tuples once inlined, and called helpers kept the loops
    scalar."""
    C = cams.shape[0]
    # One row of _BLOCK per value, in and out of the vector loop: its loads and stores then lie at fixed offsets
    # in one array, with unit stride (LLVM gave up on the inputs' strides and on alias checks with the outputs).
    f = np.empty(_PF * _BLOCK)
    B = _BLOCK
    for j in range(m):
        for i in range(4):
            f[i * B + j] = quats[n0 + j, i]
        for i in range(3):
            f[(4 + i) * B + j] = scales[n0 + j, i]
            f[(7 + i) * B + j] = means[n0 + j, i]
    for c in range(C):
        W, t, k = _cam_view(cams, c)
        for j in range(m):  # the maths up to the log, one Gaussian a vector lane (no calls, no branches)
            w, x, y, z, _nrm, _ok = _quat(f[j], f[B + j], f[2 * B + j], f[3 * B + j])
            M = _scaled(_rotmat(w, x, y, z), f[4 * B + j], f[5 * B + j], f[6 * B + j])
            p, Sc = _cam_space(f[7 * B + j], f[8 * B + j], f[9 * B + j], _mul33(M, _t33(M)), W, t)
            in_range, _zz, rz, _uc, _vc, _tx, _ty, _uf, _vf, j00, j02, j11, j12 = _jacobian(p, k, near, far)
            a, b, cc = _cov2d(j00, j02, j11, j12, Sc)
            det_orig = a * cc - b * b
            a2, c2 = a + eps2d, cc + eps2d
            det = a2 * c2 - b * b
            vis = in_range and det > 0
            det = det if vis else 1.0
            f[10 * B + j] = k[0] * p[0] * rz + k[2]
            f[11 * B + j] = k[1] * p[1] * rz + k[3]
            f[12 * B + j] = p[2]
            f[13 * B + j] = 1.0 if vis else 0.0
            f[14 * B + j] = c2 / det
            f[15 * B + j] = -b / det
            f[16 * B + j] = a2 / det
            f[17 * B + j] = math.sqrt(max(det_orig / det, 0.0))
            f[18 * B + j] = math.sqrt(max(a2, 0.0))
            f[19 * B + j] = math.sqrt(max(c2, 0.0))
        for j in range(m):
            n = n0 + j
            mx, my = f[10 * B + j], f[11 * B + j]
            o = float(opac[n])
            if antialiased:
                cm = f[17 * B + j]
                comp[c, n] = cm
                o = o * cm
            opac_out[c, n] = o
            vis = f[13 * B + j] != 0.0 and o >= ALPHA_THRESHOLD
            ext = min(math.sqrt(2.0 * math.log(max(o, ALPHA_THRESHOLD) / ALPHA_THRESHOLD)), 3.33)
            ex, ey = ext * f[18 * B + j], ext * f[19 * B + j]
            # tested before ceil: numba's ceil returns an integer, and a non-finite float has no integer value
            finite = math.isfinite(ex) and math.isfinite(ey)
            rx = math.ceil(ex if finite else 0.0)
            ry = math.ceil(ey if finite else 0.0)
            vis = vis and finite
            vis = vis and not (rx <= radius_clip and ry <= radius_clip)
            vis = vis and not (mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height)
            visible[c, n] = vis
            if vis:
                means2d[c, n, 0], means2d[c, n, 1] = mx, my
                conics[c, n, 0], conics[c, n, 1] = f[14 * B + j], f[15 * B + j]
                conics[c, n, 2] = f[16 * B + j]
                depths[c, n] = f[12 * B + j]
                radii[c, n, 0], radii[c, n, 1] = int(rx), int(ry)
            else:
                means2d[c, n, 0] = means2d[c, n, 1] = 0.0
                conics[c, n, 0] = conics[c, n, 1] = conics[c, n, 2] = 0.0
                depths[c, n] = 0.0
                radii[c, n, 0] = radii[c, n, 1] = 0


@njit(cache=True, parallel=True, error_model="numpy")
def _project_bwd(parallel, means, quats, scales, opac, viewmats, Ks, width, height, near, far, eps2d, antialiased,
                 visible, g_m2, g_con, g_dep, g_op, g_comp, d_means, d_quats, d_scales, d_opac):
    """Gradients of project.py's outputs (means2d, conics, depths, opacities, compensations) w.r.t. its inputs."""
    N = means.shape[0]
    cams = _cameras(viewmats, Ks, width, height)
    if parallel:
        for blk in prange((N + _BLOCK - 1) // _BLOCK):
            _project_bwd_block(blk * _BLOCK, min(N - blk * _BLOCK, _BLOCK), means, quats, scales, opac, cams, near,
                               far, eps2d, antialiased, visible, g_m2, g_con, g_dep, g_op, g_comp, d_means, d_quats,
                               d_scales, d_opac)
    else:  # as in _forward
        for blk in range((N + _BLOCK - 1) // _BLOCK):
            _project_bwd_block(blk * _BLOCK, min(N - blk * _BLOCK, _BLOCK), means, quats, scales, opac, cams, near,
                               far, eps2d, antialiased, visible, g_m2, g_con, g_dep, g_op, g_comp, d_means, d_quats,
                               d_scales, d_opac)


_PB = 40  # rows of _project_bwd's block buffer, as in _project_fwd: inputs 0-10, camera c's 11-19, sums 20-32, out 33-39


@njit(cache=True, error_model="numpy")
def _project_bwd_block(n0, m, means, quats, scales, opac, cams, near, far, eps2d, antialiased, visible, g_m2, g_con,
                       g_dep, g_op, g_comp, d_means, d_quats, d_scales, d_opac):
    """Gaussians n0 .. n0+m-1 of _project_bwd, one a vector lane as in _project_fwd_block: the branches are selects
    (each adds to a 0.0 that the skipped branch leaves as it is)."""
    C = cams.shape[0]
    f = np.empty(_PB * _BLOCK)
    B = _BLOCK
    for j in range(m):
        n = n0 + j
        for i in range(4):
            f[i * B + j] = quats[n, i]
        for i in range(3):
            f[(4 + i) * B + j] = scales[n, i]
            f[(7 + i) * B + j] = means[n, i]
        f[10 * B + j] = opac[n]
        for i in range(20, 33):  # gradients summed over cameras
            f[i * B + j] = 0.0
    for c in range(C):
        W, t, k = _cam_view(cams, c)
        fx, fy = k[0], k[1]
        for j in range(m):
            n = n0 + j
            f[11 * B + j] = 1.0 if visible[c, n] else 0.0
            f[12 * B + j], f[13 * B + j] = g_m2[c, n, 0], g_m2[c, n, 1]
            f[14 * B + j], f[15 * B + j], f[16 * B + j] = g_con[c, n, 0], g_con[c, n, 1], g_con[c, n, 2]
            f[17 * B + j], f[18 * B + j], f[19 * B + j] = g_dep[c, n], g_op[c, n], g_comp[c, n]
        for j in range(m):
            # The forward's chain again (recomputed, not stored), in _project_fwd_block's expressions, so every
            # intermediate value is the forward's bit for bit.
            w, x, y, z, _nrm, _ok = _quat(f[j], f[B + j], f[2 * B + j], f[3 * B + j])
            M = _scaled(_rotmat(w, x, y, z), f[4 * B + j], f[5 * B + j], f[6 * B + j])
            p, Sc = _cam_space(f[7 * B + j], f[8 * B + j], f[9 * B + j], _mul33(M, _t33(M)), W, t)
            in_range, zz, rz, uc, vc, tx, ty, u_free, v_free, j00, j02, j11, j12 = _jacobian(p, k, near, far)
            a, b, cc = _cov2d(j00, j02, j11, j12, Sc)
            det_orig = a * cc - b * b
            a2, c2 = a + eps2d, cc + eps2d
            det = a2 * c2 - b * b
            det_kept = in_range and det > 0
            det = det if det_kept else 1.0
            g0, g1, g2, gm0, gm1 = f[14 * B + j], f[15 * B + j], f[16 * B + j], f[12 * B + j], f[13 * B + j]
            g_op_c = f[18 * B + j]
            da = db = dc = 0.0  # w.r.t. cov2d's a, b, c (a2 = a + eps2d has the same gradient)
            ddet = 0.0
            dp0 = dp1 = dp2 = 0.0
            drz = 0.0
            if f[11 * B + j] != 0.0:  # visible
                dc += g0 / det
                db -= g1 / det
                da += g2 / det
                ddet += (-g0 * c2 + g1 * b - g2 * a2) / (det * det)
                dp0 += gm0 * fx * rz
                dp1 += gm1 * fy * rz
                drz += gm0 * fx * p[0] + gm1 * fy * p[1]
                dp2 += f[17 * B + j]
            if antialiased:
                r = det_orig / det
                cm = math.sqrt(max(r, 0.0))
                gc = f[19 * B + j] + g_op_c * f[10 * B + j]
                do = g_op_c * cm
                if r >= 0.0 and cm > 0.0:
                    dr = gc * 0.5 / cm
                    ddo = dr / det
                    if det_kept:
                        ddet -= dr * det_orig / (det * det)
                    da += ddo * cc
                    dc += ddo * a
                    db -= 2.0 * b * ddo
            else:
                do = g_op_c
            if det_kept:
                da += ddet * c2
                dc += ddet * a2
                db -= 2.0 * b * ddet
            h = 0.5 * db  # dcov = [[da, h], [h, dc]]
            # dJ = dcov J Sc (the four entries that J depends on)
            e00, e01, e02 = da * j00, h * j11, da * j02 + h * j12
            e10, e11, e12 = h * j00, dc * j11, h * j02 + dc * j12
            dj00 = e00 * Sc[0] + e01 * Sc[3] + e02 * Sc[6]
            dj02 = e00 * Sc[2] + e01 * Sc[5] + e02 * Sc[8]
            dj11 = e10 * Sc[1] + e11 * Sc[4] + e12 * Sc[7]
            dj12 = e10 * Sc[2] + e11 * Sc[5] + e12 * Sc[8]
            # dSc = J^T dcov J: rows (u_i, v_i) of J^T dcov
            u0, v0, u1, v1 = j00 * da, j00 * h, j11 * h, j11 * dc
            u2, v2 = j02 * da + j12 * h, j02 * h + j12 * dc
            dSc = (u0 * j00, v0 * j11, u0 * j02 + v0 * j12, u1 * j00, v1 * j11, u1 * j02 + v1 * j12,
                   u2 * j00, v2 * j11, u2 * j02 + v2 * j12)
            drz += 2.0 * (dj00 * fx + dj11 * fy - 2.0 * rz * (dj02 * fx * tx + dj12 * fy * ty))
            dtx = -2.0 * dj02 * fx * rz * rz
            dty = -2.0 * dj12 * fy * rz * rz
            dzz = dtx * uc + dty * vc
            if u_free:
                du = dtx * zz
                dp0 += du * rz
                drz += du * p[0]
            if v_free:
                dv = dty * zz
                dp1 += dv * rz
                drz += dv * p[1]
            dzz -= drz * rz * rz
            if in_range:
                dp2 += dzz
            f[29 * B + j] += W[0] * dp0 + W[3] * dp1 + W[6] * dp2
            f[30 * B + j] += W[1] * dp0 + W[4] * dp1 + W[7] * dp2
            f[31 * B + j] += W[2] * dp0 + W[5] * dp1 + W[8] * dp2
            f[32 * B + j] += do
            g = _mul33(_mul33(_mul33(_t33(W), dSc), W), M)  # dS M, dS = W^T dSc W
            f[20 * B + j] += 2.0 * g[0]
            f[21 * B + j] += 2.0 * g[1]
            f[22 * B + j] += 2.0 * g[2]
            f[23 * B + j] += 2.0 * g[3]
            f[24 * B + j] += 2.0 * g[4]
            f[25 * B + j] += 2.0 * g[5]
            f[26 * B + j] += 2.0 * g[6]
            f[27 * B + j] += 2.0 * g[7]
            f[28 * B + j] += 2.0 * g[8]
    for j in range(m):  # M = Rq diag(s): scales and rotation entries
        w, x, y, z, nrm, nrm_ok = _quat(f[j], f[B + j], f[2 * B + j], f[3 * B + j])
        Rq = _rotmat(w, x, y, z)
        dM = (f[20 * B + j], f[21 * B + j], f[22 * B + j], f[23 * B + j], f[24 * B + j], f[25 * B + j],
              f[26 * B + j], f[27 * B + j], f[28 * B + j])
        f[33 * B + j] = dM[0] * Rq[0] + dM[3] * Rq[3] + dM[6] * Rq[6]
        f[34 * B + j] = dM[1] * Rq[1] + dM[4] * Rq[4] + dM[7] * Rq[7]
        f[35 * B + j] = dM[2] * Rq[2] + dM[5] * Rq[5] + dM[8] * Rq[8]
        dR = _scaled(dM, f[4 * B + j], f[5 * B + j], f[6 * B + j])
        dq0 = 2 * (-z * dR[1] + y * dR[2] + z * dR[3] - x * dR[5] - y * dR[6] + x * dR[7])
        dq1 = 2 * (y * dR[1] + z * dR[2] + y * dR[3] - 2 * x * dR[4] - w * dR[5] + z * dR[6] + w * dR[7]
                   - 2 * x * dR[8])
        dq2 = 2 * (-2 * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + z * dR[5] - w * dR[6] + z * dR[7]
                   - 2 * y * dR[8])
        dq3 = 2 * (-2 * z * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - 2 * z * dR[4] + y * dR[5] + x * dR[6]
                   + y * dR[7])
        dot = w * dq0 + x * dq1 + y * dq2 + z * dq3 if nrm_ok else 0.0  # F.normalize's eps branch: a constant
        f[36 * B + j] = (dq0 - w * dot) / nrm if nrm_ok else dq0 / nrm
        f[37 * B + j] = (dq1 - x * dot) / nrm if nrm_ok else dq1 / nrm
        f[38 * B + j] = (dq2 - y * dot) / nrm if nrm_ok else dq2 / nrm
        f[39 * B + j] = (dq3 - z * dot) / nrm if nrm_ok else dq3 / nrm
    for j in range(m):
        n = n0 + j
        for i in range(3):
            d_means[n, i] = f[(29 + i) * B + j]
            d_scales[n, i] = f[(33 + i) * B + j]
        for i in range(4):
            d_quats[n, i] = f[(36 + i) * B + j]
        d_opac[n] = f[32 * B + j]


class _ProjectNumba(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d, radius_clip,
                antialiased):
        C, N = viewmats.shape[0], means.shape[0]
        dt = means.dtype
        a = [_np(t.to(torch.float64)) for t in (means, quats, scales, opacities, viewmats, Ks)]
        m2, con = np.empty((C, N, 2), np.float64), np.empty((C, N, 3), np.float64)
        dep, op, comp = np.empty((C, N)), np.empty((C, N)), np.ones((C, N))
        radii, vis = np.empty((C, N, 2), np.int32), np.empty((C, N), np.bool_)
        par = set_threads() > 1
        _project_fwd(par, *a, int(width), int(height), float(near), float(far), float(eps2d), float(radius_clip),
                     bool(antialiased), m2, con, dep, op, comp, radii, vis)
        ctx.args = (int(width), int(height), float(near), float(far), float(eps2d), bool(antialiased))
        ctx.a, ctx.dt = a, dt  # the float64 inputs, for the backward (converting them again costs 6 operations)
        vis_t = torch.from_numpy(vis)
        ctx.vis = vis
        ctx.mark_non_differentiable(vis_t)
        out = [torch.from_numpy(x).to(dt) for x in (m2, con, dep, op, comp)]
        return (*out, torch.from_numpy(radii), vis_t)

    @staticmethod
    def backward(ctx, g_m2, g_con, g_dep, g_op, g_comp, _g_radii, _g_vis):
        a = ctx.a
        C, N = a[4].shape[0], a[0].shape[0]
        gs = []
        for g, shape in ((g_m2, (C, N, 2)), (g_con, (C, N, 3)), (g_dep, (C, N)), (g_op, (C, N)), (g_comp, (C, N))):
            gs.append(np.zeros(shape) if g is None else _np(g.to(torch.float64)))
        d = [np.zeros(x.shape) for x in a[:4]]
        par = set_threads() > 1
        _project_bwd(par, *a, *ctx.args, ctx.vis, *gs, *d)
        dt = ctx.dt
        return (*[torch.from_numpy(x).to(dt) for x in d], None, None, None, None, None, None, None, None, None)


def project_gaussians_numba(means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d=0.3,
                            radius_clip=0.0, antialiased=False):
    """project.project_gaussians in compiled kernels (float64 inside); the torch version where cameras need grads."""
    from .project import Projection, project_gaussians

    if viewmats.requires_grad or Ks.requires_grad:
        return project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                                 eps2d=eps2d, radius_clip=radius_clip, antialiased=antialiased)
    m2, con, dep, op, comp, radii, vis = _ProjectNumba.apply(
        means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d, radius_clip, antialiased)
    return Projection(means2d=m2, conics=con, depths=dep, opacities=op, radii_xy=radii, visible=vis,
                      compensations=comp if antialiased else None)
