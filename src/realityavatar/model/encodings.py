"""Input encodings of 3D positions shared by the networks: NeRF frequency encoding, Instant-NGP hash grid."""

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


# Spatial-hash primes of Instant-NGP (Müller et al. 2022); the first is 1 so the x axis stays coherent.
_PRIMES = (1, 2654435761, 805459861)


class HashEncoding(nn.Module):
    """Multi-resolution hash encoding (Instant-NGP) in pure torch, all levels in one gather.

    Input u [N,3] in [0,1]^3 -> [N, num_levels * features_per_level]. Levels whose dense grid fits the table
    are indexed densely (no collisions); finer levels use the XOR spatial hash. Trilinear interpolation of
    the 8 voxel corners.
    """

    def __init__(
        self,
        num_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 16,
        base_resolution: int = 16,
        max_resolution: int = 1024,
        init_std: float = 1e-4,
    ) -> None:
        super().__init__()
        self.num_levels = num_levels
        self.features_per_level = features_per_level
        self.table_size = 2**log2_table_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(num_levels - 1, 1))
        res = [int(math.floor(base_resolution * growth**lvl)) for lvl in range(num_levels)]
        dense = [(r + 1) ** 3 <= self.table_size for r in res]
        sizes = [(r + 1) ** 3 if d else self.table_size for r, d in zip(res, dense)]
        offsets = [0]
        for s in sizes[:-1]:
            offsets.append(offsets[-1] + s)
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.long), persistent=False)  # [L]
        self.register_buffer("dense", torch.tensor(dense), persistent=False)  # [L]
        self.register_buffer("sizes", torch.tensor(sizes, dtype=torch.long), persistent=False)  # [L]
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.long), persistent=False)  # [L]
        self.register_buffer("primes", torch.tensor(_PRIMES, dtype=torch.long), persistent=False)
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_std, init_std))
        self.out_dim = num_levels * features_per_level

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """u [N,3] in [0,1]^3 (clamped) -> [N, L*F]. No gradient flows to u: the table is the learned part."""
        u = u.detach().clamp(0.0, 1.0)
        N = u.shape[0]
        pos = u[:, None, :] * self.resolution[None, :, None].to(u.dtype)  # [N,L,3]
        base = pos.floor().long().clamp(max=self.resolution[None, :, None])
        frac = pos - base  # [N,L,3]
        # Per-axis corner coordinates [N,L,2]; combining axes by broadcasting avoids [N,L,8,3] temporaries.
        cx, cy, cz = (torch.stack([base[..., a], base[..., a] + 1], -1) for a in range(3))
        r1 = (self.resolution + 1)[None, :, None]  # [1,L,1]
        dense_idx = cx[..., :, None, None] + r1[..., None, None] * (cy[..., None, :, None] + r1[..., None, None] * cz[..., None, None, :])
        hashed = (cx * self.primes[0])[..., :, None, None] ^ (cy * self.primes[1])[..., None, :, None] ^ (cz * self.primes[2])[..., None, None, :]
        hashed = hashed & (self.table_size - 1)
        idx = torch.where(self.dense[None, :, None, None, None], dense_idx, hashed).reshape(N, self.num_levels, 8)
        idx = idx + self.offsets[None, :, None]  # [N,L,8]
        wx, wy, wz = (torch.stack([1 - frac[..., a], frac[..., a]], -1) for a in range(3))
        w = (wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]).reshape(N, self.num_levels, 8)
        return _HashGather.apply(self.table, idx, w).reshape(N, -1)


class _HashGather(torch.autograd.Function):
    """out[n,l] = sum_c w[n,l,c] table[idx[n,l,c]]; backward by index_add_ (the generic embedding backward sorts)."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        N, L, C = idx.shape
        rows = table.index_select(0, idx.reshape(-1)).reshape(N, L, C, -1)  # [N,L,8,F]
        ctx.save_for_backward(idx, w)
        ctx.table_shape = table.shape
        return torch.einsum("nlc,nlcf->nlf", w, rows)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        idx, w = ctx.saved_tensors
        contrib = (w[..., None] * grad_out[:, :, None, :]).reshape(-1, ctx.table_shape[1])  # [N*L*8,F]
        grad_table = grad_out.new_zeros(ctx.table_shape).index_add_(0, idx.reshape(-1), contrib)
        return grad_table, None, None
