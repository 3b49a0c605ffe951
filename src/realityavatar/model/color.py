"""Per-Gaussian colour: the paper's MLP (SH basis of canonical view dir ⊕ feature ⊕ f_mt ⊕ Z_r) or plain SH."""

from __future__ import annotations

import torch
from torch import nn

from realityavatar.render import eval_sh, sh_basis


class MLPColor(nn.Module):
    """One hidden layer of hidden_dim on [SH basis(d̂) (constant term dropped), feature, f_mt, Z_r] -> sigmoid RGB.

    Z_r is a per-training-frame latent (nn.Embedding, num_frames rows). frame_idx == -1 marks a frame not seen in
    training (novel pose): it uses the mean of the trained latents, the latent closest on average to all
    training frames' lighting, rather than an arbitrary training frame's.
    """

    def __init__(
        self,
        feature_dim: int,
        fmt_dim: int,
        frame_latent_dim: int,
        num_frames: int,
        sh_degree: int,
        hidden_dim: int,
    ) -> None:
        super().__init__()
        if num_frames < 1:
            raise ValueError(f"color.num_frames: expected >= 1 training frames for Z_r, got {num_frames}")
        if not 1 <= int(sh_degree) <= 3:
            raise ValueError(f"color.sh_degree: expected 1, 2 or 3 (the view direction's SH basis), got {sh_degree}")
        if frame_latent_dim < 1:
            raise ValueError(f"color.frame_latent_dim: expected >= 1 (the per-frame latent Z_r), got {frame_latent_dim}")
        self.feature_dim = feature_dim
        self.fmt_dim = fmt_dim
        self.sh_degree = int(sh_degree)
        self.frame_latent_dim = frame_latent_dim
        self.num_frames = num_frames
        # First layer split by input so the per-Gaussian feature term is computed once for the whole batch.
        self.in_feat = nn.Linear(feature_dim, hidden_dim)
        self.in_dir = nn.Linear((self.sh_degree + 1) ** 2 - 1, hidden_dim, bias=False)
        self.in_fmt = nn.Linear(fmt_dim, hidden_dim, bias=False)
        self.frame_latents = nn.Embedding(num_frames, frame_latent_dim)
        nn.init.normal_(self.frame_latents.weight, std=0.01)
        self.in_latent = nn.Linear(frame_latent_dim, hidden_dim, bias=False)
        self.out = nn.Linear(hidden_dim, 3)

    def latent(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """frame_idx [B] (long, -1 = not a training frame) -> Z_r [B,frame_latent_dim]."""
        table = self.frame_latents.weight  # [num_frames,D]
        z = table[frame_idx.clamp_min(0)]
        return torch.where((frame_idx < 0)[:, None], table.mean(0, keepdim=True).expand_as(z), z)

    def forward(
        self, features: torch.Tensor, view_dirs: torch.Tensor, f_mt: torch.Tensor, frame_idx: torch.Tensor
    ) -> torch.Tensor:
        """features [N,F] (or per sample [B,N,F]), view_dirs [B,N,3] (canonical, any length), f_mt [B,N,Fm],
        frame_idx [B] -> rgb [B,N,3]."""
        h = self.in_feat(features)
        h = h[None] if h.ndim == 2 else h  # [1,N,H] or [B,N,H]
        h = h + self.in_dir(sh_basis(self.sh_degree, view_dirs)[..., 1:])
        h = h + self.in_fmt(f_mt)
        h = h + self.in_latent(self.latent(frame_idx.long().to(features.device)))[:, None]
        return torch.sigmoid(self.out(torch.relu(h)))

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"color": list(self.parameters())}


class SHColor(nn.Module):
    """Plain 3DGS colour: features are SH coefficients [N,(deg+1)^2*3] (coefficient-major, RGB last), evaluated
    with the view direction, +0.5 and clamped at 0 like gsplat. Has no parameters; f_mt and frame_idx are unused."""

    def __init__(self, sh_degree: int, feature_dim: int, num_frames: int | None = None) -> None:
        super().__init__()
        self.sh_degree = sh_degree
        self.num_coeffs = (sh_degree + 1) ** 2
        expected = 3 * self.num_coeffs
        if feature_dim != expected:
            raise ValueError(f"color.feature_dim: SH degree {sh_degree} needs {expected} features, got {feature_dim}")
        self.feature_dim = expected

    def forward(
        self, features: torch.Tensor, view_dirs: torch.Tensor, f_mt: torch.Tensor, frame_idx: torch.Tensor
    ) -> torch.Tensor:
        """features [N,K*3] (or per sample [B,N,K*3]), view_dirs [B,N,3] -> rgb [B,N,3] (f_mt and frame_idx unused)."""
        coeffs = self.sh_coefficients(features)  # [(B,)N,K,3]
        coeffs = coeffs[None] if coeffs.ndim == 3 else coeffs
        return torch.clamp_min(eval_sh(self.sh_degree, coeffs, view_dirs) + 0.5, 0.0)

    def sh_coefficients(self, features: torch.Tensor) -> torch.Tensor:
        """features [...,N,K*3] -> SH coefficients [...,N,K,3], the layout of 3DGS PLY files (colour = SH + 0.5)."""
        return features.reshape(*features.shape[:-1], self.num_coeffs, 3)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {}
