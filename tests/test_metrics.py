"""Metrics: PSNR, SSIM against a loop reference, masked variants, flicker, LPIPS loading, float64 accumulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from realityavatar.metrics import (
    LPIPS,
    alexnet_features,
    build_lpips,
    lpips_status,
    mask_bbox,
    masked_bbox,
    psnr,
    psnr_masked,
    ssim,
    ssim_masked,
    temporal_flicker,
    vgg_features,
)


def _img(h=24, w=20, seed=0):
    return torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed))


def test_psnr_known_values():
    gt = torch.zeros(8, 8, 3)
    assert math.isinf(float(psnr(gt, gt)))
    assert float(psnr(gt + 0.1, gt)) == pytest.approx(20.0, abs=1e-4)
    batch = psnr(torch.stack([gt + 0.1, gt + 0.01]), torch.stack([gt, gt]))
    assert batch.shape == (2,) and float(batch[1]) == pytest.approx(40.0, abs=1e-3)


def _ssim_reference(x: np.ndarray, y: np.ndarray, win: int = 11, sigma: float = 1.5) -> float:
    """Loop over every valid window position and channel (skimage gaussian_weights convention)."""
    r = np.arange(win) - (win - 1) / 2
    g = np.exp(-(r**2) / (2 * sigma**2))
    w = np.outer(g, g)
    w /= w.sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    H, W, C = x.shape
    for c in range(C):
        for i in range(H - win + 1):
            for j in range(W - win + 1):
                a, b = x[i : i + win, j : j + win, c], y[i : i + win, j : j + win, c]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
                cov = (w * (a - ma) * (b - mb)).sum()
                vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_identity_and_loop_reference():
    x = _img(16, 19, 0)
    y = (x + 0.15 * torch.randn(16, 19, 3, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    ref = _ssim_reference(x.double().numpy(), y.double().numpy())
    assert float(ssim(x, y)) == pytest.approx(ref, abs=1e-5)
    assert float(ssim(x, y)) < 0.95
    # batched = per image
    both = ssim(torch.stack([x, x]), torch.stack([y, x]))
    assert both.shape == (2,) and float(both[1]) == pytest.approx(1.0, abs=1e-6)
    # smaller than the window: padded, still 1 for identical images
    assert float(ssim(x[:5, :7], x[:5, :7])) == pytest.approx(1.0, abs=1e-6)
    # the separable torch convolutions (GPU tensors, or inputs that need a gradient) equal scipy's CPU path
    assert float(ssim(x.clone().requires_grad_(), y)) == pytest.approx(ref, abs=1e-5)
    assert float(ssim(x.clone().requires_grad_(), y)) == pytest.approx(float(ssim(x, y)), abs=1e-12)


def test_masked_bbox_variants():
    pred, gt = _img(30, 40, 0), _img(30, 40, 1)
    mask = torch.zeros(30, 40, 1)
    mask[5:17, 10:33] = 1
    assert mask_bbox(mask) == (5, 17, 10, 33)
    pb, gb = masked_bbox(pred, gt, mask)
    assert pb.shape == (12, 23, 3) and torch.equal(gb, gt[5:17, 10:33])
    assert float(psnr_masked(pred, gt, mask)) == pytest.approx(float(psnr(pred[5:17, 10:33], gt[5:17, 10:33])))
    assert float(ssim_masked(pred, gt, mask)) == pytest.approx(float(ssim(pred[5:17, 10:33], gt[5:17, 10:33])))
    assert mask_bbox(torch.zeros(30, 40, 1)) == (0, 30, 0, 40)  # empty mask -> whole image
    batched = psnr_masked(torch.stack([pred, pred]), torch.stack([gt, pred]), torch.stack([mask, mask]))
    assert batched.shape == (2,) and math.isinf(float(batched[1]))


def test_temporal_flicker():
    gt = torch.stack([torch.full((4, 4, 3), 0.1 * t) for t in range(5)])
    assert temporal_flicker(gt, gt) == 0.0
    frozen = torch.zeros_like(gt)
    assert temporal_flicker(frozen, gt) == pytest.approx(0.1, abs=1e-6)
    with pytest.raises(ValueError):
        temporal_flicker(gt[:1], gt[:1])


def _save_fake_lpips(tmp_path, net: str):
    torch.manual_seed(0)
    feats = vgg_features("vgg16") if net == "vgg" else alexnet_features()
    backbone = {f"features.{k}": v for k, v in feats.state_dict().items()}
    backbone["classifier.0.weight"] = torch.zeros(2, 2)  # extra torchvision keys are ignored
    chans = (64, 128, 256, 512, 512) if net == "vgg" else (64, 192, 384, 256, 256)
    lin = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(chans)}
    names = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}
    torch.save(backbone, tmp_path / names[net])
    torch.save(lin, tmp_path / f"{net}.pth")
    return tmp_path / names[net], tmp_path / f"{net}.pth"


@pytest.mark.parametrize("net,size", [("vgg", 32), ("alex", 64)])
def test_lpips_loads_weights_and_behaves(tmp_path, net, size):
    bb, lin = _save_fake_lpips(tmp_path, net)
    assert lpips_status(str(bb), str(lin)) == "computed"
    m, status = build_lpips(net, str(bb), str(lin))
    assert isinstance(m, LPIPS) and status == "computed"
    m_dir = LPIPS.from_paths(str(tmp_path), net=net)  # a directory with both files
    assert torch.equal(m_dir.lins[0].weight, m.lins[0].weight)
    assert torch.equal(m.lins[2].weight, torch.load(lin)["lin2.model.1.weight"])
    x, y = _img(size, size, 0), _img(size, size, 1)
    assert float(m(x, x)) == pytest.approx(0.0, abs=1e-7)
    d = float(m(x, y))
    assert d > 0
    assert float(m(torch.stack([x, x]), torch.stack([y, x]))[0]) == pytest.approx(d, rel=1e-5)
    # closer image -> smaller distance
    assert float(m(x, (0.9 * x + 0.1 * y))) < d


def test_lpips_not_computed_without_weights(tmp_path):
    status = lpips_status()
    assert status.startswith("not computed: no LPIPS weights")
    assert "metrics.lpips_weights" in status
    assert lpips_status(str(tmp_path / "nope.pth"), str(tmp_path / "nope2.pth")).startswith("not computed:")
    assert build_lpips("vgg", None, None) == (None, status)
    m, why = build_lpips("vgg", None, str(tmp_path))  # empty directory: the missing file is named
    assert m is None and why.startswith("not computed: LPIPS weight file") and "vgg" in why
    with pytest.raises(FileNotFoundError, match="not computed"):
        LPIPS("vgg", "", "")
    bb, _ = _save_fake_lpips(tmp_path, "alex")
    wrong = tmp_path / "vgg_lin.pth"
    torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate((64, 128, 256, 512, 512))}, wrong)
    with pytest.raises(ValueError, match="lin"):
        LPIPS("alex", str(bb), str(wrong))  # vgg lin weights for an alex net


def test_metrics_do_not_depend_on_float32_accumulation():
    """PSNR/SSIM accumulate in float64 (no TF32 convolutions on CUDA; CPU and GPU give the same numbers)."""
    from realityavatar.metrics import psnr, ssim

    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(48, 40, 3, generator=g), torch.rand(48, 40, 3, generator=g)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(x.double(), y.double())), abs=1e-12)
    assert float(psnr(x, y)) == pytest.approx(float(psnr(x.double(), y.double())), abs=1e-12)
    assert ssim(x, y).dtype == torch.float64
