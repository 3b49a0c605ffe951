"""Temporal module: w/o LSTM ignores the history, the LSTM does not (also after training)."""

from __future__ import annotations

import torch

from realityavatar.config import compose
from realityavatar.model.temporal import GRUTemporal, LSTMTemporal, NoTemporal, RecurrentTemporal
from tests.helpers import assert_all_grads


def test_temporal_none_ignores_history_lstm_does_not():
    torch.manual_seed(0)
    f = torch.randn(3, 6, 32)
    perm = torch.cat([torch.tensor([3, 0, 4, 1, 2]), torch.tensor([5])])
    none, lstm, gru = NoTemporal(32, 16), LSTMTemporal(32, 16, 1), GRUTemporal(32, 16, 1)
    assert torch.equal(none(f), none(f[:, perm]))
    assert not torch.allclose(lstm(f), lstm(f[:, perm]))
    assert not torch.allclose(gru(f), gru(f[:, perm]))
    for m in (none, lstm, gru):
        h = m(f)
        assert h.shape == (3, 16) and m.out_dim == 16
        h.square().sum().backward()
        assert_all_grads(m)
    assert isinstance(lstm.rnn, torch.nn.LSTM) and isinstance(gru.rnn, torch.nn.GRU)


def _still_and_spin(T: int):
    """Two pose windows [1,T,24,3] ending in the same pose: standing still, and spinning about the vertical axis
    into it."""
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

    still = torch.zeros(1, T, 24, 3)
    yaw = torch.linspace(-3.0, 0.0, T)
    spin = still.clone()
    spin[0, :, 0] = matrix_to_axis_angle(axis_angle_to_matrix(torch.stack([torch.zeros(T), yaw, torch.zeros(T)], -1)))
    return still, spin, torch.zeros(1, T, 3)


def test_trained_lstm_model_depends_on_motion_history(trained_run):
    """Same current pose, different histories (standing vs spinning into it): a trained LSTM model (the suite's
    trained run) poses the Gaussians differently."""
    from realityavatar.build import load_run

    _, module, _ = load_run(trained_run[0])
    assert isinstance(module.avatar.temporal, RecurrentTemporal)
    still, spin, transl = _still_and_spin(module.run_info.get("window_len", 6))
    with torch.no_grad():
        diff = (module.avatar.deform(module.avatar.pose_inputs(still, transl))["means"] - module.avatar.deform(module.avatar.pose_inputs(spin, transl))["means"]).norm(dim=-1)
    # 60 CPU steps move the zero-initialised decoder output only a little (~1e-5 m); the sweep-scale effect is
    # measured by python -m realityavatar.analysis.probe. What must hold: with an LSTM the history moves every Gaussian.
    assert float(diff.min()) > 1e-7 and float(diff.mean()) > 2e-6, f"history moved the Gaussians {float(diff.mean()):.2e} m"


def test_model_without_temporal_module_ignores_motion_history():
    """The w/o-LSTM model (temporal=none) cannot tell the two histories apart: its output is a function of the current
    frame only, also once its encoder and decoder have left their start (weights moved as training moves them)."""
    from realityavatar.body import build_body
    from realityavatar.build import build_module

    module = build_module(compose(["temporal=none", "gaussians.num_points=300"]), build_body("mannequin"),
                          num_train_frames=2, scene_extent=1.0)
    assert isinstance(module.avatar.temporal, NoTemporal)
    still, spin, transl = _still_and_spin(4)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        start = module.avatar.deform(module.avatar.pose_inputs(still, transl))["means"]
        for part in (module.avatar.encoder, module.avatar.temporal, module.avatar.deformer):
            for p in part.parameters():
                p.add_(0.05 * torch.randn(p.shape, generator=g))
        a, b = module.avatar.deform(module.avatar.pose_inputs(still, transl))["means"], module.avatar.deform(module.avatar.pose_inputs(spin, transl))["means"]
    assert float((a - start).norm(dim=-1).mean()) > 1e-3, "the decoder does not move the Gaussians: nothing is checked"
    assert float((a - b).norm(dim=-1).max()) == 0.0
