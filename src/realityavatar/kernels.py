"""Fused CPU kernels (Numba) for two hot spots of the training step, each with a device-agnostic torch path.

- `dssim(x, y)`: D-SSIM = mean(clamp((1 - SSIM)/2, 0, 1)) with kornia's conventions (11-tap Gaussian window of
  sigma 1.5, separable, 'reflect' padding, c1 = 0.01^2, c2 = 0.03^2, eps 1e-12 in the denominator). On the CPU with
  Numba the map, the mean and the gradient with respect to x come from one pass over each image plane (the
  gradient is formed in the forward when x needs one, so the backward is a scale). Elsewhere (a GPU): kornia's
  formula with its five Gaussian blurs stacked into one pair of depthwise convolutions.
  Eager kornia costs ~20 ms forward+backward at 3x256x256 on one core; the fused pass ~2.6 ms.
- `polar_rotation(M)`: the rotation factor R of the polar decomposition M = R S of [...,3,3] matrices, with the
  exact closed-form gradient (R is computed without a graph; the backward solves a 3x3 system per matrix) instead
  of differentiating through Newton's iterations, whose graph cost ~15 ms per step at 10k Gaussians.

Both are exact replacements (tests/test_kernels.py compares values and gradients with the reference paths).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from realityavatar.geometry import skew
from realityavatar.render.numba_backend import NUMBA_ERROR, njit, prange
from realityavatar.runtime import Table, constant, host_path

# ----------------------------------------------------------------------------------------------------------- D-SSIM
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = 0.01**2
_C2 = 0.03**2
_EPS = 1e-12


def _gauss_taps(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    n = np.arange(size, dtype=np.float64) - size // 2
    w = np.exp(-(n**2) / (2.0 * sigma**2))
    return (w / w.sum()).astype(np.float32)


@njit(cache=True, inline="always")
def _refl(i, n):
    """torch 'reflect' padding: -1 -> 1, n -> n-2."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


@njit(cache=True, fastmath=True)
def _blur_rows(src, dst, w):
    """dst[i, j] = sum_k w[k] src[i, refl(j + k - r)] (the horizontal pass, over a padded copy of each row)."""
    H, W = src.shape
    r = w.shape[0] // 2
    buf = np.empty(W + 2 * r, src.dtype)
    for i in range(H):
        for j in range(W + 2 * r):
            buf[j] = src[i, _refl(j - r, W)]
        for j in range(W):
            dst[i, j] = 0.0
        for k in range(w.shape[0]):
            wk = w[k]
            for j in range(W):
                dst[i, j] += wk * buf[j + k]


@njit(cache=True, fastmath=True)
def _blur_cols(src, dst, w):
    """dst[i, j] = sum_k w[k] src[refl(i + k - r), j] (the vertical pass)."""
    H, W = src.shape
    r = w.shape[0] // 2
    for i in range(H):
        for j in range(W):
            dst[i, j] = 0.0
        for k in range(w.shape[0]):
            wk = w[k]
            ii = _refl(i + k - r, H)
            for j in range(W):
                dst[i, j] += wk * src[ii, j]


@njit(cache=True, fastmath=True)
def _blur_rows_t(src, dst, w):
    """Adjoint of _blur_rows: dst[i, refl(j + k - r)] += w[k] src[i, j] (scattered into a padded row, then folded)."""
    H, W = src.shape
    r = w.shape[0] // 2
    buf = np.empty(W + 2 * r, src.dtype)
    for i in range(H):
        for j in range(W + 2 * r):
            buf[j] = 0.0
        for k in range(w.shape[0]):
            wk = w[k]
            for j in range(W):
                buf[j + k] += wk * src[i, j]
        for j in range(W):
            dst[i, j] = buf[j + r]
        for j in range(r):  # padded slots j - r < 0 and >= W reflect back into the row
            dst[i, _refl(j - r, W)] += buf[j]
            dst[i, _refl(W + j, W)] += buf[W + r + j]


@njit(cache=True, fastmath=True)
def _blur_cols_t(src, dst, w):
    """Adjoint of _blur_cols: dst[refl(i + k - r), j] += w[k] src[i, j]."""
    H, W = src.shape
    r = w.shape[0] // 2
    for i in range(H):
        for j in range(W):
            dst[i, j] = 0.0
    for i in range(H):
        for k in range(w.shape[0]):
            wk = w[k]
            ii = _refl(i + k - r, H)
            for j in range(W):
                dst[ii, j] += wk * src[i, j]


@njit(cache=True, fastmath=True)
def _blur(src, tmp, dst, w):
    _blur_rows(src, tmp, w)
    _blur_cols(tmp, dst, w)


@njit(cache=True, fastmath=True)
def _blur_t(src, tmp, dst, w):
    _blur_cols_t(src, tmp, w)
    _blur_rows_t(tmp, dst, w)


@njit(cache=True, fastmath=True)
def _blur_product(a, b, q, tmp, dst, w):
    """dst = blur(a * b), q holding the product."""
    H, W = a.shape
    for i in range(H):
        for j in range(W):
            q[i, j] = a[i, j] * b[i, j]
    _blur(q, tmp, dst, w)


@njit(cache=True, parallel=True, fastmath=True)
def _dssim_planes(x, y, w, want_grad, loss_sum, grad):
    """x, y [P,H,W] float32 planes. loss_sum[p] = sum over the plane of clamp((1 - s)/2, 0, 1); when want_grad,
    grad[p] = d(loss_sum[p])/dx (not yet divided by the number of elements)."""
    P, H, W = x.shape
    for p in prange(P):
        xp, yp = x[p], y[p]
        tmp = np.empty((H, W), np.float32)
        q = np.empty((H, W), np.float32)
        mx = np.empty((H, W), np.float32)
        my = np.empty((H, W), np.float32)
        bxx = np.empty((H, W), np.float32)
        byy = np.empty((H, W), np.float32)
        bxy = np.empty((H, W), np.float32)
        _blur(xp, tmp, mx, w)
        _blur(yp, tmp, my, w)
        _blur_product(xp, xp, q, tmp, bxx, w)
        _blur_product(yp, yp, q, tmp, byy, w)
        _blur_product(xp, yp, q, tmp, bxy, w)
        total = 0.0
        # per-pixel partials of the loss with respect to mu_x, blur(x^2), blur(xy); stored over mx, bxx, bxy
        for i in range(H):
            for j in range(W):
                ux, uy = mx[i, j], my[i, j]
                a1 = 2.0 * ux * uy + _C1
                a2 = 2.0 * (bxy[i, j] - ux * uy) + _C2
                b1 = ux * ux + uy * uy + _C1
                b2 = (bxx[i, j] - ux * ux) + (byy[i, j] - uy * uy) + _C2
                d = b1 * b2 + _EPS
                s = a1 * a2 / d
                ell = (1.0 - s) * 0.5
                g = -0.5
                if ell < 0.0:
                    ell = 0.0
                    g = 0.0
                elif ell > 1.0:
                    ell = 1.0
                    g = 0.0
                total += ell
                if want_grad:
                    gd = g / d
                    mx[i, j] = gd * (2.0 * uy * a2 - 2.0 * uy * a1 - 2.0 * ux * s * b2 + 2.0 * ux * s * b1)
                    bxx[i, j] = -gd * s * b1
                    bxy[i, j] = gd * 2.0 * a1
        loss_sum[p] = total
        if want_grad:
            gp = grad[p]
            _blur_t(mx, tmp, gp, w)
            _blur_t(bxx, tmp, q, w)
            for i in range(H):
                for j in range(W):
                    gp[i, j] += 2.0 * xp[i, j] * q[i, j]
            _blur_t(bxy, tmp, q, w)
            for i in range(H):
                for j in range(W):
                    gp[i, j] += yp[i, j] * q[i, j]


class _DSSIMNumba(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        B, C, H, W = x.shape
        xp = x.detach().reshape(B * C, H, W).contiguous().float().numpy()
        yp = y.detach().reshape(B * C, H, W).contiguous().float().numpy()
        want = bool(ctx.needs_input_grad[0])
        sums = np.zeros(B * C, np.float64)
        grad = np.empty((B * C, H, W) if want else (1, 1, 1), np.float32)
        _dssim_planes(xp, yp, _TAPS, want, sums, grad)
        n = float(B * C * H * W)
        if want:
            ctx.save_for_backward(torch.from_numpy(grad).reshape(B, C, H, W).to(x.dtype) / n)
        return torch.tensor(sums.sum() / n, dtype=x.dtype)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (grad,) = ctx.saved_tensors
        return g * grad, None


_TAPS = _gauss_taps()
_TAPS_T = Table(torch.from_numpy(_TAPS))  # the torch path's copy


def _dssim_torch(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """kornia's D-SSIM with its five blurs as one: x, y, x^2, y^2, xy stacked on the channel axis and blurred
    separably (reflect borders) by one pair of depthwise convolutions; ~35 fewer operations (GPU launches) forward."""
    C, r = x.shape[1], SSIM_WINDOW // 2
    s = torch.cat([x, y, x * x, y * y, x * y], 1)  # [B,5C,H,W]
    w = constant(_TAPS_T, s)
    k = s.shape[1]
    s = F.conv2d(F.pad(s, (r, r, 0, 0), mode="reflect"), w.view(1, 1, 1, -1).expand(k, 1, 1, -1), groups=k)
    s = F.conv2d(F.pad(s, (0, 0, r, r), mode="reflect"), w.view(1, 1, -1, 1).expand(k, 1, -1, 1), groups=k)
    mu1, mu2, e11, e22, e12 = s.split(C, 1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    num = (2.0 * mu1_mu2 + _C1) * (2.0 * (e12 - mu1_mu2) + _C2)
    den = (mu1_sq + mu2_sq + _C1) * ((e11 - mu1_sq) + (e22 - mu2_sq) + _C2)
    return torch.clamp((1.0 - num / (den + _EPS)) / 2, min=0, max=1).mean()


def dssim(x: torch.Tensor, y: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """D-SSIM of x against y ([B,C,H,W], values in [0,1]); equals kornia.losses.ssim_loss(x, y, 11).

    backend: "auto" (fused Numba kernel for float CPU tensors when y needs no gradient, else "torch"), "numba"
    (fused kernel; raises where it cannot run), "torch" (one stacked blur: the GPU's path) or "kornia" (kornia
    itself, the reference).
    """
    if backend not in ("auto", "numba", "torch", "kornia"):
        raise ValueError(f"dssim backend: expected 'auto', 'numba', 'torch' or 'kornia', got {backend!r}")
    fused_ok = (host_path(x) and NUMBA_ERROR is None and x.ndim == 4 and x.shape == y.shape
                and not y.requires_grad and x.shape[-1] > SSIM_WINDOW // 2 and x.shape[-2] > SSIM_WINDOW // 2)
    if backend == "numba" and not fused_ok:
        raise RuntimeError(f"dssim backend=numba needs CPU tensors of equal shape [B,C,H,W], y without grad and "
                           f"numba ({NUMBA_ERROR or 'available'}); got {tuple(x.shape)} on {x.device}")
    if backend == "kornia":
        from kornia.losses import ssim_loss

        return ssim_loss(x, y, window_size=SSIM_WINDOW)
    if backend == "torch" or not fused_ok:
        return _dssim_torch(x, y)
    return _DSSIMNumba.apply(x, y)


# ------------------------------------------------------------------------------------------------- polar rotation
@njit(cache=True, fastmath=False)
def _polar_newton(M, R, iters):
    """R[n] = rotation factor of M[n] (3x3) by Newton's iteration X <- (X + X^-T)/2, at most iters steps."""
    for n in range(M.shape[0]):
        x00, x01, x02 = M[n, 0, 0], M[n, 0, 1], M[n, 0, 2]
        x10, x11, x12 = M[n, 1, 0], M[n, 1, 1], M[n, 1, 2]
        x20, x21, x22 = M[n, 2, 0], M[n, 2, 1], M[n, 2, 2]
        for _ in range(iters):
            # cofactor matrix (= det * X^-T)
            c00 = x11 * x22 - x12 * x21
            c01 = x12 * x20 - x10 * x22
            c02 = x10 * x21 - x11 * x20
            c10 = x21 * x02 - x22 * x01
            c11 = x22 * x00 - x20 * x02
            c12 = x20 * x01 - x21 * x00
            c20 = x01 * x12 - x02 * x11
            c21 = x02 * x10 - x00 * x12
            c22 = x00 * x11 - x01 * x10
            det = x00 * c00 + x01 * c01 + x02 * c02
            if abs(det) < 1e-8:
                det = 1e-8
            inv = 1.0 / det
            y00, y01, y02 = 0.5 * (x00 + c00 * inv), 0.5 * (x01 + c01 * inv), 0.5 * (x02 + c02 * inv)
            y10, y11, y12 = 0.5 * (x10 + c10 * inv), 0.5 * (x11 + c11 * inv), 0.5 * (x12 + c12 * inv)
            y20, y21, y22 = 0.5 * (x20 + c20 * inv), 0.5 * (x21 + c21 * inv), 0.5 * (x22 + c22 * inv)
            change = (abs(y00 - x00) + abs(y01 - x01) + abs(y02 - x02) + abs(y10 - x10) + abs(y11 - x11)
                      + abs(y12 - x12) + abs(y20 - x20) + abs(y21 - x21) + abs(y22 - x22))
            x00, x01, x02, x10, x11, x12, x20, x21, x22 = y00, y01, y02, y10, y11, y12, y20, y21, y22
            if change < 1e-12:
                break
        R[n, 0, 0], R[n, 0, 1], R[n, 0, 2] = x00, x01, x02
        R[n, 1, 0], R[n, 1, 1], R[n, 1, 2] = x10, x11, x12
        R[n, 2, 0], R[n, 2, 1], R[n, 2, 2] = x20, x21, x22


def _cofactor_det(X: torch.Tensor, floor: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Cofactor matrix (= det * X^-T) of X [...,3,3] and its determinant [...], the determinant's magnitude floored.
    Its rows r1 x r2, r2 x r0, r0 x r1 are one cross product of the rows rolled by one and by two."""
    cof = torch.linalg.cross(X.roll(-1, -2), X.roll(-2, -2))
    det = (X[..., 0, :] * cof[..., 0, :]).sum(-1)
    return cof, torch.where(det.abs() < floor, constant((floor,), det), det)  # a scalar would be a new tensor per call


def _polar_newton_torch(M: torch.Tensor, iters: int) -> torch.Tensor:
    """Newton's iteration X <- (X + X^-T) / 2, its first step scaled by g = |det X|^(-1/3) (X <- (g X + (g X)^-T) / 2):
    blends of two rotations up to 175 degrees apart (det down to ~0) converge to float32 precision in 6 steps, where
    the plain iteration needs 8."""
    X = M
    for i in range(iters):
        cof, det = _cofactor_det(X, 1e-8)
        if i == 0:
            g = det.abs().pow(-1.0 / 3)[..., None, None]
            X = 0.5 * (g * X + cof / (g * det[..., None, None]))
        else:
            X = 0.5 * torch.addcdiv(X, cof, det[..., None, None])  # (X + X^-T) / 2
    return X


POLAR_ITERS = 8  # Newton converges quadratically; blends of bone rotations are within a few steps of a rotation
POLAR_ITERS_TORCH = 6  # the scaled iteration's (torch path, a GPU's): 17 fewer operations per step


_EYE3 = torch.eye(3)
_AXIAL = torch.zeros(9, 3)  # flattened A [9] -> 0.5 (A21 - A12, A02 - A20, A10 - A01)
for _i, (_p, _m) in enumerate(((7, 5), (2, 6), (3, 1))):
    _AXIAL[_p, _i], _AXIAL[_m, _i] = 0.5, -0.5
_EYE3, _AXIAL = Table(_EYE3), Table(_AXIAL)


class _PolarRotation(torch.autograd.Function):
    """R = polar factor of M; dL/dM = 2 R [y]_x with (tr(S) I - S) y = axial(skew(R^T dL/dR)), S = R^T M.

    (From M = R S: R^T dM - dM^T R = Omega S + S Omega with Omega = R^T dR skew, and S W + W S = [(tr S I - S) w]_x
    for skew W = [w]_x; the map is self-adjoint, so the vector-Jacobian product solves the same 3x3 system.)
    """

    @staticmethod
    def forward(ctx, M: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            if host_path(M) and NUMBA_ERROR is None:
                flat = M.detach().reshape(-1, 3, 3).double().contiguous().numpy()
                out = np.empty_like(flat)
                _polar_newton(flat, out, 2 * POLAR_ITERS)
                R = torch.from_numpy(out).to(M.dtype).reshape(M.shape)
            else:
                R = _polar_newton_torch(M.detach(), POLAR_ITERS_TORCH)
        ctx.save_for_backward(M, R)
        return R

    @staticmethod
    def backward(ctx, G: torch.Tensor):
        M, R = ctx.saved_tensors
        Rt = R.transpose(-1, -2)
        S = Rt @ M
        S = 0.5 * (S + S.transpose(-1, -2))
        A = Rt @ G
        k = A.flatten(-2) @ constant(_AXIAL, A)  # axial vector of A's skew part, 0.5 (A21 - A12, ...): one matmul
        tr = S[..., 0, 0] + S[..., 1, 1] + S[..., 2, 2]
        T = tr[..., None, None] * constant(_EYE3, M) - S  # symmetric positive definite
        adj, det = _cofactor_det(T, 1e-12)  # T symmetric: its cofactor matrix is its adjugate, T^-1 = adj / det
        y = (adj @ k[..., None]).squeeze(-1) / det[..., None]
        return 2.0 * (R @ skew(y))


def polar_rotation(M: torch.Tensor, backend: str = "closed_form") -> torch.Tensor:
    """Rotation factor of the polar decomposition of M [...,3,3] (det M > 0), differentiable.

    backend "closed_form" (default): no graph through the iterations, the exact gradient in closed form;
    "autograd": differentiate through 6 Newton steps (the reference, ~10x the cost of the backward).
    """
    if backend == "autograd":
        return _polar_newton_torch(M, 6)
    if backend != "closed_form":
        raise ValueError(f"polar_rotation backend: expected 'closed_form' or 'autograd', got {backend!r}")
    return _PolarRotation.apply(M)
