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
        # The bands are weighted by band_weights once the window has been narrower than every band, and stay so when
        # it opens fully (the weights reach exactly 1): a compiled graph is not traced again when the window opens.
        self.windowed = False
        # The window's weight per band and axis, made by set_window on the module's device: under torch.compile the
        # graph reads a tensor, not alpha (a float that changes every step would be a host scalar input of the graph,
        # which CUDA graphs skip).
        self.register_buffer("band_weights", torch.ones(num_freqs * in_dim), persistent=False)

    def set_window(self, alpha: float) -> None:
        """Nerfies' coarse-to-fine window: band k is weighted (1 - cos(pi clamp(alpha - k, 0, 1))) / 2, so with alpha
        = 0 only the input itself passes and each band fades in as alpha passes it."""
        alpha = float(min(max(alpha, 0.0), self.num_freqs))
        if alpha == self.alpha:
            return
        self.alpha, self.windowed = alpha, self.windowed or alpha < self.num_freqs
        with torch.no_grad():
            k = torch.arange(self.num_freqs, device=self.freqs.device, dtype=self.freqs.dtype)
            w = (1 - torch.cos(math.pi * (alpha - k).clamp(0, 1))) / 2
            self.band_weights.copy_(w.repeat_interleave(self.in_dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xf = (x[..., None, :] * self.freqs[:, None]).flatten(-2)  # [...,F*3]
        parts = [x] if self.include_input else []
        sin, cos = xf.sin(), xf.cos()
        if self.windowed:
            w = self.band_weights.to(x.dtype)
            sin, cos = sin * w, cos * w
        return torch.cat(parts + [sin, cos], -1)
