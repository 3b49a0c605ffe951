"""Image metrics: PSNR, SSIM, FLIP, LPIPS (pure torch from weight files, or the lpips package), mask-box crops, the
garment's region and its detail (image_metrics: every score of a held-out image), flicker.

Images are float [H,W,3] or [B,H,W,3] in [0,1]; batched inputs give one value per image.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import math
import os
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn


@contextlib.contextmanager
def no_tf32():
    """Full float32 matmuls and convolutions inside (CUDA's TF32 keeps 10 mantissa bits), restored after."""
    mm, conv = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = mm, conv


def _batched(x: torch.Tensor, name: str) -> tuple[torch.Tensor, bool]:
    if x.ndim == 3:
        return x[None], True
    if x.ndim == 4:
        return x, False
    raise ValueError(f"metrics: {name} expected [H,W,C] or [B,H,W,C], got {tuple(x.shape)}")


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """10 log10(1 / MSE) over all pixels and channels of each image (data range 1); inf for identical images."""
    p, single = _batched(pred, "pred")
    g, _ = _batched(gt, "gt")
    mse = ((p.double() - g.double()) ** 2).flatten(1).mean(1)  # float64: the same number on any device
    out = torch.where(mse > 0, -10.0 * torch.log10(mse.clamp_min(1e-30)), torch.full_like(mse, math.inf))
    return out[0] if single else out


def _gaussian_1d(size: int = 11, sigma: float = 1.5, device=None) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()  # [size] float64


def _ssim_index(mx, my, vx, vy, vxy):
    """Wang et al.'s SSIM from local means, variances and covariance (any shape), K1=0.01, K2=0.03, data range 1."""
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Local SSIM of each 'valid' window position, averaged over channels: [B,H-2r,W-2r] float64 (r = window // 2;
    `ssim` is its mean). Images smaller than the window are edge-padded up to it first."""
    p, _ = _batched(pred, "pred")
    g, _ = _batched(gt, "gt")
    # float64: convolutions on CUDA would otherwise run in TF32 (cudnn's default) and change the metric
    x = p.double().permute(0, 3, 1, 2)  # [B,C,H,W]
    y = g.double().permute(0, 3, 1, 2)
    H, W = x.shape[-2:]
    if H < window or W < window:
        ph, pw = max(window - H, 0), max(window - W, 0)
        pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        x, y = F.pad(x, pad, mode="replicate"), F.pad(y, pad, mode="replicate")
    C = x.shape[1]
    # The Gaussian window is separable: two 1-D passes ('valid' positions only). On the CPU scipy's correlate1d in
    # float64 (a 256^2 RGB image in ~20 ms; the dense 11x11 float64 conv2d took ~1.3 s and was most of evaluation).
    g1 = _gaussian_1d(window, sigma, x.device)
    if x.device.type == "cpu" and not (x.requires_grad or y.requires_grad):
        from scipy.ndimage import correlate1d

        r, gn = window // 2, g1.numpy()

        def filt(t: torch.Tensor) -> torch.Tensor:
            a = correlate1d(correlate1d(t.numpy(), gn, axis=-2, mode="constant"), gn, axis=-1, mode="constant")
            return torch.from_numpy(a[..., r : a.shape[-2] - r, r : a.shape[-1] - r])
    else:
        wv, wh = g1.view(1, 1, window, 1).expand(C, 1, window, 1), g1.view(1, 1, 1, window).expand(C, 1, 1, window)
        filt = lambda t: F.conv2d(F.conv2d(t, wv, groups=C), wh, groups=C)
    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    return _ssim_index(mx, my, sxx, syy, sxy).mean(1)


def ssim(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) with an 11x11 Gaussian window (sigma 1.5), K1=0.01, K2=0.03, data range 1.

    Convention: local statistics use population (not sample) covariance and the mean is taken over 'valid'
    window positions only, averaged over channels. This equals skimage's
    structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1,
    channel_axis=-1) (its filter is 11 wide for sigma 1.5 and it crops 5 border pixels before averaging).
    3DGS's training SSIM zero-pads instead and reads slightly lower near borders. Images smaller than the
    window are edge-padded up to it.
    """
    out = ssim_map(pred, gt, window, sigma).flatten(1).mean(1)
    return out[0] if pred.ndim == 3 else out


def ssim_skimage(pred: torch.Tensor, gt: torch.Tensor, window: int = 7) -> torch.Tensor:
    """skimage's structural_similarity with its defaults, as Dyco calls it (`data_range=1, channel_axis=-1`): a
    `window` x `window` uniform window, sample covariance (x N/(N-1)), K1=0.01, K2=0.03, the mean over the positions
    whose window lies inside the image, averaged over channels. pred, gt [H,W,3] or [B,H,W,3] -> float64 per image."""
    p, single = _batched(pred, "pred")
    g, _ = _batched(gt, "gt")
    x, y = p.double().permute(0, 3, 1, 2), g.double().permute(0, 3, 1, 2)  # [B,C,H,W]
    if min(x.shape[-2:]) < window:
        raise ValueError(f"ssim_skimage: images of {tuple(x.shape[-2:])} px are smaller than the {window}-wide window "
                         "(skimage refuses them too)")
    filt = lambda t: F.avg_pool2d(t, window, stride=1)  # the uniform filter at 'valid' positions: skimage's crop
    n = window * window
    cov = n / (n - 1.0)
    mx, my = filt(x), filt(y)
    vx, vy = cov * (filt(x * x) - mx * mx), cov * (filt(y * y) - my * my)
    vxy = cov * (filt(x * y) - mx * my)
    # per channel, then over channels (skimage's channel_axis)
    out = _ssim_index(mx, my, vx, vy, vxy).flatten(2).mean(2).mean(1)
    return out[0] if single else out


def ssim_3dgs(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """3DGS's `utils/loss_utils.ssim`, as SeqAvatar's render.py scores: an 11x11 Gaussian window (sigma 1.5) with
    zero padding (every pixel has a value; the border reads lower), population covariance, the mean over all pixels
    and channels. pred, gt [H,W,3] or [B,H,W,3] -> float64 per image."""
    p, single = _batched(pred, "pred")
    g, _ = _batched(gt, "gt")
    x, y = p.double().permute(0, 3, 1, 2), g.double().permute(0, 3, 1, 2)
    C, r = x.shape[1], window // 2
    g1 = _gaussian_1d(window, sigma, x.device)
    w = (g1[:, None] @ g1[None, :]).expand(C, 1, window, window)
    filt = lambda t: F.conv2d(t, w, padding=r, groups=C)
    mx, my = filt(x), filt(y)
    sxx, syy, sxy = filt(x * x) - mx * mx, filt(y * y) - my * my, filt(x * y) - mx * my
    out = _ssim_index(mx, my, sxx, syy, sxy).flatten(1).mean(1)
    return out[0] if single else out


def psnr_per_channel(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """SeqAvatar's PSNR (3DGS `utils/image_utils.psnr` on a [3,H,W] image, then `.mean()`): the PSNR of each colour
    channel, averaged; not the PSNR of the mean squared error. [H,W,3] or [B,H,W,3] -> float64 per image."""
    p, single = _batched(pred, "pred")
    g, _ = _batched(gt, "gt")
    mse = ((p.double() - g.double()) ** 2).flatten(1, 2).mean(1)  # [B,3]
    out = (-10.0 * torch.log10(mse.clamp_min(1e-30))).mean(1)
    return out[0] if single else out


def floor_uint8(image: torch.Tensor) -> torch.Tensor:
    """Dyco's `to_8b_image`, (255 * clip(x, 0, 1)).astype(uint8) / 255: quantised by truncation, not rounding."""
    return (torch.floor(image.float().clamp(0, 1) * 255.0) / 255.0).to(image.dtype)  # float32 as numpy does it


def smpl_box_mask(joints: torch.Tensor, root_rot: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor, height: int,
                  width: int, offset: float = 0.3) -> torch.Tensor:
    """Dyco's ray mask: the pixels whose camera ray meets the box around the posed joints, axis-aligned in the
    body's frame (its root rotation `root_rot` [3,3] undone), widened by `offset` m (cfg.bbox_offset 0.3) and 0.01 m
    more (`rays_intersect_3d_bbox`). joints [24,3] world, K [3,3], viewmat [4,4] world-to-camera; rays through
    integer pixel coordinates, as Dyco's get_rays_from_KRT. -> bool [H,W,1]."""
    dt = torch.float64
    R, t = viewmat[:3, :3].to(dt), viewmat[:3, 3].to(dt)
    Rr = root_rot.to(dt)
    local = joints.to(dt) @ Rr  # [24,3]: R_root^T x
    lo, hi = local.amin(0) - offset - 0.01, local.amax(0) + offset + 0.01
    v, u = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
    Kd = K.to(dt)
    d_cam = torch.stack([(u - Kd[0, 2]) / Kd[0, 0], (v - Kd[1, 2]) / Kd[1, 1], torch.ones_like(u)], -1)  # [H,W,3]
    d = d_cam @ R @ Rr  # camera -> world (R^T d) -> body frame (R_root^T)
    o = (-(R.T @ t)) @ Rr  # [3]
    d = torch.where(d.abs() < 1e-5, torch.full_like(d, 1e-5), d)
    t0, t1 = (lo - o) / d, (hi - o) / d
    near = torch.minimum(t0, t1).amax(-1)
    far = torch.maximum(t0, t1).amin(-1)
    return (far > near)[..., None]  # the ray passes through the slab of every axis at once


def mask_box_mask(mask: torch.Tensor, pad: int = 5) -> torch.Tensor:
    """SeqAvatar's bound mask (`get_rect_bound_mask`): the ground-truth mask's bounding box grown by `pad` pixels,
    clipped to the image. mask [H,W,1] -> bool [H,W,1]."""
    y0, y1, x0, x1 = mask_bbox(mask, pad)
    out = torch.zeros(mask.shape[0], mask.shape[1], 1, dtype=torch.bool, device=mask.device)
    out[y0:y1, x0:x1] = True
    return out


def silhouette_iou(alpha: torch.Tensor, mask: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """Intersection over union of the predicted silhouette (alpha > threshold) and the mask (> 0.5): [H,W,1] each."""
    a, m = alpha > threshold, mask > 0.5
    union = (a | m).sum()
    return torch.where(union > 0, (a & m).sum() / union.clamp(min=1), torch.ones((), device=alpha.device))


def mask_bbox(mask: torch.Tensor, pad: int = 0) -> tuple[int, int, int, int]:
    """mask [H,W] or [H,W,1] -> (y0, y1, x0, x1) of its non-zero box (+pad, clipped); the whole image if empty."""
    m = mask.reshape(mask.shape[0], mask.shape[1], -1).amax(-1) > 0.5
    H, W = m.shape
    ys, xs = m.any(1).nonzero().squeeze(-1), m.any(0).nonzero().squeeze(-1)
    if ys.numel() == 0:
        return 0, H, 0, W
    return max(int(ys[0]) - pad, 0), min(int(ys[-1]) + 1 + pad, H), max(int(xs[0]) - pad, 0), min(int(xs[-1]) + 1 + pad, W)


REGION_ERODE = 2  # pixels taken off a region's edge before it is scored: its outline is the silhouette's, not texture


def erode(region: torch.Tensor, pixels: int = REGION_ERODE) -> torch.Tensor:
    """region [H,W,1] (> 0.5 inside) -> bool [H,W,1] without the pixels within `pixels` of its edge (a square
    structuring element: a pixel stays when its (2 pixels + 1)^2 neighbourhood is inside; the image's edge counts as
    outside)."""
    inside = (region > 0.5).double().permute(2, 0, 1)[None]  # [1,1,H,W]
    k = 2 * pixels + 1
    kept = -F.max_pool2d(-F.pad(inside, (pixels,) * 4, value=0.0), k, stride=1)
    return kept[0].permute(1, 2, 0) > 0.5


def laplacian_energy(image: torch.Tensor) -> torch.Tensor:
    """|discrete Laplacian| of image [H,W,3], averaged over channels: [H,W] float64 (edge-replicated), the fine
    detail that blur removes."""
    x = image.double().permute(2, 0, 1)[:, None]  # [3,1,H,W]
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64, device=x.device)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), k.view(1, 1, 3, 3)).abs().mean(0)[0]


def flip_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """NVIDIA's FLIP error (Andersson et al. 2020, LDR, default 67 pixels per degree) of pred against gt [H,W,3] in
    [0,1]: [H,W] float64 in [0,1], 0 where they look alike. A perceptual error that needs no downloaded weights
    (the flip-evaluator package computes it)."""
    import flip_evaluator
    import numpy as np

    def arr(t: torch.Tensor):
        return np.ascontiguousarray(t.detach().clamp(0, 1).cpu().numpy(), dtype=np.float32)

    err, _, _ = flip_evaluator.evaluate(arr(gt), arr(pred), "LDR", applyMagma=False, computeMeanError=False)
    return torch.from_numpy(np.asarray(err, dtype=np.float64).reshape(gt.shape[0], gt.shape[1]))


def region_metrics(pred: torch.Tensor, gt: torch.Tensor, region: torch.Tensor, flip: torch.Tensor,
                   ssim_local: torch.Tensor) -> dict[str, float]:
    """Scores of pred against gt [H,W,3] inside `region` [H,W,1] (bool, already eroded), from the whole image's FLIP
    map [H,W] and SSIM map (ssim_map's [H-10,W-10] valid positions): psnr (over the region's pixels), ssim and flip
    (their maps' means there), detail (mean |Laplacian| of pred over gt's: 1 keeps the texture, < 1 blurs it).
    {} for an empty region."""
    m = region[..., 0]
    n = int(m.sum())
    if n == 0:
        return {}
    diff = (pred.double() - gt.double())[m]  # [n,3]
    mse = float((diff**2).mean())
    r = (m.shape[0] - ssim_local.shape[0]) // 2
    m_valid = m[r : m.shape[0] - r, r : m.shape[1] - r].to(ssim_local.device)
    lap_gt = float(laplacian_energy(gt)[m].mean())
    out = {"psnr": -10.0 * math.log10(mse) if mse > 0 else math.inf,
           "flip": float(flip.to(m.device)[m].mean()),
           "detail": float(laplacian_energy(pred)[m].mean()) / lap_gt if lap_gt > 0 else math.nan}
    if m_valid.any():
        out["ssim"] = float(ssim_local[m_valid].mean())
    return out


def image_metrics(pred: torch.Tensor, gt: torch.Tensor, alpha: torch.Tensor, mask: torch.Tensor,
                  garment: torch.Tensor | None = None, lpips: nn.Module | None = None) -> dict[str, float]:
    """Every score of one held-out image: pred, gt [H,W,3] in [0,1], alpha, mask [H,W,1], garment [H,W,1] (the
    pixels that show the garment, synthetic scenes) or None.

    Whole image: psnr, ssim, flip, iou (alpha > 0.5 against the mask), lpips (x1000, when given). Inside the mask's
    bounding box: psnr_masked, ssim_masked, flip_masked, lpips_masked. Inside the mask, eroded by REGION_ERODE:
    detail_masked. Inside the garment label, eroded likewise: psnr_garment, ssim_garment, flip_garment,
    detail_garment (absent when the label is empty after erosion)."""
    flip = flip_map(pred, gt)
    local = ssim_map(pred, gt)[0]
    rec = {"psnr": float(psnr(pred, gt)), "ssim": float(local.mean()), "flip": float(flip.mean()),
           "iou": float(silhouette_iou(alpha, mask))}
    y0, y1, x0, x1 = mask_bbox(mask)
    pb, gb = pred[y0:y1, x0:x1], gt[y0:y1, x0:x1]
    rec["psnr_masked"], rec["ssim_masked"] = float(psnr(pb, gb)), float(ssim(pb, gb))
    rec["flip_masked"] = float(flip[y0:y1, x0:x1].mean())
    inner = region_metrics(pred, gt, erode(mask), flip, local)
    if "detail" in inner:
        rec["detail_masked"] = inner["detail"]
    if garment is not None:
        rec.update({f"{k}_garment": v for k, v in region_metrics(pred, gt, erode(garment), flip, local).items()})
    if lpips is not None:
        rec["lpips"] = float(lpips(pred, gt)) * 1000.0
        rec["lpips_masked"] = float(lpips(pb, gb)) * 1000.0
    return rec


class EvalProtocol:
    """How a published table scores a held-out image (eval.protocol): which pixels of the prediction count
    (`masking`: none, Dyco's SMPL box, SeqAvatar's mask box + 5 px), whether images are floored to uint8 first, the
    SSIM and PSNR functions and LPIPS's input range. `prepare` makes the images the scores read; `scores` gives
    psnr, ssim and (with a network) lpips x1000."""

    def __init__(self, name: str, masking: Literal["none", "smpl_box", "mask_box"], quantise: bool,
                 ssim_fn, psnr_fn, lpips_range: Literal["[-1,1]", "[0,1]"], source: str) -> None:
        self.name, self.masking, self.quantise = name, masking, quantise
        self.ssim_fn, self.psnr_fn, self.lpips_range, self.source = ssim_fn, psnr_fn, lpips_range, source

    def describe(self) -> dict:
        """What metrics.json records under eval_protocol."""
        return {"name": self.name, "masking": self.masking, "uint8_floor": self.quantise,
                "ssim": self.ssim_fn.__name__, "psnr": self.psnr_fn.__name__, "lpips_input": self.lpips_range,
                "source": self.source}

    def prepare(self, pred: torch.Tensor, gt: torch.Tensor, keep: torch.Tensor | None,
                background: torch.Tensor | float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """pred, gt [H,W,3] in [0,1]; keep bool [H,W,1], the pixels the protocol scores (None for masking "none"):
        the prediction elsewhere becomes the background (Dyco: the ground truth too; its pixels there are already
        background in these datasets)."""
        if self.masking != "none":
            if keep is None:
                raise ValueError(f"eval.protocol={self.name}: needs the {self.masking} pixels of each image")
            bg = torch.as_tensor(background, dtype=pred.dtype, device=pred.device).expand_as(pred)
            pred = torch.where(keep, pred, bg)
            if self.masking == "smpl_box":
                gt = torch.where(keep, gt, bg.to(gt.dtype))
        if self.quantise:
            pred, gt = floor_uint8(pred), floor_uint8(gt)
        return pred, gt

    def scores(self, pred: torch.Tensor, gt: torch.Tensor, keep: torch.Tensor | None, lpips: nn.Module | None = None,
               background: torch.Tensor | float = 0.0) -> dict[str, float]:
        p, g = self.prepare(pred, gt, keep, background)
        out = {"psnr": float(self.psnr_fn(p, g)), "ssim": float(self.ssim_fn(p, g))}
        if lpips is not None:
            # our LPIPS maps [0,1] to the network's [-1,1]; "[0,1]" feeds the images unmapped, as SeqAvatar does
            p_in, g_in = (p, g) if self.lpips_range == "[-1,1]" else ((p + 1) / 2, (g + 1) / 2)
            out["lpips"] = float(lpips(p_in, g_in)) * 1000.0
        return out


PROTOCOLS = {
    # ours: the raw render against the image, image_metrics's scores (its SSIM: 11-wide Gaussian, valid positions)
    "ours": EvalProtocol("ours", "none", False, ssim, psnr, "[-1,1]", "realityavatar.metrics.image_metrics"),
    "dyco": EvalProtocol("dyco", "smpl_box", True, ssim_skimage, psnr, "[-1,1]",
                         "Yifever20002/Dyco run.py unpack_to_image + to_8b_image, core/utils/metrics_util.py "
                         "(skimage structural_similarity, LPIPS on x*2-1, x1000); SMPL box: "
                         "core/data/human_nerf/train.py skeleton_to_bbox (bbox_offset 0.3)"),
    "seqavatar": EvalProtocol("seqavatar", "mask_box", False, ssim_3dgs, psnr_per_channel, "[0,1]",
                              "zezeaaa/SeqAvatar render.py (bound mask: utils/image_utils.get_rect_bound_mask, 5 px; "
                              "ssim: utils/loss_utils; psnr: utils/image_utils; lpips.LPIPS(net='vgg') on [0,1])"),
}


def eval_protocol(name: str) -> EvalProtocol:
    """The EvalProtocol `eval.protocol` names."""
    if name not in PROTOCOLS:
        raise ValueError(f"eval.protocol: expected one of {', '.join(PROTOCOLS)}, got {name!r}")
    return PROTOCOLS[name]


def temporal_flicker(frames_pred: torch.Tensor, frames_gt: torch.Tensor) -> float:
    """Frame-to-frame change error: mean_t |(pred_t - pred_{t-1}) - (gt_t - gt_{t-1})| over pixels and channels.

    frames [F,H,W,3] of one camera in time order. 0 when the rendering changes exactly as the video does;
    penalises both flicker (changes the video lacks) and frozen motion (missing changes).
    """
    if frames_pred.shape != frames_gt.shape or frames_pred.ndim != 4 or frames_pred.shape[0] < 2:
        raise ValueError(
            f"temporal_flicker: expected two [F>=2,H,W,3] tensors of one shape, got {tuple(frames_pred.shape)}, {tuple(frames_gt.shape)}"
        )
    dp = frames_pred[1:].float() - frames_pred[:-1].float()
    dg = frames_gt[1:].float() - frames_gt[:-1].float()
    return float((dp - dg).abs().mean())


# ---------------------------------------------------------------------- backbones (torchvision `features` layouts)
_VGG_CFG = {
    "vgg16": [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"],
    "vgg19": [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512, "M"],
}


def vgg_features(arch: Literal["vgg16", "vgg19"]) -> nn.Sequential:
    """torchvision's vgg16/vgg19 `.features` (same layer indices, so its state-dict keys load directly)."""
    layers: list[nn.Module] = []
    c = 3
    for v in _VGG_CFG[arch]:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
            c = v
    return nn.Sequential(*layers)


def load_state_file(path: str, what: str) -> dict[str, torch.Tensor]:
    """A weights file that must hold a state dict (a torchvision checkpoint, an lpips lin file); errors name the file."""
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load raises several types on a truncated or foreign file
        first = (str(e).strip().splitlines() or [""])[0].split(". ")[0][:160]  # torch's advice is for trusted files
        raise ValueError(f"{what} {path!r}: not a torch state dict file ({type(e).__name__}: {first})") from e
    if isinstance(sd, dict) and "state_dict" in sd:
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not all(torch.is_tensor(v) for v in sd.values()):
        raise ValueError(f"{what} {path!r}: expected a state dict (name -> tensor), got {type(sd).__name__}")
    return sd


def load_features_state(features: nn.Sequential, path: str) -> None:
    """Load the `features.*` entries of a torchvision checkpoint (e.g. vgg19-dcbb9e9d.pth) into `features`
    (which may be a prefix of torchvision's `.features`; extra checkpoint layers are ignored)."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"backbone weights: file {path!r} does not exist")
    sd = load_state_file(path, "backbone weights")
    own = features.state_dict()
    sub = {k[len("features."):]: v for k, v in sd.items() if k.startswith("features.") and k[len("features."):] in own}
    missing = sorted(set(own) - set(sub))
    if missing:
        raise ValueError(f"backbone weights {path!r}: missing torchvision 'features.*' keys {missing[:4]}... "
                         "(expected a torchvision vgg16/vgg19 state dict)")
    features.load_state_dict(sub)


# ---------------------------------------------------------------------- LPIPS
# VGG only: every eval.protocol (ours, Dyco, SeqAvatar) scores LPIPS with lpips.LPIPS(net="vgg")
_LPIPS_TAPS = {"vgg": (3, 8, 15, 22, 29)}  # relu outputs used by lpips
_LPIPS_CHANNELS = {"vgg": (64, 128, 256, 512, 512)}
_LPIPS_MIN_SIZE = {"vgg": 16}  # smaller images leave a pooling layer no output


def _lpips_input(x: torch.Tensor, name: str, net: str, like: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """[H,W,3] or [B,H,W,3] in [0,1] -> [B,3,H',W'] in [-1,1] in `like`'s device and dtype, edge-padded up to the
    network's smallest input (a thin mask box; the lpips package fails on those)."""
    b, single = _batched(x, name)
    b = b.to(like).permute(0, 3, 1, 2) * 2 - 1
    m = _LPIPS_MIN_SIZE.get(net, 0)
    ph, pw = max(m - b.shape[-2], 0), max(m - b.shape[-1], 0)
    if ph or pw:
        b = F.pad(b, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2), mode="replicate")
    return b, single


TORCHVISION_NAMES = {"vgg": "vgg16-397923af.pth"}


def resolve_lpips_paths(
    net: str, lin_weights: str | None, backbone_weights: str | None = None
) -> tuple[str | None, str | None]:
    """Accept files or a directory: a directory `lin_weights` means <dir>/<net>.pth (lpips package file name) and,
    when backbone_weights is not given, <dir>/<torchvision file name> (vgg16-397923af.pth)."""
    lin, backbone = lin_weights, backbone_weights
    if lin and os.path.isdir(lin):
        if not backbone:
            backbone = os.path.join(lin, TORCHVISION_NAMES.get(net, ""))
        lin = os.path.join(lin, f"{net}.pth")
    if backbone and os.path.isdir(backbone):
        backbone = os.path.join(backbone, TORCHVISION_NAMES.get(net, ""))
    return backbone, lin


def lpips_status(backbone_weights: str | None = None, lin_weights: str | None = None) -> str:
    """'computed' when both weight files exist, else 'not computed: <why>' (the text metrics.json records)."""
    if not backbone_weights or not lin_weights:
        return ("not computed: no LPIPS weights (set metrics.lpips_weights=<dir with the lpips vgg.pth and "
                "torchvision vgg16-397923af.pth>, or metrics.lpips_backbone_weights=<file>)")
    for p in (backbone_weights, lin_weights):
        if not os.path.isfile(p):
            return f"not computed: LPIPS weight file {p} does not exist"
    return "computed"


class LPIPS(nn.Module):
    """LPIPS (Zhang et al. 2018) in pure torch, v0.1 linear layers, like `lpips.LPIPS(net=..., normalize=True)`.

    Inputs [H,W,3] or [B,H,W,3] in [0,1] are mapped to [-1,1], shifted/scaled by lpips' ScalingLayer, passed
    through the backbone (torchvision's vgg16 weights), unit-normalised per channel; squared
    differences are weighted by the learned 1x1 convs (lin weights file of the lpips package, keys
    `lin{k}.model.1.weight`) and spatially averaged. Tables report the value x1000. Images smaller than the
    network's smallest input (16 px) are edge-padded up to it.
    """

    def __init__(self, net: Literal["vgg"] = "vgg", backbone_weights: str = "", lin_weights: str = "") -> None:
        super().__init__()
        if net not in _LPIPS_TAPS:
            raise ValueError(f"LPIPS: net expected 'vgg' (the network every eval.protocol uses), got {net!r}")
        status = lpips_status(backbone_weights, lin_weights)
        if status != "computed":
            raise FileNotFoundError(f"LPIPS: {status}")
        self.net = net
        self.taps = _LPIPS_TAPS[net]
        self.features = vgg_features("vgg16")[: self.taps[-1] + 1]  # the final max-pool is never used
        load_features_state(self.features, backbone_weights)
        chans = _LPIPS_CHANNELS[net]
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in chans])
        sd = load_state_file(lin_weights, "LPIPS lin weights")
        for k, lin in enumerate(self.lins):
            key = f"lin{k}.model.1.weight"
            if key not in sd or sd[key].shape != lin.weight.shape:
                raise ValueError(f"LPIPS lin weights {lin_weights!r}: expected {key} of shape {tuple(lin.weight.shape)}")
            lin.weight.data.copy_(sd[key])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        p, single = _lpips_input(pred, "pred", self.net, self.shift)  # the network's device and dtype
        g, _ = _lpips_input(gt, "gt", self.net, self.shift)
        x, y = (p - self.shift) / self.scale, (g - self.shift) / self.scale
        total = 0.0
        with no_tf32():
            for lin, fx, fy in zip(self.lins, self._taps(x), self._taps(y)):
                nx = fx / (fx.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
                ny = fy / (fy.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
                total = total + lin((nx - ny) ** 2).mean((1, 2, 3))
        return total[0] if single else total


# ---------------------------------------------------------------------- weights found in the environment
def hub_checkpoint(name: str) -> str | None:
    """torchvision's download cache entry `name` (<torch.hub.get_dir()>/checkpoints, i.e. $TORCH_HOME/hub/checkpoints,
    TORCH_HOME defaulting to ~/.cache/torch), or None when it is not there."""
    path = os.path.join(torch.hub.get_dir(), "checkpoints", name)
    return path if os.path.isfile(path) else None


def _home_relative(path: str) -> str:
    """`path` with the user's home as `~`: the status is written into metrics.json, and results committed from one
    machine should not carry its home folder."""
    home = os.path.expanduser("~")
    return "~" + path[len(home):] if home not in ("", "/") and path.startswith(home + os.sep) else path


def lpips_package_file(net: str) -> str | None:
    """The installed lpips package's v0.1 linear layers, <package>/weights/v0.1/<net>.pth, or None. Found without
    importing lpips (that imports torchvision, which need not work with this torch)."""
    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):  # ValueError: a module in sys.modules without a spec
        return None
    for root in (spec.submodule_search_locations or []) if spec else []:
        path = os.path.join(root, "weights", "v0.1", f"{net}.pth")
        if os.path.isfile(path):
            return path
    return None


class PackageLPIPS(nn.Module):
    """The lpips package's `lpips.LPIPS(net=...)` behind LPIPS's interface: [H,W,3] or [B,H,W,3] in [0,1] -> one
    value per image (the package takes [B,3,H,W] in [-1,1] and returns [B,1,1,1])."""

    def __init__(self, model: nn.Module, net: str = "vgg") -> None:
        super().__init__()
        self.model, self.net = model.requires_grad_(False).eval(), net

    def train(self, mode: bool = True):  # the package's lin layers hold dropout: always in eval mode
        return super().train(False)

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        ref = next(self.model.parameters())  # the network's device and dtype
        x, single = _lpips_input(pred, "pred", self.net, ref)
        y, _ = _lpips_input(gt, "gt", self.net, ref)
        with no_tf32():
            d = self.model(x, y).flatten()  # [B]
        return d[0] if single else d


def package_lpips(net: str) -> tuple[PackageLPIPS | None, str]:
    """(lpips.LPIPS(net) wrapped, "computed (lpips package <version> <net>)") when lpips and torchvision import and
    torchvision has (or, connected, downloads) its backbone; else (None, why not)."""
    try:
        import lpips  # imports torchvision

        model = lpips.LPIPS(net=net, verbose=False)
    except Exception as e:  # noqa: BLE001 (not installed, a torchvision built for another torch, offline download)
        return None, f"lpips package not used: {type(e).__name__}: {e}"
    try:
        version = importlib.metadata.version("lpips")
    except importlib.metadata.PackageNotFoundError:
        version = getattr(lpips, "__version__", "unknown version")
    return PackageLPIPS(model, net), f"computed (lpips package {version} {net})"


def build_lpips(net: str = "vgg", backbone_weights: str | None = None,
                lin_weights: str | None = None) -> tuple[LPIPS | PackageLPIPS | None, str]:
    """(LPIPS module, "computed (<where the weights came from>)") or (None, "not computed: <why>"): the status that
    metrics.json records. In order: configured weights (`lin_weights` a file or a directory, see
    resolve_lpips_paths); without them the lpips package itself when it and torchvision import; then the pure-torch
    LPIPS on the installed lpips package's lin file and torchvision's backbone in torch's hub cache (or
    `backbone_weights`)."""
    if lin_weights:
        backbone, lin = resolve_lpips_paths(net, lin_weights, backbone_weights)
        lin_from = "metrics.lpips_weights"
        backbone_from = "metrics.lpips_backbone_weights" if backbone_weights else lin_from
    else:
        reasons = []
        if not backbone_weights:
            model, why = package_lpips(net)
            if model is not None:
                return model, why
            reasons.append(why)
        name = TORCHVISION_NAMES.get(net, "")
        backbone, _ = resolve_lpips_paths(net, None, backbone_weights)
        backbone_from = "metrics.lpips_backbone_weights" if backbone_weights else "torch hub"
        backbone = backbone or hub_checkpoint(name)
        lin, lin_from = lpips_package_file(net), "lpips package"
        if not lin or not backbone:
            missing = ([] if lin else [f"lpips package weights/v0.1/{net}.pth"]) + (
                [] if backbone else [_home_relative(os.path.join(torch.hub.get_dir(), "checkpoints", name))])
            reasons.append(f"not found: {', '.join(missing)}")
            return None, (f"not computed: no LPIPS weights ({'; '.join(reasons)}; set metrics.lpips_weights=<dir "
                          f"with the lpips {net}.pth and torchvision {name}>)")
    status = lpips_status(backbone, lin)
    if status != "computed":
        return None, status
    return LPIPS(net, backbone, lin), f"computed (weights: {lin_from} {lin} + {backbone_from} {backbone})"
