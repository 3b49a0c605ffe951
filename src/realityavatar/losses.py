"""Training loss terms: L1 + λ1 mask + λ2 perceptual (D-SSIM, or VGG19 features) + λ3 skinning (paper §Optimization),
the long-range silhouette term and the garment sheet's strain; each term a component with its weight (and schedule),
summed by `total_loss` in the configured order."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import kd_tree, sample_surface
from realityavatar.kernels import dssim
from realityavatar.metrics import hub_checkpoint, load_features_state, vgg_features
from realityavatar.model.skinning import skinning_loss
from realityavatar.runtime import constant, host_path

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


@dataclass
class TrainingRender:
    """What a loss term sees of one training step: the rendered batch and the avatar that rendered it."""

    rgb: torch.Tensor  # [B,H,W,3]
    alpha: torch.Tensor  # [B,H,W,1]
    batch: dict  # the DataModule's batch: image [B,H,W,3], mask [B,H,W,1], viewmat, K, ...
    posed: dict  # Avatar.deform's output: means [B,N,3], ... (sheet=skirt: sheet_verts [B,P,3])
    avatar: nn.Module  # model/avatar.py Avatar: body, skinning, sheet, ...


def total_loss(terms: Mapping[str, nn.Module], out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The training loss: the sum of the configured terms in their order (conf/loss plus the silhouette group), each
    term(out) -> (its weighted value, {name: detached value to log}). A term that is off is not in `terms`."""
    total, logs = None, {}
    for term in terms.values():
        value, logged = term(out)
        total = value if total is None else total + value
        logs.update(logged)
    return total, logs


class LossTerm(nn.Module):
    """A term of the training loss: forward(out) -> (its weighted value, {name: detached value to log}).
    bind(avatar) runs once, when the module is built: outside torch.compile's graphs, what a term draws from the
    avatar ahead of training (a term that needs nothing keeps this one). set_progress(step) runs before every
    training step, also outside the graphs: a term whose weight follows a schedule keeps it in a buffer, so that the
    compiled loss reads a tensor and is not traced again when the weight changes."""

    weights_from: str | None = None  # the network weights file a term loaded (metrics.json's perceptual_weights)

    def bind(self, avatar: nn.Module) -> None:
        """Nothing to prepare."""

    def set_progress(self, step: int | None) -> None:
        """Nothing follows the step (None: a finished run)."""


class NoLoss(LossTerm):
    """A term that adds nothing (`silhouette=none`)."""

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return out.rgb.new_zeros(()), {}


class ColourL1(LossTerm):
    """weight x mean |rendered - ground-truth colour| (the paper's L1)."""

    def __init__(self, weight: float) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        v = (out.rgb - out.batch["image"]).abs().mean()
        return self.weight * v, {"l1": v.detach()}


class MaskLoss(LossTerm):
    """weight x the rendered alpha's disagreement with the mask: mean squared (mse), absolute (l1) or BCE (bce)."""

    def __init__(self, weight: float, kind: Literal["mse", "bce", "l1"]) -> None:
        super().__init__()
        if kind not in ("mse", "bce", "l1"):
            raise ValueError(f"loss.mask.kind: expected 'mse', 'bce' or 'l1', got {kind!r}")
        self.weight, self.kind = float(weight), kind

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        a, m = out.alpha, out.batch["mask"]
        if self.kind == "mse":
            v = ((a - m) ** 2).mean()
        elif self.kind == "l1":
            v = (a - m).abs().mean()
        else:
            v = F.binary_cross_entropy(a.clamp(1e-5, 1 - 1e-5), m)
        return self.weight * v, {"mask": v.detach()}


class DSSIMLoss(LossTerm):
    """λ2 as D-SSIM: weight x (1 - SSIM)/2 (11x11 window; kornia's ssim_loss(x, y, 11), a fused Numba kernel on the
    CPU). It needs no downloaded weights (`loss=default`)."""

    kind = "dssim"  # metrics.json's `perceptual`

    def __init__(self, weight: float) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        v = dssim(out.rgb.permute(0, 3, 1, 2), out.batch["image"].permute(0, 3, 1, 2))
        return self.weight * v, {"perceptual": v.detach()}


VGG19_HUB_NAME = "vgg19-dcbb9e9d.pth"  # torchvision's vgg19 in torch's hub cache


class VGG19PerceptualLoss(LossTerm):
    """λ2 as the paper's perceptual loss: weight x `VGG19Loss` (`loss=vgg19`). vgg19_weights: a torchvision vgg19
    .pth, or null for torchvision's vgg19 in torch's hub cache ($TORCH_HOME/hub/checkpoints); neither is an error.
    VGG feature losses and D-SSIM differ in scale: each term has its own weight."""

    kind = "vgg19"

    def __init__(self, weight: float, vgg19_weights: str | None) -> None:
        super().__init__()
        self.weights_from = f"loss.perceptual.vgg19_weights {vgg19_weights}"
        if not vgg19_weights and (found := hub_checkpoint(VGG19_HUB_NAME)):
            vgg19_weights, self.weights_from = found, f"torch hub {found}"
        if not vgg19_weights or not Path(vgg19_weights).is_file():
            raise FileNotFoundError(f"loss.perceptual.vgg19_weights: expected a torchvision vgg19 .pth (or "
                                    f"{VGG19_HUB_NAME} in torch's hub cache), got {vgg19_weights!r}")
        self.vgg = VGG19Loss(str(vgg19_weights))
        self.weight = float(weight)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        v = self.vgg(out.rgb.permute(0, 3, 1, 2), out.batch["image"].permute(0, 3, 1, 2))
        return self.weight * v, {"perceptual": v.detach()}


class SkinningLoss(LossTerm):
    """The paper's L_skin: the skinning field against the body's weights at `samples` points drawn from the canonical
    body surface each step; weight until step `switch`, weight_after from then on (3DGS-Avatar's 10 -> 0.1). Only for
    a skinning field that trains (`loss=learnt_skinning` with skinning=mlp or skinning.learnable=true): with the
    frozen grid it would have no gradient, and `bind` refuses it."""

    def __init__(self, weight: float, weight_after: float, switch: int, samples: int) -> None:
        super().__init__()
        self.weight, self.weight_after, self.switch = float(weight), float(weight_after), int(switch)
        self.samples = int(samples)
        # The pool the samples are drawn from (bind): moved with the module, not saved in checkpoints.
        self.register_buffer("pool_points", torch.zeros(0, 3), persistent=False)
        self.register_buffer("pool_weights", torch.zeros(0, 0), persistent=False)
        # The weight at the current step (set_progress), on the module's device.
        self.register_buffer("weight_now", torch.tensor(self.weight), persistent=False)
        self._weight_set = self.weight

    def bind(self, avatar: nn.Module) -> None:
        """A fixed pool of 20 x `samples` points on the canonical body surface and the body's weights there [P,24]."""
        if not any(p.requires_grad for p in avatar.skinning.parameters()):
            raise ValueError(f"loss.skinning: the skinning field {type(avatar.skinning).__name__} has no trained "
                             "weights (skinning=grid with learnable: false), so the term would have no gradient; use "
                             "it with skinning=mlp or skinning.learnable=true, or loss=default")
        body = avatar.body
        self.pool_points, self.pool_weights = sample_surface(
            body.canonical_vertices().detach(), body.faces, body.skin_weights, 20 * self.samples,
            torch.Generator().manual_seed(1234))

    def set_progress(self, step: int | None) -> None:
        """weight before step `switch`, weight_after from it on and for a finished run (None); the buffer is
        written only when the weight changes (no launch in the other steps)."""
        w = self.weight_after if step is None or step >= self.switch else self.weight
        if w != self._weight_set:
            self.weight_now.fill_(w)
            self._weight_set = w

    def targets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """`samples` surface points [S,3] and the body's weights there [S,24], drawn from the pool."""
        if not len(self.pool_points):
            raise RuntimeError("SkinningLoss: no surface pool; bind(avatar) first (AvatarModule binds its terms)")
        idx = torch.randint(0, self.pool_points.shape[0], (self.samples,), device=self.pool_points.device)
        return self.pool_points[idx], self.pool_weights[idx]

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        pts, w = self.targets()
        v = skinning_loss(out.avatar.skinning, pts, w)
        return self.weight_now * v, {"skin": v.detach()}


class SheetStrain(LossTerm):
    """weight x the garment sheet's stretch down the garment beyond sheet.strain_free (model/sheet.py `strain`),
    on the posed vertices; only with sheet=skirt: `'+loss.sheet_strain={_target_:realityavatar.losses.SheetStrain}'`."""

    def __init__(self, weight: float) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        v = out.avatar.sheet.strain(out.posed["sheet_verts"])
        return self.weight * v, {"sheet_strain": v.detach()}


class SheetSlideSmooth(LossTerm):
    """The sliding sheet's smoothness (SlidingSheet brings it): weight x the mean squared second difference of its
    slide angles over consecutive training frames and over neighbouring rings (frames held still count as zero)."""

    def __init__(self, weight: float) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        sheet = out.avatar.sheet
        t = sheet.slide * sheet.live[:, None]  # [F,rows+1]
        v = t.new_zeros(())
        if t.shape[0] > 2:
            v = v + ((t[2:] - 2 * t[1:-1] + t[:-2]) ** 2).mean()
        if t.shape[1] > 2:
            v = v + ((t[:, 2:] - 2 * t[:, 1:-1] + t[:, :-2]) ** 2).mean()
        return self.weight * v, {"sheet_slide": v.detach()}


class GarmentTracking(LossTerm):
    """The physics garment's tracking residual held near the simulated cloth (sheet=physics with residual: true
    brings it): stretch x the squared relative change of the cloth's edge lengths from the simulated frame's, smooth
    x the offsets' squared Laplacian over the mesh, temporal x their squared change to the next training frame."""

    def __init__(self, stretch: float, smooth: float, temporal: float) -> None:
        super().__init__()
        self.weights = {"stretch": float(stretch), "smooth": float(smooth), "temporal": float(temporal)}

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        terms = out.avatar.sheet.tracking_terms(out.posed["sheet_verts"], out.batch["frame_idx"])
        total = sum(self.weights[k] * v for k, v in terms.items())
        return total, {f"garment_{k}": v.detach() for k, v in terms.items()}


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """points [N,3] world, viewmat [4,4] world-to-camera (OpenCV), K [3,3] -> pixel coords [N,2], depth [N]."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]  # [N,3]
    z = cam[:, 2]
    uv = K.diagonal()[:2] * cam[:, :2] / z.clamp(min=1e-3)[:, None] + K[:2, 2]  # f * x / z + c
    return uv, z


def outside_distance(uv: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Pixel coords uv [N,2], a mask's distance field dist [H,W] (pixels) -> each point's distance to the mask [N]:
    the field sampled bilinearly inside the image, plus the distance to the image beyond it."""
    H, W = dist.shape
    lim = constant((W - 1.0, H - 1.0), uv)
    inside = torch.minimum(uv.clamp(min=0.0), lim)
    grid = (inside / lim * 2 - 1)[None, None]  # [1,1,N,2] in grid_sample's [-1,1] (align_corners=True)
    d_in = F.grid_sample(dist[None, None], grid, mode="bilinear", align_corners=True)[0, 0, 0]  # [N]
    return d_in + (uv - inside).norm(dim=-1)


def nearest_index(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Index into points [N,2] of the nearest point to each query [P,2] (no gradient). On the CPU a k-d tree
    (O((N + P) log N); the dense [P,N] distance matrix was most of the silhouette term's cost at 10k Gaussians),
    on a GPU the dense argmin."""
    if not host_path(queries):
        return torch.cdist(queries, points).argmin(1)
    _, idx = kd_tree(points.detach().double().numpy()).query(queries.detach().double().numpy(), k=1)
    return torch.from_numpy(idx).long()


class SilhouetteChamfer(LossTerm):
    """Long-range silhouette supervision: a 2D chamfer between projected Gaussian centres and the mask.

    Photometric and per-pixel mask losses reach a Gaussian only through pixels its footprint covers, so a
    Gaussian 30 cm from a flared hem gets no pull towards it. Two terms, in image heights squared:
    - outside: every projected centre outside the mask is pulled in along the mask's distance field
      (a visual-hull condition: every point of the subject projects inside every camera's silhouette);
    - coverage: mask pixels the prediction leaves uncovered (alpha < `covered_alpha`; at most `max_pixels`,
      sampled) pull their nearest projected centre.
    """

    def __init__(self, weight: float, outside_weight: float, coverage_weight: float, covered_alpha: float,
                 max_pixels: int, near: float) -> None:
        super().__init__()
        if weight < 0 or outside_weight < 0 or coverage_weight < 0:
            raise ValueError("silhouette: weights must be >= 0")
        self.weight, self.outside_weight, self.coverage_weight = float(weight), float(outside_weight), float(coverage_weight)
        self.covered_alpha, self.max_pixels, self.near = float(covered_alpha), int(max_pixels), float(near)

    def forward(self, out: TrainingRender) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Both terms of every sample's image, averaged over the batch, weighted."""
        B = out.rgb.shape[0]
        sil: dict[str, torch.Tensor] = {}
        for b in range(B):
            for k, v in self.image_terms(out.posed["means"][b], out.batch["viewmat"][b], out.batch["K"][b],
                                         out.batch["mask"][b], out.batch["mask_dist"][b], out.alpha[b]).items():
                sil[k] = sil[k] + v if k in sil else v
        if B > 1:
            sil = {k: v / B for k, v in sil.items()}
        return self.total(sil), {k: v.detach() for k, v in sil.items()}

    def image_terms(self, means: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, mask: torch.Tensor,
                    dist: torch.Tensor, alpha: torch.Tensor) -> dict[str, torch.Tensor]:
        """means [N,3] posed, viewmat [4,4], K [3,3], mask / alpha [H,W,1], dist [H,W] (`mask_distance(mask)`) ->
        {"sil_outside", "sil_coverage"}. Fixed shapes throughout (no read of the device): centres behind the camera
        and pixel slots beyond the uncovered ones carry weight 0."""
        H, W = mask.shape[:2]
        uv, z = project_points(means, viewmat, K)
        front = (z > self.near).to(uv.dtype)  # [N]
        d = outside_distance(uv, dist.to(uv))  # [N] pixels
        out = {"sil_outside": (((d / H) ** 2) * front).sum() / front.sum().clamp_min(1.0)}
        # Coverage: up to max_pixels uncovered mask pixels, drawn uniformly (random scores, the top ones), each pulls
        # its nearest projected centre in front of the camera.
        need = ((mask[..., 0] > 0.5) & (alpha[..., 0].detach() < self.covered_alpha)).flatten()  # [H*W]
        score = torch.where(need, torch.rand(need.shape, device=need.device), -1.0)
        top, idx = score.topk(min(self.max_pixels, need.numel()))
        pix = torch.stack([idx % W, torch.div(idx, W, rounding_mode="floor")], -1).to(uv.dtype)  # [P,2] (x,y)
        behind = (1e9 * (1 - front))[:, None]  # never the nearest while a centre in front exists
        nearest = nearest_index(pix, uv.detach() + behind)  # [P]
        weight = (top >= 0).to(uv.dtype) * front[nearest]
        err = (((uv[nearest] - pix) / H) ** 2).sum(-1)
        out["sil_coverage"] = (err * weight).sum() / weight.sum().clamp_min(1.0)
        return out

    def total(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.weight * (self.outside_weight * terms["sil_outside"] + self.coverage_weight * terms["sil_coverage"])
