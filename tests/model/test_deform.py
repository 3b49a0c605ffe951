"""Motion-trend decoder: identity start, the encoding, the paper's deformation equations, coarse-to-fine."""

from __future__ import annotations

import torch

from realityavatar.geometry import (
    quat_to_matrix,
)
from realityavatar.model.deform import apply_deformation
from tests.helpers import assert_all_grads
from tests.model.configured import component


def test_motion_trend_decoder_identity_start_and_grads():
    torch.manual_seed(0)
    dec = component("deformer", cond_dim=16, hidden_dim=32, feature_dim=16)
    x = torch.randn(100, 3) * 0.4
    log_s = torch.randn(100, 3) - 4
    q = torch.nn.functional.normalize(torch.randn(100, 4), dim=-1)
    dec.fit_bounds(x)
    out = dec(x, torch.randn(2, 16))
    assert out["dx"].shape == (2, 100, 3) and out["ds"].shape == (2, 100, 3)
    assert out["dq"].shape == (2, 100, 4) and out["f_mt"].shape == (2, 100, 16)
    x_e, ls_e, q_e = apply_deformation(x, log_s, q, out)
    assert torch.allclose(x_e, x.expand(2, -1, -1)) and torch.allclose(ls_e, log_s.expand(2, -1, -1))
    assert torch.allclose(quat_to_matrix(q_e), quat_to_matrix(q).expand(2, -1, -1, -1), atol=1e-6)
    assert out["f_mt"].abs().sum() > 0
    assert bool(dec.bounds_fitted) and (dec.bbox_min <= x.min(0).values).all() and (dec.bbox_max >= x.max(0).values).all()
    loss = sum(v.square().sum() for v in out.values())
    loss.backward()
    assert_all_grads(dec)


def test_the_encoding_gives_the_means_no_gradient_path():
    """The decoder's encoding sees x_c detached: the means get their gradient from x_e = x_c + dx only."""
    torch.manual_seed(0)
    dec = component("deformer", cond_dim=8, hidden_dim=16, feature_dim=4)
    with torch.no_grad():
        dec.out.weight.normal_()  # outputs depend on x_c
    x = (torch.randn(30, 3) * 0.3).requires_grad_()
    out = dec(x, torch.randn(2, 8))
    (out["dx"].sum() + out["f_mt"].sum()).backward()
    assert x.grad is None or x.grad.abs().max() == 0


def test_apply_deformation_follows_paper_equations():
    x = torch.randn(5, 3)
    log_s = torch.randn(5, 3)
    q_c = torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    dq = torch.nn.functional.normalize(torch.randn(1, 5, 4), dim=-1)
    out = {"dx": torch.randn(1, 5, 3), "ds": torch.randn(1, 5, 3), "dq": dq}
    x_e, ls_e, q_e = apply_deformation(x, log_s, q_c, out)
    assert torch.allclose(x_e, x + out["dx"])
    assert torch.allclose(ls_e.exp(), log_s.exp() * out["ds"].exp(), rtol=1e-5)
    assert torch.allclose(quat_to_matrix(q_e), quat_to_matrix(dq) @ quat_to_matrix(q_c), atol=1e-5)  # R_e = ΔR R_c


def test_coarse_to_fine_window_opens_the_frequency_bands_in_turn():
    """schedule.deform_anneal (Nerfies' coarse-to-fine window): at alpha 0 only the input passes, a band fades in as
    alpha passes it, at alpha = num_freqs the encoding is the plain one bit for bit; the schedule opens it linearly
    from deform_start over deform_anneal steps."""
    from realityavatar.model.encodings import FrequencyEncoding

    enc = FrequencyEncoding(4)
    x = torch.rand(5, 3) * 2 - 1
    plain = enc(x)
    F_, D = 4, 3
    def bands(e):  # [sin|cos, band, xyz]
        return e[:, D:].reshape(5, 2, F_, D)

    enc.set_window(0.0)
    assert torch.equal(enc(x)[:, :D], x) and float(bands(enc(x)).abs().max()) == 0.0
    enc.set_window(1.5)  # band 0 full, band 1 half, bands 2-3 shut
    b, p = bands(enc(x)), bands(plain)
    assert torch.allclose(b[:, :, 0], p[:, :, 0]) and torch.allclose(b[:, :, 1], 0.5 * p[:, :, 1])
    assert float(b[:, :, 2:].abs().max()) == 0.0
    enc.set_window(4.0)
    assert torch.equal(enc(x), plain)

    from realityavatar.model.module import Schedule

    d = component("deformer", cond_dim=8, hidden_dim=16, num_layers=2, feature_dim=4, num_freqs=6)
    assert d.encoding.alpha == 6.0  # a decoder nobody set (a module outside training) sees every band
    sched = Schedule(deform_start=10, skin_pretrain_steps=0, deform_anneal=100)
    for step, alpha in ((0, 0.0), (10, 0.0), (60, 3.0), (110, 6.0), (500, 6.0), (None, 6.0)):
        d.set_window(sched.deform_window(step))
        assert d.encoding.alpha == alpha, (step, d.encoding.alpha)
    assert Schedule(deform_start=0, skin_pretrain_steps=0, deform_anneal=0).deform_window(0) == 1.0  # 0: every band from the start


def test_training_opens_the_coarse_to_fine_window_and_a_checkpoint_keeps_it(scenes_root, tmp_path, monkeypatch):
    """Every training step sets the decoder's window from schedule.deform_anneal, and load_run puts a checkpoint's
    window back where its step had it: a run stopped mid-anneal (4 of 8 steps) renders with half its bands, as it
    trained, not with bands it never trained."""
    from realityavatar.build import load_run
    from realityavatar.config import compose, prepare_run
    from realityavatar.model.module import AvatarModule
    from realityavatar.train import run

    assert compose([]).schedule.deform_anneal == compose([]).iterations // 2
    steps = []
    orig = AvatarModule.set_progress
    monkeypatch.setattr(AvatarModule, "set_progress", lambda self, step: (steps.append(step), orig(self, step))[1])
    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=4", "schedule.deform_anneal=8",
                                        "gaussians.num_points=300", "test_after_fit=false", "logger=none"]),
                               tmp_path / "run")
    run(cfg, choices)
    assert [s for s in steps if s is not None][:4] == list(range(4))
    _, module, _ = load_run(tmp_path / "run")
    assert module.avatar.deformer.encoding.alpha == module.avatar.deformer.encoding.num_freqs * 4 / 8


def test_a_box_fitted_to_points_flat_along_an_axis_gives_finite_offsets():
    """fit_bounds pads each axis by at least 1 mm: one Gaussian (gaussians.num_points=1), or points on a plane, gave a
    box of zero width and NaN offsets (the run stopped in the silhouette term's k-d tree, 'data must be finite')."""
    dec = component("deformer")
    for points in (torch.tensor([[0.1, 0.2, 0.3]]), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])):
        dec.fit_bounds(points)
        out = dec(points, torch.zeros(1, 128))
        assert all(torch.isfinite(v).all() for v in out.values()), points
