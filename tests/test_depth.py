"""Depth distortion (`depth=distortion`): blend weights along a ray kept to a thin depth interval."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.losses import DepthDistortion, NoDepthDistortion
from realityavatar.render import rasterize


def _two_on_the_axis(gap: float, opacity: float = 0.6):
    """Two isotropic Gaussians on the optical axis of a 33x33 camera, the second `gap` metres behind the first."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0 + gap]], dtype=torch.float64, requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.full((2, 3), 0.05, dtype=torch.float64)
    opac = torch.full((2,), opacity, dtype=torch.float64, requires_grad=True)
    K = torch.tensor([[[40.0, 0, 16.5], [0, 40.0, 16.5], [0, 0, 1]]], dtype=torch.float64)
    return means, quats, scales, opac, torch.eye(4, dtype=torch.float64)[None], K


def _render_moments(means, quats, scales, opac, vm, K):
    z = means[:, 2] - 2.0  # camera-space depth, shifted as the module does
    cols = torch.stack([z, z.square()], dim=-1)
    img, alpha, _ = rasterize(means, quats, scales, opac, cols, vm, K, 33, 33, backend="torch")
    return img, alpha


def test_depth_distortion_is_the_weighted_squared_gap_and_pulls_the_layers_together():
    loss = DepthDistortion(weight=1.0)
    for gap in (0.0, 0.05, 0.2):
        means, quats, scales, opac, vm, K = _two_on_the_axis(gap)
        img, alpha = _render_moments(means, quats, scales, opac, vm, K)
        per_pixel = alpha * img[..., 1:2] - img[..., 0:1].square()
        # centre pixel: weights w1 = a, w2 = (1 - a) a; sum_ij w_i w_j (z_i - z_j)^2 / 2 = w1 w2 gap^2
        a = 0.6
        assert float(per_pixel[0, 16, 16, 0]) == pytest.approx(a * (1 - a) * a * gap**2, rel=1e-6, abs=1e-12)
        assert float(per_pixel.min()) >= -1e-12
        if gap == 0.0:
            assert float(loss(img, alpha)) == pytest.approx(0.0, abs=1e-12)
    # the gradient moves the back Gaussian towards the front one and the front one back, and fades the back one
    means, quats, scales, opac, vm, K = _two_on_the_axis(0.2)
    img, alpha = _render_moments(means, quats, scales, opac, vm, K)
    loss(img, alpha).backward()
    assert float(means.grad[1, 2]) > 0 > float(means.grad[0, 2])  # descent: back one forward, front one back
    assert float(opac.grad[1]) > 0


def test_depth_group_composes_and_switches_off():
    assert isinstance(instantiate(compose([]).depth), NoDepthDistortion)  # the default
    on = instantiate(compose(["depth=distortion", "depth.weight=10"]).depth)
    assert isinstance(on, DepthDistortion) and on.weight == 10.0
    with pytest.raises(ValueError, match="depth.weight"):
        DepthDistortion(weight=-1.0)


def _ci_module(extra: list[str]):
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=600", *extra])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    return dm, build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)


def test_module_renders_depth_moments_beside_the_same_colour(scenes_root):
    dm, module = _ci_module(["depth=distortion"])
    assert module.depth is not None and _ci_module([])[1].depth is None
    batch = module.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
    with torch.no_grad():
        rgb0, alpha0, _, _ = module.render_batch(batch)
        rgb1, alpha1, _, posed = module.render_batch(batch, depth_moments=True)
    assert torch.allclose(rgb0, rgb1, atol=1e-6) and torch.equal(alpha0, alpha1)
    m = posed["depth_moments"][0]  # [H,W,2]
    E = batch["viewmat"][0]
    z = posed["means"][0] @ E[2, :3] + E[2, 3]
    z = z - z.mean()
    solid = alpha1[0, ..., 0] > 0.05
    mean_depth = m[..., 0][solid] / alpha1[0, ..., 0][solid]  # a convex combination of the Gaussians' depths
    assert float(mean_depth.min()) >= float(z.min()) - 1e-5 and float(mean_depth.max()) <= float(z.max()) + 1e-5
    var = alpha1[0, ..., 0] * m[..., 1] - m[..., 0].square()
    assert float(var.min()) > -1e-5 and float(var.max()) > 0


def test_depth_term_trains_and_is_logged(scenes_root, tmp_path):
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=6", "depth=distortion",
                                        "gaussians.num_points=400", "test_after_fit=false"]), tmp_path / "run")
    run(cfg, choices)
    import csv

    with open(next((tmp_path / "run").rglob("metrics.csv"))) as f:
        rows = list(csv.DictReader(f))
    vals = [float(r["train/depth"]) for r in rows if r.get("train/depth")]
    assert vals and all(np.isfinite(vals)) and max(vals) > 0, rows[:2]
