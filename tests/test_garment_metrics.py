"""The garment's scores (metrics.image_metrics): regions eroded off their outline, PSNR / SSIM / FLIP / detail inside
them, and the motion phases evaluation groups them by (PoseTable.motion_phases)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from realityavatar.metrics import erode, flip_map, image_metrics, laplacian_energy, region_metrics, ssim_map


def _textured(seed: int = 0, size: int = 48) -> torch.Tensor:
    """An image [H,W,3] of 2-pixel stripes in random colours: detail the eye and the Laplacian both see."""
    g = torch.Generator().manual_seed(seed)
    cols = torch.rand(size // 2, 3, generator=g) * 0.8 + 0.1
    return cols.repeat_interleave(2, 0)[:, None, :].expand(size, size, 3).contiguous()


def _blur(x: torch.Tensor) -> torch.Tensor:
    k = torch.ones(3, 1, 5, 5, dtype=x.dtype) / 25
    return torch.nn.functional.conv2d(torch.nn.functional.pad(x.permute(2, 0, 1)[None], (2,) * 4, mode="replicate"),
                                      k, groups=3)[0].permute(1, 2, 0)


def test_erode_removes_two_pixels_of_outline_and_the_image_edge():
    region = torch.zeros(20, 20, 1)
    region[4:14, 5:15] = 1
    out = erode(region)
    assert out.dtype == torch.bool and out.shape == (20, 20, 1)
    assert out[6:12, 7:13].all() and int(out.sum()) == 36  # 10 x 10 -> 6 x 6
    edge = torch.ones(8, 8, 1)
    assert int(erode(edge).sum()) == 16  # the image's edge counts as outside: 8 x 8 -> 4 x 4


def test_region_scores_read_only_the_region():
    """A region's PSNR is the pixels' own MSE there; changing the image outside the region changes the whole-image
    PSNR but none of the region's scores."""
    gt = _textured()
    pred = (gt + 0.05).clamp(0, 1)
    region = torch.zeros(48, 48, 1, dtype=torch.bool)
    region[4:20, 12:40] = True
    flip, local = flip_map(pred, gt), ssim_map(pred, gt)[0]
    got = region_metrics(pred, gt, region, flip, local)
    mse = float(((pred - gt).double()[region[..., 0]] ** 2).mean())
    assert got["psnr"] == pytest.approx(-10 * math.log10(mse), abs=1e-9)
    spoilt = pred.clone()
    spoilt[40:] = 0.0  # outside the region, beyond the reach of the SSIM window and of FLIP's filters
    again = region_metrics(spoilt, gt, region, flip_map(spoilt, gt), ssim_map(spoilt, gt)[0])
    assert again == pytest.approx(got)
    full = image_metrics(pred, gt, torch.ones(48, 48, 1), torch.ones(48, 48, 1))
    assert image_metrics(spoilt, gt, torch.ones(48, 48, 1), torch.ones(48, 48, 1))["psnr"] < full["psnr"] - 3


def test_identical_images_score_perfectly_and_blur_loses_detail():
    gt = _textured()
    region = erode(torch.ones(48, 48, 1))
    same = region_metrics(gt, gt, region, flip_map(gt, gt), ssim_map(gt, gt)[0])
    assert same["psnr"] == math.inf and same["detail"] == pytest.approx(1.0)
    assert same["flip"] == 0.0 and same["ssim"] == pytest.approx(1.0)
    blurred = _blur(gt)
    b = region_metrics(blurred, gt, region, flip_map(blurred, gt), ssim_map(blurred, gt)[0])
    assert b["detail"] < 0.5 and b["flip"] > 0.05 and b["ssim"] < 0.9
    assert float(laplacian_energy(blurred).mean()) < float(laplacian_energy(gt).mean())


def test_image_metrics_garment_keys_only_with_a_label():
    gt = _textured()
    pred = _blur(gt)
    mask = torch.zeros(48, 48, 1)
    mask[4:44, 8:40] = 1
    alpha = mask.clone()
    plain = image_metrics(pred, gt, alpha, mask)
    assert {"psnr", "ssim", "flip", "iou", "psnr_masked", "ssim_masked", "flip_masked", "detail_masked"} <= set(plain)
    assert not any(k.endswith("_garment") for k in plain) and "lpips" not in plain
    garment = torch.zeros(48, 48, 1, dtype=torch.bool)
    garment[20:40, 10:38] = True
    labelled = image_metrics(pred, gt, alpha, mask, garment)
    assert {f"{m}_garment" for m in ("psnr", "ssim", "flip", "detail")} <= set(labelled)
    assert labelled["detail_garment"] < 0.6 and labelled["iou"] == 1.0
    sliver = torch.zeros(48, 48, 1, dtype=torch.bool)
    sliver[20:23] = True  # 3 rows: nothing left after a 2-pixel erosion
    assert not any(k.endswith("_garment") for k in image_metrics(pred, gt, alpha, mask, sliver))


def _spinning_table(frames, yaw_deg):
    from realityavatar.data.poses import PoseTable
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

    base = axis_angle_to_matrix(torch.tensor([[1.2, 0.0, 0.0]], dtype=torch.float64))  # a tilted start
    yaw = torch.zeros(len(yaw_deg), 3, dtype=torch.float64)
    yaw[:, 1] = torch.deg2rad(torch.as_tensor(yaw_deg, dtype=torch.float64))
    poses = torch.zeros(len(frames), 24, 3)
    poses[:, 0] = matrix_to_axis_angle(axis_angle_to_matrix(yaw) @ base).float()
    return PoseTable(frames, poses, torch.zeros(len(frames), 3))


def test_motion_phases_from_the_turning():
    """25 fps: 10 still frames, 20 frames turning at 360 deg/s, then still: rest, spin, one second 'after', then
    'settled'; a sequence that does not turn is 'all'; subsampled frames measure the turning per second."""
    fps = 25.0
    yaw = np.concatenate([np.zeros(10), 14.4 * np.arange(1, 21), np.full(40, 288.0)])  # 14.4 deg/frame = 360 deg/s
    frames = np.arange(len(yaw))
    phases = _spinning_table(frames, yaw).motion_phases(frames, fps)
    assert [phases[f] for f in (0, 9)] == ["rest"] * 2
    assert all(phases[f] == "spin" for f in range(10, 30))
    assert phases[30] == "after" and phases[54] == "after" and phases[55] == "settled" and phases[69] == "settled"
    sparse = frames[::5]
    coarse = _spinning_table(sparse, yaw[::5]).motion_phases(sparse, fps)
    assert coarse[5] == "rest" and coarse[15] == "spin" and coarse[60] == "settled"
    still = _spinning_table(frames, np.zeros(len(frames))).motion_phases(frames, fps)
    assert set(still.values()) == {"all"}


def test_motion_phases_match_the_scene_events(scenes_root):
    """On the ci scene the phases read from the poses agree with the simulator's spin events to 2 frames."""
    import json

    from realityavatar.data.i3d import read_i3d

    meta = json.loads((scenes_root / "skirt_spin_ci-meta.json").read_text())
    ev = meta["motion"]["events"]
    scene = read_i3d(scenes_root, "skirt_spin_ci")
    phases = scene.poses.motion_phases(scene.frames("novel_view"), meta["fps"])
    spin = [f for f, p in phases.items() if p == "spin"]
    assert abs(spin[0] - ev["spin_start_frame"]) <= 2 and abs(spin[-1] + 1 - ev["spin_stop_frame"]) <= 2
    assert phases[ev["spin_stop_frame"]] == "after"
