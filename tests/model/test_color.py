"""Colour models: the paper's MLP and per-Gaussian SH."""

from __future__ import annotations

import pytest
import torch

from realityavatar.model.color import MLPColor, SHColor
from realityavatar.render import eval_sh
from tests.helpers import assert_all_grads

SIZES = {"feature_dim": 8, "fmt_dim": 16, "frame_latent_dim": 4, "num_frames": 5, "sh_degree": 3, "hidden_dim": 64}


def test_mlp_color_shapes_grads_and_novel_pose_latent():
    torch.manual_seed(0)
    col = MLPColor(**SIZES)
    feats = torch.randn(40, 8)
    dirs = torch.randn(2, 40, 3)
    f_mt = torch.randn(2, 40, 16)
    rgb = col(feats, dirs, f_mt, torch.tensor([1, 3]))
    assert rgb.shape == (2, 40, 3) and (rgb > 0).all() and (rgb < 1).all()
    rgb.sum().backward()
    assert_all_grads(col)
    # frame_idx -1 uses the mean of the trained latents
    import copy

    with torch.no_grad():
        col.frame_latents.weight.normal_()
    assert torch.allclose(col.latent(torch.tensor([-1, 2]))[0], col.frame_latents.weight.mean(0))
    twin = copy.deepcopy(col)
    with torch.no_grad():
        twin.frame_latents.weight[0] = col.frame_latents.weight.mean(0)
    a = col(feats, dirs[:1], f_mt[:1], torch.tensor([-1]))
    b = twin(feats, dirs[:1], f_mt[:1], torch.tensor([0]))
    assert torch.allclose(a, b, atol=1e-6)
    assert not torch.allclose(a, col(feats, dirs[:1], f_mt[:1], torch.tensor([0])), atol=1e-4)
    with pytest.raises(IndexError):
        col(feats, dirs[:1], f_mt[:1], torch.tensor([5]))
    # the paper's colour model has every input: no option turns one off
    for bad, field in (({"sh_degree": 0}, "color.sh_degree"), ({"frame_latent_dim": 0}, "color.frame_latent_dim"),
                       ({"num_frames": 0}, "color.num_frames")):
        with pytest.raises(ValueError, match=field):
            MLPColor(**{**SIZES, **bad})


def test_sh_color_matches_eval_sh():
    col = SHColor(sh_degree=2, feature_dim=27, num_frames=3)
    feats = torch.randn(10, 27, requires_grad=True)
    dirs = torch.randn(2, 10, 3)
    rgb = col(feats, dirs, None, torch.tensor([0, 0]))
    ref = torch.clamp_min(eval_sh(2, feats.reshape(10, 9, 3)[None].expand(2, -1, -1, -1), dirs) + 0.5, 0.0)
    assert torch.allclose(rgb, ref)
    rgb.sum().backward()
    assert feats.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="feature_dim"):
        SHColor(sh_degree=3, feature_dim=32)


def test_colour_of_per_sample_features_equals_each_samples_own():
    """Features [B,N,F] (a sliding sheet's, per sample) give each sample the colour its own [N,F] would."""
    torch.manual_seed(0)
    N, B = 7, 2
    dirs, f_mt, idx = torch.randn(B, N, 3), torch.randn(B, N, 4), torch.tensor([0, 1])
    for color, F_ in ((MLPColor(5, 4, 3, 2, 3, 16), 5), (SHColor(3, 48), 48)):
        feats = torch.randn(B, N, F_)
        both = color(feats, dirs, f_mt, idx)
        for b in range(B):
            assert torch.allclose(both[b], color(feats[b], dirs[b : b + 1], f_mt[b : b + 1], idx[b : b + 1])[0])
