"""Test scenes for the renderer tests: random Gaussians, one Gaussian, the benchmarks' human scene."""

from __future__ import annotations

import math

import numpy as np
import torch

from realityavatar.data.synthetic.cameras import look_at as _look_at
from tests.helpers import CONF as ROOT_CONF

F64 = torch.float64


CONF = ROOT_CONF / "render"


def look_at(campos, target, dtype=F64):
    """The scene generator's OpenCV world-to-camera matrix, here with world z up, as a tensor."""
    return torch.from_numpy(_look_at(np.asarray(campos, float), np.asarray(target, float), up=(0.0, 0.0, 1.0))).to(dtype)


def gradcheck_gaussians(n: int = 5, cameras: int | None = None):
    """Five float64 leaf tensors for the rasterizer's gradchecks: means, quats, scales, opacities, colours ([n,3], or
    [cameras,n,3] per camera)."""
    g = torch.Generator().manual_seed(1)
    means = (torch.randn(n, 3, generator=g, dtype=F64) * 0.25).requires_grad_()
    quats = torch.randn(n, 4, generator=g, dtype=F64).requires_grad_()
    scales = (torch.rand(n, 3, generator=g, dtype=F64) * 0.1 + 0.1).requires_grad_()
    op = (torch.rand(n, generator=g, dtype=F64) * 0.5 + 0.45).requires_grad_()
    shape = (n, 3) if cameras is None else (cameras, n, 3)
    return means, quats, scales, op, torch.rand(*shape, generator=g, dtype=F64).requires_grad_()


def random_scene(n, seed, cams=1, w=40, h=32, dtype=F64, opaque_frac=0.3):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.12 + 0.02
    op = torch.rand(n, generator=g, dtype=dtype)
    op[: int(n * opaque_frac)] = 1.0  # hits the alpha clamp at the centre and drives early termination
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    vms = torch.stack([look_at((3 * math.sin(a), -3 * math.cos(a), 0.3), (0, 0, 0)) for a in
                       torch.linspace(0, 1.5, cams).tolist()]).to(dtype)
    K = torch.tensor([[45.0, 0, w / 2 + 0.7], [0, 47.0, h / 2 - 0.4], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, op, colors, vms, K[None].repeat(cams, 1, 1), w, h


def single_gaussian(x, y, z=2.0, s=0.02, f=100.0, w=64, h=48):
    means = torch.tensor([[x, y, z]], dtype=F64)
    quats = torch.tensor([[0.3, -0.2, 0.5, 0.1]], dtype=F64)  # any rotation: the Gaussian is isotropic
    scales = torch.full((1, 3), s, dtype=F64)
    colors = torch.tensor([[0.2, 0.5, 0.9]], dtype=F64)
    vms = torch.eye(4, dtype=F64)[None]
    Ks = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=F64)[None]
    return means, quats, scales, torch.tensor([0.8], dtype=F64), colors, vms, Ks, w, h
