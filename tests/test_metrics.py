"""Metrics: PSNR, SSIM against a loop reference, mask-box scores, flicker, LPIPS loading, float64 accumulation."""

from __future__ import annotations

import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from realityavatar.metrics import (
    LPIPS,
    PackageLPIPS,
    build_lpips,
    image_metrics,
    lpips_status,
    mask_bbox,
    psnr,
    ssim,
    temporal_flicker,
    vgg_features,
)
from tests.helpers import plant_found_weights


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


def test_box_scores_read_the_mask_box_only():
    """image_metrics's *_masked scores are the whole-image scores of the mask's bounding box: pixels outside it do not
    count (the box of an empty mask is the whole image)."""
    pred, gt = _img(30, 40, 0), _img(30, 40, 1)
    mask = torch.zeros(30, 40, 1)
    mask[5:17, 10:33] = 1
    assert mask_bbox(mask) == (5, 17, 10, 33) and mask_bbox(mask, pad=6) == (0, 23, 4, 39)
    assert mask_bbox(torch.zeros(30, 40, 1)) == (0, 30, 0, 40)  # empty mask -> whole image
    rec = image_metrics(pred, gt, mask, mask)
    box = pred[5:17, 10:33], gt[5:17, 10:33]
    assert rec["psnr_masked"] == pytest.approx(float(psnr(*box))) and rec["ssim_masked"] == pytest.approx(float(ssim(*box)))
    outside = pred.clone()
    outside[20:] = gt[20:]  # perfect outside the box: the whole image improves, the box does not move
    moved = image_metrics(outside, gt, mask, mask)
    assert moved["psnr"] > rec["psnr"] and moved["psnr_masked"] == rec["psnr_masked"]
    assert moved["ssim_masked"] == rec["ssim_masked"]


def test_temporal_flicker():
    gt = torch.stack([torch.full((4, 4, 3), 0.1 * t) for t in range(5)])
    assert temporal_flicker(gt, gt) == 0.0
    frozen = torch.zeros_like(gt)
    assert temporal_flicker(frozen, gt) == pytest.approx(0.1, abs=1e-6)
    with pytest.raises(ValueError):
        temporal_flicker(gt[:1], gt[:1])


def _save_fake_lpips(tmp_path, chans=(64, 128, 256, 512, 512), name="vgg.pth"):
    """A torchvision-layout vgg16 file and an lpips lin file (random weights) in tmp_path."""
    torch.manual_seed(0)
    backbone = {f"features.{k}": v for k, v in vgg_features("vgg16").state_dict().items()}
    backbone["classifier.0.weight"] = torch.zeros(2, 2)  # extra torchvision keys are ignored
    lin = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(chans)}
    torch.save(backbone, tmp_path / "vgg16-397923af.pth")
    torch.save(lin, tmp_path / name)
    return tmp_path / "vgg16-397923af.pth", tmp_path / name


def test_lpips_loads_weights_and_behaves(tmp_path):
    bb, lin = _save_fake_lpips(tmp_path)
    size = 32
    assert lpips_status(str(bb), str(lin)) == "computed"
    m, status = build_lpips("vgg", str(bb), str(lin))
    assert isinstance(m, LPIPS) and status == f"computed (weights: metrics.lpips_weights {lin} + metrics.lpips_backbone_weights {bb})"
    m_dir, status = build_lpips("vgg", None, str(tmp_path))  # metrics.lpips_weights=<a directory with both files>
    assert status == f"computed (weights: metrics.lpips_weights {lin} + metrics.lpips_weights {bb})"
    assert torch.equal(m_dir.lins[0].weight, m.lins[0].weight)
    assert torch.equal(m.lins[2].weight, torch.load(lin)["lin2.model.1.weight"])
    x, y = _img(size, size, 0), _img(size, size, 1)
    assert float(m(x, x)) == pytest.approx(0.0, abs=1e-7)
    d = float(m(x, y))
    assert d > 0
    assert float(m(torch.stack([x, x]), torch.stack([y, x]))[0]) == pytest.approx(d, rel=1e-5)
    # closer image -> smaller distance
    assert float(m(x, (0.9 * x + 0.1 * y))) < d
    # a thin mask box is edge-padded up to the network's smallest input (16 px)
    thin_x, thin_y, low = x[:5, :9], y[:5, :9], 16
    pad = (low - 9) // 2, low - 9 - (low - 9) // 2, (low - 5) // 2, low - 5 - (low - 5) // 2
    padded = [torch.nn.functional.pad(t.permute(2, 0, 1)[None], pad, mode="replicate")[0].permute(1, 2, 0)
              for t in (thin_x, thin_y)]
    assert float(m(thin_x, thin_y)) == pytest.approx(float(m(*padded)), rel=1e-6) and float(m(thin_x, thin_y)) > 0


def test_lpips_not_computed_without_weights(tmp_path):
    status = lpips_status()
    assert status.startswith("not computed: no LPIPS weights")
    assert "metrics.lpips_weights" in status
    assert lpips_status(str(tmp_path / "nope.pth"), str(tmp_path / "nope2.pth")).startswith("not computed:")
    m, why = build_lpips("vgg", None, None)  # nothing configured, nothing found (tests/conftest.py)
    assert m is None and why.startswith("not computed: no LPIPS weights") and "metrics.lpips_weights" in why
    assert "lpips package weights/v0.1/vgg.pth" in why and "hub/checkpoints/vgg16-397923af.pth" in why
    with pytest.MonkeyPatch.context() as mp:  # torch's default cache under the home folder: named from `~`
        mp.setenv("HOME", str(tmp_path))
        mp.setenv("TORCH_HOME", str(tmp_path / ".cache" / "torch"))
        _, why = build_lpips("vgg", None, None)
    assert "not found: lpips package weights/v0.1/vgg.pth, ~/.cache/torch/hub/checkpoints/vgg16-397923af.pth;" in why
    assert str(tmp_path) not in why
    m, why = build_lpips("vgg", None, str(tmp_path))  # empty directory: the missing file is named
    assert m is None and why.startswith("not computed: LPIPS weight file") and "vgg" in why
    with pytest.raises(FileNotFoundError, match="not computed"):
        LPIPS("vgg", "", "")
    bb, wrong = _save_fake_lpips(tmp_path, chans=(64, 192, 384, 256, 256), name="alex.pth")
    with pytest.raises(ValueError, match=r"expected lin1.model.1.weight of shape \(1, 128, 1, 1\)"):
        LPIPS("vgg", str(bb), str(wrong))  # the lpips package's alexnet lin file for the vgg net
    with pytest.raises(ValueError, match="net expected 'vgg'"):
        LPIPS("alex", str(bb), str(wrong))


def test_lpips_found_in_lpips_package_and_torch_hub(tmp_path, monkeypatch):
    """metrics.lpips_weights unset: the installed lpips package's lin file and torchvision's vgg16 in torch's hub
    cache give the pure-torch LPIPS (lpips itself does not import here), and the status says where they came from."""
    found = plant_found_weights(tmp_path, monkeypatch)
    m, status = build_lpips("vgg")
    assert isinstance(m, LPIPS)
    assert status == f"computed (weights: lpips package {found['lin']} + torch hub {found['vgg16']})"
    ref = LPIPS("vgg", found["vgg16"], found["lin"])
    x, y = _img(32, 32, 0), _img(32, 32, 1)
    assert float(m(x, y)) == float(ref(x, y)) > 0
    other = tmp_path / "other_vgg16.pth"  # a configured backbone with the package's lin file
    torch.save({f"features.{k}": v for k, v in vgg_features("vgg16").state_dict().items()}, other)
    assert build_lpips("vgg", str(other))[1] == (f"computed (weights: lpips package {found['lin']} + "
                                                  f"metrics.lpips_backbone_weights {other})")


@pytest.mark.parametrize("lin,vgg16", [(True, False), (False, True)])
def test_lpips_half_found_is_not_computed_and_says_what_is_missing(tmp_path, monkeypatch, lin, vgg16):
    plant_found_weights(tmp_path, monkeypatch, lin=lin, vgg16=vgg16)
    m, why = build_lpips("vgg")
    missing = "lpips package weights/v0.1/vgg.pth" if vgg16 else f"{tmp_path}/torch_home/hub/checkpoints/vgg16-397923af.pth"
    assert m is None and why.startswith("not computed: no LPIPS weights") and f"not found: {missing};" in why
    assert "lpips package not used: ImportError: planted lpips" in why  # why the package itself was not used


def test_found_weight_file_that_is_not_a_state_dict_is_named(tmp_path, monkeypatch):
    found = plant_found_weights(tmp_path, monkeypatch)
    good = Path(found["vgg16"]).read_bytes()
    Path(found["vgg16"]).write_bytes(b"<html>captive portal</html>")
    with pytest.raises(ValueError, match=f"backbone weights '{found['vgg16']}': not a torch state dict file"):
        build_lpips("vgg")
    Path(found["vgg16"]).write_bytes(good)
    torch.save(torch.zeros(3), found["lin"])  # a tensor, not a state dict
    with pytest.raises(ValueError, match=f"LPIPS lin weights '{found['lin']}': expected a state dict"):
        build_lpips("vgg")


def _fake_lpips_package(monkeypatch, fail: Exception | None = None, location: str | None = None) -> list:
    """A stand-in for the lpips package (it cannot be installed here): its LPIPS is the mean squared difference of
    its [-1,1] inputs, [B,1,1,1] like the package's; it records what it was given. `location`: its directory."""
    import importlib.machinery

    calls = []

    class FakeLPIPS(torch.nn.Module):
        def __init__(self, net="alex", verbose=True):
            super().__init__()
            if fail is not None:
                raise fail
            self.w = torch.nn.Parameter(torch.ones(()))
            self.drop = torch.nn.Dropout()
            calls.append({"net": net})

        def forward(self, in0, in1):
            calls.append({"shape": tuple(in0.shape), "range": (float(in0.min()), float(in0.max())),
                          "training": self.training, "grad": self.w.requires_grad})
            return (self.w * (in0 - in1) ** 2).mean((1, 2, 3), keepdim=True)

    fake = types.ModuleType("lpips")
    fake.LPIPS, fake.__version__ = FakeLPIPS, "0.1.4"
    if location:
        fake.__spec__ = importlib.machinery.ModuleSpec("lpips", None, is_package=True)
        fake.__spec__.submodule_search_locations = [location]
    monkeypatch.setitem(sys.modules, "lpips", fake)
    return calls


def test_lpips_package_is_used_directly_when_it_imports(monkeypatch):
    calls = _fake_lpips_package(monkeypatch)
    m, status = build_lpips("vgg")
    assert isinstance(m, PackageLPIPS) and status == "computed (lpips package 0.1.4 vgg)"
    assert calls == [{"net": "vgg"}]
    m.train()  # as inside a LightningModule's fit: the package's dropout stays off
    black, white = torch.zeros(8, 6, 3), torch.ones(8, 6, 3)
    assert float(m(black, white)) == pytest.approx(4.0)  # [0,1] -> [-1,1]: (-1 - 1)^2
    # an 8x6 mask box is edge-padded to vgg's smallest input, 16x16 (the package fails on it)
    assert calls[-1] == {"shape": (1, 3, 16, 16), "range": (-1.0, -1.0), "training": False, "grad": False}
    assert m(torch.stack([black, white]), torch.stack([white, white])).tolist() == pytest.approx([4.0, 0.0])


def test_lpips_package_that_fails_falls_back_to_found_files(tmp_path, monkeypatch):
    """Offline, lpips.LPIPS cannot download torchvision's vgg16: the files found are used, else the reason is kept."""
    offline = OSError("download of vgg16-397923af.pth failed: offline")
    _fake_lpips_package(monkeypatch, fail=offline)
    m, why = build_lpips("vgg")
    assert m is None and "lpips package not used: OSError: download of vgg16-397923af.pth failed: offline" in why
    found = plant_found_weights(tmp_path, monkeypatch)
    _fake_lpips_package(monkeypatch, fail=offline, location=str(Path(found["lin"]).parents[2]))
    m, status = build_lpips("vgg")
    assert isinstance(m, LPIPS) and status == f"computed (weights: lpips package {found['lin']} + torch hub {found['vgg16']})"


def test_metrics_do_not_depend_on_float32_accumulation():
    """PSNR/SSIM accumulate in float64 (no TF32 convolutions on CUDA; CPU and GPU give the same numbers)."""
    from realityavatar.metrics import psnr, ssim

    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(48, 40, 3, generator=g), torch.rand(48, 40, 3, generator=g)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(x.double(), y.double())), abs=1e-12)
    assert float(psnr(x, y)) == pytest.approx(float(psnr(x.double(), y.double())), abs=1e-12)
    assert ssim(x, y).dtype == torch.float64


# ---------------------------------------------------------------------- published protocols (eval.protocol)

def _scene_pair(h=40, w=36, seed=3):
    """A structured ground truth (a disc on black, uint8-quantised like a PNG) and a noisy, shifted prediction."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    disc = ((yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (h / 3) ** 2).float()[..., None]
    gt = torch.round(disc * torch.rand(h, w, 3, generator=g) * 255) / 255
    pred = (torch.roll(gt, 1, 1) + 0.05 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    return pred, gt, disc


def _ssim_3dgs_loop(pred, gt, window=11, sigma=1.5):
    """3DGS's SSIM written out per pixel: Gaussian-weighted sums over each pixel's window, zero outside the image,
    averaged over all pixels and channels."""
    x, y = pred.double().numpy(), gt.double().numpy()
    H, W, C = x.shape
    r = window // 2
    g1 = np.exp(-((np.arange(window) - r) ** 2) / (2 * sigma**2))
    g1 /= g1.sum()
    wgt = np.outer(g1, g1)
    xp, yp = (np.pad(a, ((r, r), (r, r), (0, 0))) for a in (x, y))
    total = 0.0
    for i in range(H):
        for j in range(W):
            for c in range(C):
                a, b = xp[i:i + window, j:j + window, c], yp[i:i + window, j:j + window, c]
                mx, my = (wgt * a).sum(), (wgt * b).sum()
                vx, vy, vxy = (wgt * a * a).sum() - mx**2, (wgt * b * b).sum() - my**2, (wgt * a * b).sum() - mx * my
                total += ((2 * mx * my + 1e-4) * (2 * vxy + 9e-4)) / ((mx**2 + my**2 + 1e-4) * (vx + vy + 9e-4))
    return total / (H * W * C)


def test_dyco_ssim_equals_skimage_structural_similarity():
    """Dyco calls skimage's structural_similarity(pred, gt, channel_axis=-1, data_range=1) with its defaults."""
    metrics_ssim = pytest.importorskip("skimage.metrics").structural_similarity
    from realityavatar.metrics import PROTOCOLS, ssim_skimage

    assert PROTOCOLS["dyco"].ssim_fn is ssim_skimage
    for seed in range(3):
        pred, gt, _ = _scene_pair(seed=seed)
        ref = metrics_ssim(pred.double().numpy(), gt.double().numpy(), channel_axis=-1, data_range=1)
        assert float(ssim_skimage(pred, gt)) == pytest.approx(ref, abs=1e-10)
        assert float(ssim(pred, gt)) != pytest.approx(ref, abs=1e-3)  # ours is another convention
    batch = ssim_skimage(torch.stack([pred, gt]), torch.stack([gt, gt]))
    assert batch.shape == (2,) and float(batch[1]) == pytest.approx(1.0)


def test_seqavatar_ssim_equals_a_direct_3dgs_ssim():
    from realityavatar.metrics import PROTOCOLS, ssim_3dgs

    assert PROTOCOLS["seqavatar"].ssim_fn is ssim_3dgs
    pred, gt, _ = _scene_pair(h=17, w=15)
    assert float(ssim_3dgs(pred, gt)) == pytest.approx(_ssim_3dgs_loop(pred, gt), abs=1e-10)
    assert float(ssim_3dgs(gt, gt)) == pytest.approx(1.0)


def test_seqavatar_psnr_averages_the_channels_psnr():
    """3DGS's psnr on a [3,H,W] image, then .mean(): channel errors 0.1, 0.01, 0.001 give 20, 40, 60 dB -> 40."""
    from realityavatar.metrics import psnr_per_channel

    gt = torch.zeros(6, 5, 3)
    pred = gt + torch.tensor([0.1, 0.01, 0.001])
    assert float(psnr_per_channel(pred, gt)) == pytest.approx(40.0, abs=1e-6)
    assert float(psnr(pred, gt)) == pytest.approx(-10 * math.log10((0.01 + 1e-4 + 1e-6) / 3), abs=1e-6)


def test_floor_uint8_truncates_like_dyco_and_keeps_png_values():
    from realityavatar.metrics import floor_uint8

    levels = torch.arange(256, dtype=torch.float32) / 255  # a PNG's values survive (float32, as numpy computes)
    assert torch.equal(floor_uint8(levels), levels)
    x = torch.tensor([0.9999, 0.5, 1.5, -0.2])
    assert (floor_uint8(x) * 255).round().tolist() == [254, 127, 255, 0]  # truncation, not rounding (0.5 -> 127)


def test_mask_box_is_seqavatars_rect_bound_mask():
    """get_rect_bound_mask: the mask's box grown by 5 px (inclusive ends), clipped to the image."""
    from realityavatar.metrics import mask_box_mask

    mask = torch.zeros(30, 40, 1)
    mask[10:13, 2:20] = 1  # rows 10..12, columns 2..19
    box = mask_box_mask(mask)[..., 0]
    ys, xs = box.any(1).nonzero().squeeze(-1), box.any(0).nonzero().squeeze(-1)
    assert (int(ys[0]), int(ys[-1]), int(xs[0]), int(xs[-1])) == (5, 17, 0, 24)
    assert int(box.sum()) == 13 * 25


def test_smpl_box_is_the_rays_through_the_body_box():
    """A camera at the origin looking along +z and a box of joints 5 m ahead: the rays that meet it are those through
    the front face's projection (u = cx + f x / z_near at integer pixels, Dyco's rays); a body turned 45 degrees turns the box."""
    from realityavatar.geometry import axis_angle_to_matrix
    from realityavatar.metrics import smpl_box_mask

    f, cx, cy, H, W = 40.0, 32.0, 24.0, 48, 64
    K = torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    joints = torch.tensor([[-0.2, -0.5, 5.0], [0.2, 0.5, 5.2], [0.0, 0.0, 5.1]])
    mask = smpl_box_mask(joints, torch.eye(3), K, torch.eye(4), H, W, offset=0.3)[..., 0]
    lo, hi, z = torch.tensor([-0.51, -0.81]), torch.tensor([0.51, 0.81]), 5.0 - 0.31
    u, v = torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64)
    ux, vy = (u - cx) / f * z, (v - cy) / f * z
    ref = ((vy >= lo[1]) & (vy <= hi[1]))[:, None] & ((ux >= lo[0]) & (ux <= hi[0]))[None, :]
    assert torch.equal(mask, ref) and 0 < int(mask.sum()) < H * W
    turned = smpl_box_mask(joints, axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 4])), K, torch.eye(4), H, W)
    assert not torch.equal(turned[..., 0], mask)


class _RecordLPIPS(torch.nn.Module):
    """Stands in for LPIPS: records what it is given (our LPIPS maps [0,1] to the network's [-1,1] inside)."""

    def forward(self, pred, gt):
        self.seen = (pred.clone(), gt.clone())
        return (pred - gt).abs().mean()


@pytest.mark.parametrize("name", ["ours", "dyco", "seqavatar"])
def test_protocols_mask_quantise_and_score_as_specified(name):
    from realityavatar.metrics import eval_protocol, floor_uint8, psnr_per_channel, ssim_3dgs, ssim_skimage

    pred, gt, disc = _scene_pair()
    pred = pred + 0.3 * (1 - disc)  # a halo outside the person, which masking removes
    keep = torch.zeros_like(disc, dtype=torch.bool)
    keep[5:35, 4:32] = True
    proto = eval_protocol(name)
    lp = _RecordLPIPS()
    out = proto.scores(pred, gt, keep, lp)
    if name == "ours":
        p, g = pred, gt
        assert out["psnr"] == pytest.approx(float(psnr(p, g))) and out["ssim"] == pytest.approx(float(ssim(p, g)))
    elif name == "dyco":  # prediction and ground truth both background outside the SMPL box, then floored to uint8
        p, g = floor_uint8(torch.where(keep, pred, 0.0)), floor_uint8(torch.where(keep, gt, 0.0))
        assert out["psnr"] == pytest.approx(float(psnr(p, g)))
        assert out["ssim"] == pytest.approx(float(ssim_skimage(p, g)))
    else:  # the prediction only zeroed outside the mask box; the image as stored (already uint8)
        p, g = torch.where(keep, pred, 0.0), gt
        assert out["psnr"] == pytest.approx(float(psnr_per_channel(p, g)))
        assert out["ssim"] == pytest.approx(float(ssim_3dgs(p, g)))
        p, g = (p + 1) / 2, (g + 1) / 2  # SeqAvatar feeds [0,1] where the network expects [-1,1]
    torch.testing.assert_close(lp.seen[0], p.to(lp.seen[0].dtype))
    torch.testing.assert_close(lp.seen[1], g.to(lp.seen[1].dtype))
    assert out["lpips"] == pytest.approx(float((p - g).abs().mean()) * 1000)
    assert proto.describe()["name"] == name


def test_unknown_protocol_and_missing_pixels_are_named():
    from realityavatar.metrics import eval_protocol

    with pytest.raises(ValueError, match="eval.protocol: expected one of ours, dyco, seqavatar, got 'dyko'"):
        eval_protocol("dyko")
    pred, gt, _ = _scene_pair()
    with pytest.raises(ValueError, match="eval.protocol=dyco: needs the smpl_box pixels"):
        eval_protocol("dyco").scores(pred, gt, None)


def test_summarise_reports_the_spread_over_cameras():
    """Per split and phase, the std over held-out cameras of their mean scores (a verdict needs it beside the mean)."""
    from realityavatar.evaluate import summarise

    rows = [{"split": "novel_view", "phase": "rest", "view": v, "frame": f, "psnr_garment": base + f}
            for v, base in ((1, 20.0), (4, 24.0), (6, 22.0)) for f in (0, 1)]
    out = summarise(rows)
    assert np.isclose(out["test/novel_view/rest/psnr_garment"], 22.5)
    assert np.isclose(out["test/novel_view/rest/psnr_garment_camera_std"], np.std([20.5, 24.5, 22.5]))
    assert "test/novel_view/psnr_camera_std" not in out  # only scores the rows have
    one = summarise([r for r in rows if r["view"] == 1])
    assert "test/novel_view/psnr_garment_camera_std" not in one  # one camera: no spread
