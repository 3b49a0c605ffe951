"""Training loss L1 + λ1 mask + λ2 perceptual (VGG19 features, or D-SSIM without weights) + λ3 skinning."""

from __future__ import annotations

import os
from typing import Literal

import torch
import torch.nn.functional as F
from kornia.losses import ssim_loss
from torch import nn

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
    3DGS-Avatar: lambda_skin_start before skin_decay_step, lambda_skin_end after.
    """

    def __init__(
        self,
        lambda_mask: float = 0.1,
        lambda_perceptual: float = 0.01,
        lambda_dssim: float = 0.2,
        lambda_skin_start: float = 10.0,
        lambda_skin_end: float = 0.1,
        skin_decay_step: int = 1000,
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
        self.skin_decay_step = skin_decay_step
        self.mask_loss = mask_loss

    def lambda_skin(self, step: int) -> float:
        return self.lambda_skin_start if step < self.skin_decay_step else self.lambda_skin_end

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
        step: int = 0,
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
                terms["perceptual"] = ssim_loss(x, y, window_size=11)
        total = terms["l1"] + self.lambda_mask * terms["mask"]
        if "perceptual" in terms:
            total = total + self.lambda_perceptual * terms["perceptual"]
        if skinning is not None and skin_points is not None and skin_weights is not None:
            terms["skin"] = skinning_loss(skinning, skin_points, skin_weights)
            total = total + self.lambda_skin(step) * terms["skin"]
        terms = {k: v.detach() for k, v in terms.items()}
        return total, terms
