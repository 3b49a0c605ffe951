"""Skinning fields over the 24 bones (an MLP, or a voxel grid diffused from the body), LBS of Gaussians, skinning loss."""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import kd_tree, matrix_to_quat, quat_multiply, sample_surface, unit
from realityavatar.kernels import polar_rotation
from realityavatar.model.encodings import FrequencyEncoding

NUM_BONES = 24


class AtDeformed:
    """Where a skinning field is read (`skinning.query`): at the deformed canonical position x_e = x_c + dx, as
    3DGS-Avatar (the default)."""

    def __call__(self, x_c: torch.Tensor, x_e: torch.Tensor) -> torch.Tensor:
        """x_c [N,3], x_e [B,N,3] -> the query points [B,N,3]."""
        return x_e


class AtCanonical:
    """At the undeformed canonical position x_c, so a garment point keeps the bones it was laid out on however far
    the decoder moves it (read at x_c + dx, a hem pushed 30 cm out takes the weights of whatever part lies there;
    docs/research/2026-11-26-spin-gap-oracles.md; `+experiment=spin_target`)."""

    def __call__(self, x_c: torch.Tensor, x_e: torch.Tensor) -> torch.Tensor:
        return x_c[None].expand(x_e.shape[0], -1, -1)


QueryPoint = AtDeformed | AtCanonical


class SkinningField(nn.Module):
    """MLP on a (canonical-space) position -> softmax weights over the 24 bones.

    Positions are mapped to [-1,1] with `center`/`half_extent` before a frequency encoding, so the field does
    not depend on the body's units as long as the box covers it.
    """

    def __init__(self, hidden_dim: int, num_layers: int, num_freqs: int, center: tuple[float, float, float],
                 half_extent: float, query: QueryPoint, num_bones: int = NUM_BONES) -> None:
        super().__init__()
        self.query = query
        self.encoding = FrequencyEncoding(num_freqs)
        # Persistent so a checkpoint carries the normalisation the weights were trained with.
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32))
        self.register_buffer("half_extent", torch.tensor(float(half_extent)))
        layers: list[nn.Module] = []
        d = self.encoding.out_dim
        for _ in range(num_layers):
            layers += [nn.Linear(d, hidden_dim), nn.ReLU(inplace=True)]
            d = hidden_dim
        layers.append(nn.Linear(d, num_bones))
        self.mlp = nn.Sequential(*layers)
        self.num_bones = num_bones

    @torch.no_grad()
    def fit_bounds(self, points: torch.Tensor, padding: float = 0.1) -> None:
        """Centre the input box on points [P,3] (e.g. the canonical Gaussians) with a relative padding."""
        lo, hi = points.min(0).values, points.max(0).values
        self.center.copy_((lo + hi) / 2)
        self.half_extent.fill_(float((hi - lo).max()) / 2 * (1 + padding))

    def init_from_body(self, vertices: torch.Tensor, faces: torch.Tensor, weights: torch.Tensor,
                       steps: int) -> dict | None:
        """Before step 0: fit the field to the body's skin weights for `steps` steps (`pretrain_skinning`); the
        record of the fit, or None when steps <= 0 (no pre-fit)."""
        if steps <= 0:
            return None
        return {"steps": int(steps), "loss": pretrain_skinning(self, vertices, faces, weights, steps=steps)}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"skinning": list(self.parameters())}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [...,3] -> weights [...,24] (rows sum to 1)."""
        u = (x - self.center) / self.half_extent
        return torch.softmax(self.mlp(self.encoding(u)), dim=-1)


class SkinningGrid(nn.Module):
    """Skinning weights on a voxel grid over canonical space, trilinearly interpolated (`skinning=grid`).

    Built from the body once per run (`init_from_body`, before step 0, instead of the MLP's pre-fit): every voxel
    takes the inverse-distance blend of the skin weights of its `k` nearest body-surface samples; away from the body
    the weights are blended with a smoothed copy (`smooth_iters` passes of a 3x3x3 box filter), fully so beyond
    `smooth_ramp` metres. So a point between the thighs, where a skirt hangs, gets a blend of both thighs instead
    of the side it happens to be closer to (Animatable Gaussians diffuses the weights into a volume for this reason),
    and a flared hem 40 cm from the body gets the hips' weights, not an MLP's extrapolation. The grid holds the
    weights themselves (trilinear blends of them stay convex; interpolated log weights smeared sharp joint borders);
    a lookup is one `grid_sample` (gradients reach the query positions, i.e. the decoder's offsets), instead of a
    4-layer MLP per Gaussian. `learnable: true` trains the weights with the `skinning` learning rate (clamped at 0
    and renormalised at lookup); by default they stay as built (no optimizer state, no skinning-loss gradient).
    """

    def __init__(self, voxel_size: float, padding: float, k: int, smooth_iters: int, smooth_ramp: float,
                 learnable: bool, max_voxels: int, query: QueryPoint, num_bones: int = NUM_BONES) -> None:
        super().__init__()
        check_grid_settings("skinning (grid)", voxel_size, padding, k, smooth_iters, smooth_ramp)
        self.query = query
        self.voxel_size, self.padding, self.k = float(voxel_size), float(padding), int(k)
        self.smooth_iters, self.smooth_ramp, self.max_voxels = int(smooth_iters), float(smooth_ramp), int(max_voxels)
        self.num_bones = num_bones
        # [1,24,D,H,W] weights (D along z, H along y, W along x: grid_sample's order); resized by init_from_body.
        self.grid = nn.Parameter(torch.full((1, num_bones, 2, 2, 2), 1.0 / num_bones), requires_grad=bool(learnable))
        self.register_buffer("lo", torch.full((3,), -1.0))
        self.register_buffer("hi", torch.full((3,), 1.0))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # A checkpoint's grid has the resolution its body gave it: take that shape before loading.
        key = prefix + "grid"
        if key in state_dict and state_dict[key].shape != self.grid.shape:
            self.grid.data = torch.empty_like(state_dict[key], device=self.grid.device, dtype=self.grid.dtype)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def init_from_body(self, vertices: torch.Tensor, faces: torch.Tensor, weights: torch.Tensor, steps: int = 0,
                       seed: int = 0) -> dict:
        """Fill the grid from the body's canonical surface: vertices [V,3], faces [F,3], weights [V,24]. Built, not
        fitted: `steps` (the MLP's pre-fit length) is not used, and the record says 0 steps."""
        grid, lo, hi, pts, w = diffuse_to_grid(vertices, faces, weights, self.voxel_size, self.padding, self.k,
                                               self.smooth_iters, self.smooth_ramp, self.max_voxels, seed, "skinning")
        grid = grid / grid.sum(1, keepdim=True).clamp_min(1e-8)
        # channels last (each voxel's 24 weights together): a lookup reads 8 runs of 24 floats, not 192 scattered
        # ones; grid_sample's values and gradients are the same (10.3 -> 8.4 ms at 10k Gaussians on a 2-core CPU)
        self.grid.data = grid.to(self.grid).contiguous(memory_format=torch.channels_last_3d)
        self.lo.copy_(lo.to(self.lo))
        self.hi.copy_(hi.to(self.hi))
        return {"steps": 0, "voxels": list(grid.shape[:1:-1]), "voxel_size": self.voxel_size,
                "surface_fit": float(((self(pts.to(self.lo)) - w.to(self.lo)) ** 2).sum(-1).mean())}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"skinning": list(self.parameters())}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [...,3] -> weights [...,24] (rows sum to 1); outside the grid the border voxels' weights."""
        w = sample_grid(self.grid, self.lo, self.hi, x)
        if self.grid.requires_grad:  # trained weights may leave the simplex
            w = w.clamp_min(0)
            w = w / w.sum(-1, keepdim=True).clamp_min(1e-8)
        return w


# The nearest-sample queries of the last few grids (see diffuse_to_grid): a run builds the skinning grid and the
# shading-normal grid from the same samples, and a float64 build or another grid's settings would otherwise evict it.
_KNN_CACHE: OrderedDict = OrderedDict()
_KNN_CACHE_SIZE = 4


def check_grid_settings(name: str, voxel_size: float, padding: float, k: int, smooth_iters: int,
                        smooth_ramp: float) -> None:
    """The settings of a body grid built by `diffuse_to_grid`; `name` is the config the error names."""
    if voxel_size <= 0 or padding < 0 or k < 1 or smooth_iters < 0 or smooth_ramp <= 0:
        raise ValueError(
            f"{name}: expected voxel_size > 0, padding >= 0, k >= 1, smooth_iters >= 0, smooth_ramp > 0; "
            f"got {voxel_size}, {padding}, {k}, {smooth_iters}, {smooth_ramp}")


@torch.no_grad()
def diffuse_to_grid(vertices: torch.Tensor, faces: torch.Tensor, values: torch.Tensor, voxel_size: float,
                    padding: float, k: int, smooth_iters: int, smooth_ramp: float, max_voxels: int, seed: int = 0,
                    name: str = "skinning"):
    """Per-vertex values [V,C] of a canonical body mesh diffused into a voxel grid over its box (+padding).

    Every voxel takes the inverse-distance blend of the values of its k nearest surface samples (200k, area
    weighted); from the surface out to `smooth_ramp` metres it is blended with a copy smoothed by `smooth_iters` passes
    of a 3x3x3 box filter, which it equals beyond. Returns grid [1,C,D,H,W] (D along z, H along y, W along x:
    grid_sample's order), lo [3], hi [3], and the surface samples with their values (points [n,3], values [n,C]).
    `name` is the config group named in the error when the grid would be too large.
    """
    import numpy as np

    lo = vertices.min(0).values - padding
    hi = vertices.max(0).values + padding
    size = ((hi - lo) / voxel_size).ceil().long() + 1  # voxels along x, y, z
    if int(size.prod()) > max_voxels:
        raise ValueError(
            f"{name}.voxel_size={voxel_size}: {size.tolist()} = {int(size.prod())} voxels over the body's box "
            f"(+{padding} m), more than {name}.max_voxels={max_voxels}; use a larger voxel_size")
    hi = lo + (size - 1).to(lo) * voxel_size
    gen = torch.Generator().manual_seed(seed)
    pts, w = sample_surface(vertices.detach().float().cpu(), faces.cpu(), values.detach().float().cpu(), 200_000, gen)
    nx, ny, nz = (int(v) for v in size)
    # Grids of the same samples, voxel centres and k (the skin weights and the shading normals) share the
    # nearest-sample query: the samples depend on the mesh and the seed only, not on the values.
    key = (hashlib.sha1(pts.numpy().tobytes()).hexdigest(), tuple(float(v) for v in lo), nx, ny, nz,
           float(voxel_size), k)
    hit = _KNN_CACHE.get(key)
    if hit is None:
        axes = [np.linspace(float(lo[i]), float(hi[i]), n) for i, n in enumerate((nx, ny, nz))]
        zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # [D,H,W] each
        centres = np.stack([xx, yy, zz], -1).reshape(-1, 3)
        # as many query threads as torch uses (1 in sweeps that share the CPU; all cores on a GPU machine)
        dist, idx = kd_tree(pts.numpy()).query(centres, k=k, workers=max(1, torch.get_num_threads()))
        hit = (dist.reshape(len(centres), -1), idx.reshape(len(centres), -1))
    _KNN_CACHE[key] = hit
    _KNN_CACHE.move_to_end(key)
    while len(_KNN_CACHE) > _KNN_CACHE_SIZE:
        _KNN_CACHE.popitem(last=False)
    dist, idx = hit
    inv = 1.0 / np.maximum(dist, 1e-4)
    near = (w.numpy()[idx] * (inv / inv.sum(1, keepdims=True))[..., None]).sum(1)  # [P,C]
    near = torch.from_numpy(near).float().T.reshape(1, w.shape[1], nz, ny, nx)
    smooth = near
    for _ in range(smooth_iters):
        smooth = F.avg_pool3d(F.pad(smooth, (1, 1, 1, 1, 1, 1), mode="replicate"), 3, stride=1)
    ramp = torch.from_numpy(np.clip(dist[:, 0] / smooth_ramp, 0.0, 1.0)).float().reshape(1, 1, nz, ny, nx)
    return (1 - ramp) * near + ramp * smooth, lo, hi, pts, w


def sample_grid(grid: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of grid [1,C,D,H,W] spanning the box lo..hi at x [...,3] -> [...,C]; outside the box the
    border voxels' values. Gradients reach x (and the grid when it is a trained parameter)."""
    u = (x - lo) / (hi - lo) * 2 - 1
    flat = u.reshape(1, -1, 1, 1, 3).to(grid.dtype)
    v = F.grid_sample(grid, flat, mode="bilinear", padding_mode="border", align_corners=True)
    return v.view(grid.shape[1], -1).transpose(0, 1).reshape(x.shape[:-1] + (grid.shape[1],))  # views: no copy


def skinning_loss(field: nn.Module, points: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Mean over points of ||field(x) - w||^2 (the paper's L_skin); points [P,3], weights [P,24]."""
    return ((field(points) - weights) ** 2).sum(-1).mean()


def pretrain_skinning(
    field: SkinningField,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    weights: torch.Tensor,
    steps: int = 300,
    batch: int = 4096,
    lr: float = 3e-3,
    seed: int = 0,
) -> float:
    """Fit the field to the body's barycentric skin weights on its canonical surface; returns the final loss."""
    gen = torch.Generator().manual_seed(seed)
    field.fit_bounds(vertices)
    pts, w = sample_surface(vertices, faces, weights, max(batch * 8, 32768), gen)
    opt = torch.optim.Adam(field.parameters(), lr=lr)
    loss = torch.tensor(float("nan"))
    for _ in range(steps):
        idx = torch.randint(0, pts.shape[0], (batch,), generator=gen).to(pts.device)
        loss = skinning_loss(field, pts[idx], w[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return float(loss.detach())


def lbs_gaussians(
    means: torch.Tensor, quats: torch.Tensor, weights: torch.Tensor, A: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linear blend skinning of Gaussians (paper eqs. for T, R_o, x_o).

    means [B,N,3] or [N,3], quats [B,N,4] or [N,4] (wxyz), weights [B,N,24] or [N,24], A [B,24,4,4]
    (canonical -> posed bone transforms) -> means_o [B,N,3], quats_o [B,N,4], rot [B,N,3,3] (R_T below; its
    transpose takes posed view directions back to canonical space for the colour model).
    Positions use the blended matrix T exactly (x_o = T x_e). The blended 3x3 block is generally not a
    rotation (it shrinks between bones that disagree); the Gaussian's rotation uses its polar rotation factor
    R_T, so R_o = R_T R_e and the Gaussian keeps its own scales (the renderer takes quaternion + scale, not a
    full covariance; the shrink/shear part of T is dropped for the covariance only).
    """
    if A.ndim != 4 or A.shape[-2:] != (4, 4):
        raise ValueError(f"lbs_gaussians: A must be [B,24,4,4], got {tuple(A.shape)}")
    B = A.shape[0]
    if means.ndim == 2:
        means = means.expand(B, -1, -1)
    if quats.ndim == 2:
        quats = quats.expand(B, -1, -1)
    if weights.ndim == 2:
        weights = weights.expand(B, -1, -1)
    R = A[:, :, :3, :3].reshape(B, A.shape[1], 9)  # [B,24,9]
    t = A[:, :, :3, 3]  # [B,24,3]
    RT = torch.bmm(weights, R).reshape(B, -1, 3, 3)  # [B,N,3,3]
    tT = torch.bmm(weights, t)  # [B,N,3]
    means_o = (RT @ means[..., None]).squeeze(-1) + tT
    rot = polar_rotation(RT)  # closed-form gradient (realityavatar.kernels), no graph through the iterations
    quats_o = quat_multiply(matrix_to_quat(rot), unit(quats))
    return means_o, quats_o, rot
