"""Input encoding of 3D positions shared by the networks: NeRF frequency encoding."""

from __future__ import annotations

import math

import torch
from torch import nn


class FrequencyEncoding(nn.Module):
    """NeRF positional encoding: x ⊕ sin(2^k π x) ⊕ cos(2^k π x), k < num_freqs."""

    def __init__(self, num_freqs: int = 6, include_input: bool = True, in_dim: int = 3) -> None:
        super().__init__()
        self.num_freqs = num_freqs
        self.include_input = include_input
        self.register_buffer("freqs", (2.0 ** torch.arange(num_freqs)) * math.pi, persistent=False)
        self.out_dim = in_dim * (2 * num_freqs + int(include_input))
        self.in_dim = in_dim
        self.alpha = float(num_freqs)  # coarse-to-fine window (set_window); num_freqs: every band at full weight

    def set_window(self, alpha: float) -> None:
        """Nerfies' coarse-to-fine window: band k is weighted (1 - cos(pi clamp(alpha - k, 0, 1))) / 2, so with alpha
        = 0 only the input itself passes and each band fades in as alpha passes it."""
        self.alpha = float(min(max(alpha, 0.0), self.num_freqs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xf = (x[..., None, :] * self.freqs[:, None]).flatten(-2)  # [...,F*3]
        parts = [x] if self.include_input else []
        sin, cos = xf.sin(), xf.cos()
        if self.alpha < self.num_freqs:
            k = torch.arange(self.num_freqs, device=x.device, dtype=x.dtype)
            w = (1 - torch.cos(math.pi * (self.alpha - k).clamp(0, 1))) / 2
            w = w.repeat_interleave(self.in_dim)
            sin, cos = sin * w, cos * w
        return torch.cat(parts + [sin, cos], -1)
