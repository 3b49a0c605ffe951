"""Flow supervision (`flow=dis`): DIS flow pairs, the rendered image motion of the Gaussians, the term, the data path."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.data.flow import FlowSpec, flow_pair
from realityavatar.losses import FlowLoss, NoFlow


def _texture(H: int = 64, W: int = 64, seed: int = 0) -> np.ndarray:
    """Smooth random colour texture (blobs a few pixels wide), uint8 [H,W,3]."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    x = gaussian_filter(rng.random((H, W, 3)), sigma=(2.0, 2.0, 0))
    x = (x - x.min()) / (x.max() - x.min())
    return (x * 255).astype(np.uint8)


def test_flow_pair_points_from_the_later_image_to_the_earlier():
    """Content moved by (+3, -2) px from the earlier image p to the later image t: a pixel of t finds its material
    at (-3, +2) in p. Pixels whose match leaves the earlier mask are not valid."""
    tex = _texture(80, 80)
    img_p = tex[8:72, 8:72]
    img_t = tex[10:74, 5:69]  # t(y, x) = tex(y + 10, x + 5) = p(y + 2, x - 3)
    mask = np.zeros((64, 64), bool)
    mask[8:56, 8:56] = True
    mask_p = mask.copy()
    flow, valid = flow_pair(img_t, mask, img_p, mask_p, FlowSpec(fb_tol=1.0, erode=1))
    assert flow.shape == (64, 64, 2) and valid.dtype == bool
    assert valid.sum() > 0.6 * mask.sum(), valid.sum()
    med = np.median(flow[valid], axis=0)
    assert abs(med[0] - (-3.0)) < 0.3 and abs(med[1] - 2.0) < 0.3, med
    assert not valid[~mask].any()
    # A match that lands outside the earlier mask is dropped: shrink mask_p to its left half.
    mask_p2 = mask.copy()
    mask_p2[:, 32:] = False
    _, valid2 = flow_pair(img_t, mask, img_p, mask_p2, FlowSpec())
    assert not valid2[:, 40:].any() and valid2[:, 10:28].any()


def test_flow_spec_refuses_bad_values():
    for kw, field in [({"frame_gap": 0}, "frame_gap"), ({"preset": "slow"}, "preset"), ({"fb_tol": 0.0}, "fb_tol"),
                      ({"erode": -1}, "erode")]:
        with pytest.raises(ValueError, match=field):
            FlowSpec(**kw)


def test_flow_loss_is_zero_at_the_flow_and_ignores_invalid_pixels():
    H = 16
    flow = torch.randn(1, H, H, 2) * 3
    alpha = torch.rand(1, H, H, 1)
    valid = torch.zeros(1, H, H, 1)
    valid[:, 4:12, 4:12] = 1
    loss = FlowLoss(weight=1.0)
    assert float(loss(alpha * flow / H, alpha, flow, valid)) == pytest.approx(0.0, abs=1e-7)
    wrong = alpha * flow / H
    wrong[:, :4] += 1.0  # rows outside the valid square
    assert float(loss(wrong, alpha, flow, valid)) == pytest.approx(0.0, abs=1e-7)
    wrong[:, 4:12, 4:12] += 0.1
    assert float(loss(wrong, alpha, flow, valid)) > 0.1
    # The push fades with the error (Charbonnier): 0.01 px off gets ~1/50 of the gradient of 5 px off.
    grads = []
    for off_px in (0.01, 5.0):
        pred = (alpha * flow / H + off_px / H).requires_grad_()
        loss(pred, alpha, flow, valid).backward()
        grads.append(float(pred.grad.abs().sum()))
    assert grads[0] < 0.05 * grads[1], grads


def test_flow_group_composes_and_switches_off():
    assert isinstance(instantiate(compose(["flow=none"]).flow), NoFlow)
    on = instantiate(compose(["flow=dis", "flow.frame_gap=2"]).flow)
    assert isinstance(on, FlowLoss) and on.spec.frame_gap == 2 and on.weight > 0


def _ci_module(extra: list[str]):
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=600", *extra])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    return dm, module


def test_training_samples_carry_flow_to_the_earlier_image(scenes_root):
    dm, _ = _ci_module(["flow=dis"])
    ds = dm.datasets["train"]
    frames = sorted({r.frame for r in ds.records})
    first = next(i for i, r in enumerate(ds.records) if r.frame == frames[0])
    later = next(i for i, r in enumerate(ds.records) if r.frame == frames[1])
    s0, s1 = ds[first], ds[later]
    H, W = s1["height"], s1["width"]
    assert s1["flow"].shape == (H, W, 2) and s1["flow_valid"].shape == (H, W, 1)
    assert float(s0["flow_valid"].sum()) == 0.0  # the first frame has no earlier image
    assert float(s1["flow_valid"].sum()) > 0.0
    assert float((s1["flow_valid"] * (1 - s1["mask"])).sum()) == 0.0  # only inside the mask
    # The earlier pose window ends one frame before.
    w_prev, _ = ds.poses.window(frames[1] - 1, ds.window_len, ds.window_step)
    assert torch.equal(s1["prev_poses"], w_prev)
    assert "flow" not in dm.datasets["novel_view"][0]
    # A gap no training image has is refused, naming the field.
    from realityavatar.build import build_data

    cfg = compose(["data=synthetic_ci", "trainer=ci", "flow=dis", "flow.frame_gap=10000"])
    with pytest.raises(ValueError, match="flow.frame_gap"):
        build_data(cfg, instantiate(cfg.body))


def test_rendered_image_motion_matches_a_known_translation(scenes_root):
    """The earlier frame's body 5 cm along the camera's +x: every Gaussian's image displacement (t -> t-1) is
    fx * 5 cm / depth to the right and 0 down, and the composited channels lie within the Gaussians' range wherever
    the render is opaque."""
    dm, module = _ci_module(["flow=dis"])
    batch = next(iter(dm.train_dataloader()))
    batch = module.on_after_batch_transfer(batch, 0)
    E, K = batch["viewmat"][0], batch["K"][0]
    batch["prev_poses"] = batch["poses"].clone()
    batch["prev_transl"] = batch["transl"] + 0.05 * E[0, :3]  # world shift = camera x axis * 5 cm
    with torch.no_grad():
        motion = module.image_motion(batch, deform=True)
        _, alpha, _, posed = module.render_batch(batch, extra=motion)
        per_gaussian = motion(posed)[0]  # [N,2] image heights
        depth = (posed["means"][0] @ E[:3, :3].T + E[:3, 3])[:, 2]
    H = float(batch["height"][0])
    expect = K[0, 0] * 0.05 / depth / H  # the shifted frame's depth is the same (x shift only)
    assert torch.allclose(per_gaussian[:, 0], expect, rtol=0.05, atol=1e-4), (per_gaussian[:5, 0], expect[:5])
    assert float(per_gaussian[:, 1].abs().max()) < 0.05 * float(expect.min())
    img = posed["extra_image"][0]  # [H,W,2]
    solid = alpha[0, ..., 0] > 0.05  # the composite over alpha is a convex combination of the Gaussians' values
    assert solid.sum() > 20
    ratio = img[solid][:, 0] / alpha[0][solid][:, 0]
    lo, hi = float(per_gaussian[:, 0].min()), float(per_gaussian[:, 0].max())
    assert float(ratio.min()) >= lo - 1e-6 and float(ratio.max()) <= hi + 1e-6
    assert float((img[~(alpha[0, ..., 0] > 0)]).abs().max()) == 0.0  # background stays 0


def test_flow_term_trains_and_is_logged(scenes_root, tmp_path):
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=6", "flow=dis",
                                        "gaussians.num_points=400", "test_after_fit=false"]),
                               tmp_path / "run")
    run(cfg, choices)
    import csv

    with open(next((tmp_path / "run").rglob("metrics.csv"))) as f:
        rows = list(csv.DictReader(f))
    vals = [float(r["train/flow"]) for r in rows if r.get("train/flow")]
    assert vals and all(np.isfinite(vals)), rows[:2]


def test_flow_files_are_read_and_checked(tmp_path):
    from realityavatar.data.flow import read_flow_file

    (tmp_path / "03").mkdir()
    flow = np.full((8, 10, 2), 1.5, np.float32)
    valid = np.zeros((8, 10), bool)
    valid[2:5, 3:7] = True
    np.savez(tmp_path / "03" / "000012.npz", flow=flow, valid=valid)
    f, v = read_flow_file(tmp_path, 3, 12, (8, 10))
    assert f.shape == (8, 10, 2) and float(f[0, 0, 0]) == 1.5 and v.sum() == 12
    f, v = read_flow_file(tmp_path, 3, 13, (8, 10))  # no file: no valid pixel
    assert not v.any()
    with pytest.raises(ValueError, match="000012.npz"):
        read_flow_file(tmp_path, 3, 12, (16, 20))  # another resolution
    np.savez(tmp_path / "03" / "000014.npz", flow=flow)
    with pytest.raises(ValueError, match="valid"):
        read_flow_file(tmp_path, 3, 14, (8, 10))
    with pytest.raises(ValueError, match="flow.dir"):
        FlowSpec(source="files", dir=str(tmp_path / "nowhere"))


def test_oracle_flow_is_the_projected_motion_of_the_visible_surface():
    """A square 2 m in front of the camera moved by (-2 cm, +1 cm) since the earlier frame: every pixel that sees it
    has the flow fx * (-dx, -dy) / 2 m (to the earlier frame), the rest no hit."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ablations"))
    from oracle_flow import oracle_flow

    V = np.array([[-0.3, -0.3, 2.0], [0.3, -0.3, 2.0], [0.3, 0.3, 2.0], [-0.3, 0.3, 2.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    shift = np.array([-0.02, 0.01, 0.0])
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    flow, hit = oracle_flow((V, faces), V - shift, K, np.eye(4), 32, 32)
    assert hit[16, 16] and not hit[0, 0] and hit.sum() > 100
    np.testing.assert_allclose(flow[hit], np.broadcast_to(-40.0 * shift[:2] / 2.0, (int(hit.sum()), 2)), atol=1e-4)


@pytest.mark.parametrize("prev_grad", [False, True])
def test_flow_term_moves_gaussians_and_never_fades_them(scenes_root, prev_grad):
    """The flow term alone: its gradient reaches the Gaussians' positions (through their image motion) and the
    networks, but not their opacities or scales (the blend weights of its render pass are detached). With
    flow.prev_grad the earlier frame's positions take part: the same batch gives another position gradient."""
    dm, module = _ci_module(["flow=dis", f"flow.prev_grad={str(prev_grad).lower()}"])
    batch = module.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
    batch["flow"] = torch.full_like(batch["flow"], 2.0)  # every valid pixel moved 2 px since the earlier frame
    batch["flow_valid"] = batch["mask"].clone()
    batch["prev_transl"] = batch["transl"] + 0.03  # the earlier frame elsewhere, so the two frames differ
    motion = module.image_motion(batch, deform=True)
    _, alpha, _, posed = module.render_batch(batch, extra=motion)
    module.flow(posed["extra_image"], alpha, batch["flow"], batch["flow_valid"]).backward()
    g = module.gaussians
    assert g.means.grad is not None and float(g.means.grad.abs().sum()) > 0
    for name in ("opacity_logits", "log_scales", "features"):
        grad = getattr(g, name).grad
        assert grad is None or float(grad.abs().sum()) == 0.0, name
    _MEANS_GRAD[prev_grad] = g.means.grad.clone()
    if len(_MEANS_GRAD) == 2:
        assert not torch.allclose(_MEANS_GRAD[False], _MEANS_GRAD[True])


_MEANS_GRAD: dict = {}
