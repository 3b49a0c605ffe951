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
        feature_dim: int = 32,
        fmt_dim: int = 16,
        frame_latent_dim: int = 16,
        num_frames: int = 1,
        sh_degree: int = 3,
        hidden_dim: int = 64,
        use_fmt: bool = True,
    ) -> None:
        super().__init__()
        if num_frames < 1 and frame_latent_dim > 0:
            raise ValueError(f"color.num_frames: expected >= 1 training frames for Z_r, got {num_frames}")
        self.feature_dim = feature_dim
        self.fmt_dim = fmt_dim if use_fmt else 0
        self.sh_degree = sh_degree
        self.frame_latent_dim = frame_latent_dim
        self.num_frames = num_frames
        n_basis = (sh_degree + 1) ** 2 - 1
        # First layer split by input so the per-Gaussian feature term is computed once for the whole batch.
        self.in_feat = nn.Linear(feature_dim, hidden_dim)
        self.in_dir = nn.Linear(n_basis, hidden_dim, bias=False) if n_basis > 0 else None
        self.in_fmt = nn.Linear(fmt_dim, hidden_dim, bias=False) if use_fmt else None
        if frame_latent_dim > 0:
            self.frame_latents = nn.Embedding(num_frames, frame_latent_dim)
            nn.init.normal_(self.frame_latents.weight, std=0.01)
            self.in_latent = nn.Linear(frame_latent_dim, hidden_dim, bias=False)
        else:
            self.frame_latents = None
        self.out = nn.Linear(hidden_dim, 3)

    def latent(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """frame_idx [B] (long, -1 = not a training frame) -> Z_r [B,frame_latent_dim]."""
        table = self.frame_latents.weight  # [num_frames,D]
        z = table[frame_idx.clamp_min(0)]
        return torch.where((frame_idx < 0)[:, None], table.mean(0, keepdim=True).expand_as(z), z)

    def forward(
        self, features: torch.Tensor, view_dirs: torch.Tensor, f_mt: torch.Tensor | None, frame_idx: torch.Tensor
    ) -> torch.Tensor:
        """features [N,F], view_dirs [B,N,3] (canonical, any length), f_mt [B,N,Fm] | None, frame_idx [B] -> rgb [B,N,3]."""
        h = self.in_feat(features)[None]  # [1,N,H]
        if self.in_dir is not None:
            h = h + self.in_dir(sh_basis(self.sh_degree, view_dirs)[..., 1:])
        if self.in_fmt is not None:
            if f_mt is None:
                raise ValueError("color: use_fmt=True needs f_mt [B,N,Fm] from the deformer, got None")
            h = h + self.in_fmt(f_mt)
        if self.frame_latents is not None:
            h = h + self.in_latent(self.latent(frame_idx.long().to(features.device)))[:, None]
        return torch.sigmoid(self.out(torch.relu(h)))

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"color": list(self.parameters())}


class SHColor(nn.Module):
    """Plain 3DGS colour: features are SH coefficients [N,(deg+1)^2*3] (coefficient-major, RGB last), evaluated
    with the view direction, +0.5 and clamped at 0 like gsplat. Has no parameters; f_mt and frame_idx are unused."""

    def __init__(self, sh_degree: int = 3, feature_dim: int | None = None, num_frames: int | None = None) -> None:
        super().__init__()
        self.sh_degree = sh_degree
        self.num_coeffs = (sh_degree + 1) ** 2
        expected = 3 * self.num_coeffs
        if feature_dim is not None and feature_dim != expected:
            raise ValueError(f"color.feature_dim: SH degree {sh_degree} needs {expected} features, got {feature_dim}")
        self.feature_dim = expected

    def forward(
        self, features: torch.Tensor, view_dirs: torch.Tensor, f_mt: torch.Tensor | None, frame_idx: torch.Tensor
    ) -> torch.Tensor:
        """features [N,K*3], view_dirs [B,N,3] -> rgb [B,N,3]."""
        coeffs = self.sh_coefficients(features)  # [N,K,3]
        return torch.clamp_min(eval_sh(self.sh_degree, coeffs[None], view_dirs) + 0.5, 0.0)

    def sh_coefficients(self, features: torch.Tensor) -> torch.Tensor:
        """features [N,K*3] -> SH coefficients [N,K,3], the layout of 3DGS PLY files (colour = SH + 0.5)."""
        return features.reshape(features.shape[0], self.num_coeffs, 3)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {}
