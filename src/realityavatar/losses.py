"""Training loss L1 + λ1 mask + λ2 perceptual (VGG19 features, or D-SSIM without weights) + λ3 skinning."""

from __future__ import annotations

import os
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.kernels import dssim
from realityavatar.metrics import load_features_state, vgg_features
from realityavatar.model.skinning import skinning_loss

_VGG19_TAPS = (1, 6, 11, 20, 29)  # relu1_1 .. relu5_1
_VGG19_WEIGHTS = (1 / 32, 1 / 16, 1 / 8, 1 / 4, 1.0)  # pix2pixHD's per-layer weights (deeper = more semantic)


class VGG19Loss(nn.Module):
    """Perceptual loss: weighted L1 between VGG19 relu{1..5}_1 features of ImageNet-normalised images.

    Weights: a torchvision vgg19 state dict (vgg19-dcbb9e9d.pth); frozen.
    """

    def __init__(self, weights_path: str) -> None:
        super().__init__()
        self.features = vgg_features("vgg19")[: _VGG19_TAPS[-1] + 1]  # layers after relu5_1 are never used
        load_features_state(self.features, weights_path)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True):  # the backbone stays in eval mode
        return super().train(False)

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """pred, gt [B,3,H,W] in [0,1] -> scalar."""
        x, y = (pred - self.mean) / self.std, (gt - self.mean) / self.std
        loss = pred.new_zeros(())
        k = 0
        for i, layer in enumerate(self.features):
            x, y = layer(x), layer(y)
            if i in _VGG19_TAPS:
                loss = loss + _VGG19_WEIGHTS[k] * (x - y).abs().mean()
                k += 1
        return loss


class AvatarLoss(nn.Module):
    """L = L1 + λ_mask L_mask + λ_p L_percep + λ_skin(step) L_skin (paper §Optimization).

    perceptual="auto" uses VGG19 when `vgg19_weights` points to a file, else D-SSIM = (1 - SSIM)/2 (kornia,
    11x11 window) weighted by lambda_dssim (VGG feature losses and D-SSIM differ in scale, so each has its own
    λ). `perceptual_kind` records which one is used ("vgg19" | "dssim"). The skinning weight follows
    3DGS-Avatar: lambda_skin_start, then lambda_skin_end once the caller says so (`skin_decayed`, from the
    module's Schedule.skin_switch: step-dependent switches live in the schedule, not here).
    """

    def __init__(
        self,
        lambda_mask: float = 0.1,
        lambda_perceptual: float = 0.01,
        lambda_dssim: float = 0.2,
        lambda_skin_start: float = 10.0,
        lambda_skin_end: float = 0.1,
        mask_loss: Literal["mse", "bce", "l1"] = "mse",
        perceptual: Literal["auto", "vgg19", "dssim"] = "auto",
        vgg19_weights: str | None = None,
    ) -> None:
        super().__init__()
        if perceptual not in ("auto", "vgg19", "dssim"):
            raise ValueError(f"loss.perceptual: expected 'auto', 'vgg19' or 'dssim', got {perceptual!r}")
        if mask_loss not in ("mse", "bce", "l1"):
            raise ValueError(f"loss.mask_loss: expected 'mse', 'bce' or 'l1', got {mask_loss!r}")
        have_vgg = bool(vgg19_weights) and os.path.isfile(str(vgg19_weights))
        if perceptual == "vgg19" and not have_vgg:
            raise FileNotFoundError(f"loss.vgg19_weights: perceptual=vgg19 needs a torchvision vgg19 .pth, got {vgg19_weights!r}")
        self.perceptual_kind = "vgg19" if (perceptual == "vgg19" or (perceptual == "auto" and have_vgg)) else "dssim"
        self.vgg = VGG19Loss(str(vgg19_weights)) if self.perceptual_kind == "vgg19" else None
        self.lambda_mask = lambda_mask
        self.lambda_perceptual = lambda_perceptual if self.perceptual_kind == "vgg19" else lambda_dssim
        self.lambda_skin_start = lambda_skin_start
        self.lambda_skin_end = lambda_skin_end
        self.mask_loss = mask_loss

    def lambda_skin(self, decayed: bool) -> float:
        return self.lambda_skin_end if decayed else self.lambda_skin_start

    def forward(
        self,
        pred_rgb: torch.Tensor,
        pred_alpha: torch.Tensor,
        gt_rgb: torch.Tensor,
        gt_mask: torch.Tensor,
        *,
        skinning: nn.Module | None = None,
        skin_points: torch.Tensor | None = None,
        skin_weights: torch.Tensor | None = None,
        skin_decayed: bool = False,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """pred_rgb, gt_rgb [B,H,W,3]; pred_alpha, gt_mask [B,H,W,1]; skin samples [P,3], [P,24] -> (total, terms)."""
        terms: dict[str, torch.Tensor] = {"l1": (pred_rgb - gt_rgb).abs().mean()}
        a = pred_alpha
        if self.mask_loss == "mse":
            terms["mask"] = ((a - gt_mask) ** 2).mean()
        elif self.mask_loss == "l1":
            terms["mask"] = (a - gt_mask).abs().mean()
        else:
            terms["mask"] = F.binary_cross_entropy(a.clamp(1e-5, 1 - 1e-5), gt_mask)
        if self.lambda_perceptual > 0:
            x = pred_rgb.permute(0, 3, 1, 2)
            y = gt_rgb.permute(0, 3, 1, 2)
            if self.vgg is not None:
                terms["perceptual"] = self.vgg(x, y)
            else:
                terms["perceptual"] = dssim(x, y)  # kornia's ssim_loss(x, y, 11); fused Numba kernel on the CPU
        total = terms["l1"] + self.lambda_mask * terms["mask"]
        if "perceptual" in terms:
            total = total + self.lambda_perceptual * terms["perceptual"]
        if skinning is not None and skin_points is not None and skin_weights is not None:
            terms["skin"] = skinning_loss(skinning, skin_points, skin_weights)
            total = total + self.lambda_skin(skin_decayed) * terms["skin"]
        terms = {k: v.detach() for k, v in terms.items()}
        return total, terms


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """points [N,3] world, viewmat [4,4] world-to-camera (OpenCV), K [3,3] -> pixel coords [N,2], depth [N]."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]  # [N,3]
    z = cam[:, 2]
    zc = z.clamp(min=1e-3)
    uv = torch.stack([K[0, 0] * cam[:, 0] / zc + K[0, 2], K[1, 1] * cam[:, 1] / zc + K[1, 2]], -1)
    return uv, z


def mask_distance(mask: torch.Tensor) -> torch.Tensor:
    """mask [H,W] (1 inside) -> Euclidean distance in pixels of every pixel to the nearest mask pixel [H,W]."""
    from scipy.ndimage import distance_transform_edt

    m = (mask.detach() > 0.5).cpu().numpy()
    if not m.any():
        return torch.zeros_like(mask)
    return torch.from_numpy(distance_transform_edt(~m)).to(mask)


def outside_distance(uv: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Pixel coords uv [N,2], a mask's distance field dist [H,W] (pixels) -> each point's distance to the mask [N]:
    the field sampled bilinearly inside the image, plus the distance to the image beyond it."""
    H, W = dist.shape
    lim = uv.new_tensor([W - 1.0, H - 1.0])
    inside = torch.minimum(torch.maximum(uv, uv.new_zeros(2)), lim)
    grid = (inside / lim * 2 - 1)[None, None]  # [1,1,N,2] in grid_sample's [-1,1] (align_corners=True)
    d_in = F.grid_sample(dist[None, None], grid, mode="bilinear", align_corners=True)[0, 0, 0]  # [N]
    return d_in + (uv - inside).norm(dim=-1)


def nearest_index(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Index into points [N,2] of the nearest point to each query [P,2] (no gradient). On the CPU a k-d tree
    (O((N + P) log N); the dense [P,N] distance matrix was most of the silhouette term's cost at 10k Gaussians),
    on a GPU the dense argmin."""
    if queries.device.type != "cpu":
        return torch.cdist(queries, points).argmin(1)
    from scipy.spatial import cKDTree

    _, idx = cKDTree(points.detach().double().numpy()).query(queries.detach().double().numpy(), k=1)
    return torch.from_numpy(idx).long()


class SilhouetteChamfer(nn.Module):
    """Long-range silhouette supervision: a 2D chamfer between projected Gaussian centres and the mask.

    Photometric and per-pixel mask losses reach a Gaussian only through pixels its footprint covers, so a
    Gaussian 30 cm from a flared hem gets no pull towards it. Two terms, in image heights squared:
    - outside: every projected centre outside the mask is pulled in along the mask's distance field
      (a visual-hull condition: every point of the subject projects inside every camera's silhouette);
    - coverage: mask pixels the prediction leaves uncovered (alpha < `covered_alpha`; at most `max_pixels`,
      sampled) pull their nearest projected centre.
    """

    def __init__(self, weight: float = 10.0, outside_weight: float = 1.0, coverage_weight: float = 1.0,
                 covered_alpha: float = 0.5, max_pixels: int = 1024, near: float = 0.05) -> None:
        super().__init__()
        if weight < 0 or outside_weight < 0 or coverage_weight < 0:
            raise ValueError("silhouette: weights must be >= 0")
        self.weight, self.outside_weight, self.coverage_weight = float(weight), float(outside_weight), float(coverage_weight)
        self.covered_alpha, self.max_pixels, self.near = float(covered_alpha), int(max_pixels), float(near)
        self.last_pulled: torch.Tensor | None = None  # set by forward: the Gaussians uncovered pixels pulled

    def forward(self, means: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, mask: torch.Tensor,
                alpha: torch.Tensor) -> dict[str, torch.Tensor]:
        """means [N,3] posed, viewmat [4,4], K [3,3], mask / alpha [H,W,1] -> {"sil_outside", "sil_coverage"}."""
        H = mask.shape[0]
        uv, z = project_points(means, viewmat, K)
        front = z > self.near
        uv, scale = uv[front], float(H)
        d = outside_distance(uv, mask_distance(mask[..., 0]))  # [N] pixels
        out = {"sil_outside": ((d / scale) ** 2).mean() if d.numel() else means.new_zeros(())}
        # Coverage: uncovered mask pixels -> their nearest projected centre.
        need = ((mask[..., 0] > 0.5) & (alpha[..., 0].detach() < self.covered_alpha)).nonzero()  # [P,2] (y,x)
        if need.shape[0] and uv.shape[0]:
            if need.shape[0] > self.max_pixels:
                need = need[torch.randperm(need.shape[0], device=need.device)[: self.max_pixels]]
            pix = need.flip(-1).to(uv.dtype)  # [P,2] (x,y)
            nearest = nearest_index(pix, uv.detach())  # [P]
            out["sil_coverage"] = (((uv[nearest] - pix) / scale) ** 2).sum(-1).mean()
            # Which Gaussians the uncovered pixels pulled (indices into `means`), for density=coverage.
            self.last_pulled = front.nonzero().squeeze(-1)[nearest.to(front.device)].detach()
        else:
            out["sil_coverage"] = means.new_zeros(())
            self.last_pulled = None
        return out

    def total(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.weight * (self.outside_weight * terms["sil_outside"] + self.coverage_weight * terms["sil_coverage"])


class NoSilhouette(nn.Module):
    """Ablation: no long-range silhouette term (only the per-pixel mask loss supervises the silhouette)."""

    weight = 0.0

    def forward(self, means, viewmat, K, mask, alpha) -> dict[str, torch.Tensor]:
        return {}

    def total(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.zeros(())  # never added by the module: forward returns no terms


class FlowLoss(nn.Module):
    """Image-flow supervision of the Gaussians' motion (`flow=dis`): against sliding over the garment.

    Each training image (frame t, camera c) comes with the optical flow to camera c's image at t - frame_gap
    (`data.flow.flow_pair`: DIS both ways, forward-backward checked, inside the eroded mask). The module deforms the
    Gaussians for that earlier frame too (no gradient), projects both positions into camera c and renders each
    Gaussian's image displacement (u_{t-gap} - u_t, in image heights, clamped to +-max_motion) with the image's blend
    weights, detached (a second raster pass), so the term moves Gaussians and never fades or shrinks them. The term
    is the L1 between that rendered flow and alpha x the image flow over the valid pixels (mean over them): a
    Gaussian is pulled to move with the material under it, also along the cloth, where the photometric loss is blind
    once the texture is blurred.
    """

    def __init__(self, weight: float = 1.0, frame_gap: int = 1, preset: str = "medium", fb_tol: float = 1.0,
                 erode: int = 1, source: str = "dis", dir: str | None = None, max_motion: float = 0.1,
                 eps_px: float = 0.5, prev_grad: bool = False) -> None:
        super().__init__()
        from realityavatar.data.flow import FlowSpec

        if not (weight >= 0):
            raise ValueError(f"flow.weight: expected a number >= 0, got {weight!r}")
        if not (max_motion > 0):
            raise ValueError(f"flow.max_motion: expected a number > 0 (image heights), got {max_motion!r}")
        if not (eps_px > 0):
            raise ValueError(f"flow.eps_px: expected a number > 0 (pixels), got {eps_px!r}")
        self.weight, self.max_motion, self.eps_px = float(weight), float(max_motion), float(eps_px)
        self.prev_grad = bool(prev_grad)
        self.spec = FlowSpec(frame_gap=int(frame_gap), source=str(source), dir=dir, preset=str(preset),
                             fb_tol=float(fb_tol), erode=int(erode))

    def forward(self, pred: torch.Tensor, alpha: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """pred [B,H,W,2] rendered displacement (image heights), alpha [B,H,W,1], flow [B,H,W,2] (pixels),
        valid [B,H,W,1] -> mean Charbonnier penalty over valid pixels, in image heights (0 when none).

        Per pixel sqrt(|e|^2 + eps^2) - eps with e the end-point error in pixels: like L1 for errors well above
        eps_px, quadratic below, so a Gaussian that already moves with the flow gets no push. (With plain L1 the
        sign of a vanishing error drove every Gaussian at full strength, and Adam made that noise a random walk:
        with the exact flow, seed 0, held-out IoU at rest fell from 0.94 to 0.67.)"""
        H = flow.shape[1]
        e = (pred * H - alpha.detach() * flow) * valid  # pixels
        pen = (e.square().sum(-1, keepdim=True) + self.eps_px**2).sqrt() - self.eps_px
        return (pen * valid).sum() / valid.sum().clamp_min(1.0) / H


class NoFlow(nn.Module):
    """No flow term (the default): the training samples carry no flow and the module renders no displacement."""

    weight = 0.0
    spec = None
