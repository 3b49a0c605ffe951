"""Model components: shapes, gradients, ablation options, identity starts, LBS, density control, checkpoint resize."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from fixtures_data import RandomBody

from realityavatar.geometry import (
    axis_angle_to_matrix,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    rigid,
    sample_surface,
)
from realityavatar.model.color import MLPColor, SHColor
from realityavatar.model.deform import MotionTrendDecoder, apply_deformation
from realityavatar.model.density import DensityControl, NoDensityControl
from realityavatar.model.encoders import PART_DIMS, LatentBoneEncoder, pose_features
from realityavatar.model.gaussians import PARAM_NAMES, CanonicalGaussians
from realityavatar.model.skinning import SkinningField, lbs_gaussians, pretrain_skinning, skinning_loss
from realityavatar.model.temporal import NoTemporal, RecurrentTemporal
from realityavatar.render import eval_sh


@pytest.fixture(scope="module")
def body() -> RandomBody:
    return RandomBody(seed=3, pelvis=(0.0, 0.0, 0.0), spread=0.15)


def _poses(B=2, T=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, T, 24, 3, generator=g) * 0.3, torch.randn(B, T, 3, generator=g) * 0.5


def _all_grads(module: torch.nn.Module):
    missing = [n for n, p in module.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not missing, f"no gradient reached {missing}"


# ---------------------------------------------------------------------- Gaussians and surface sampling
def test_sample_surface_barycentric_weights(body):
    gen = torch.Generator().manual_seed(0)
    pts, w = sample_surface(body.rest_vertices, body.faces, body.skin_weights, 500, gen)
    assert pts.shape == (500, 3) and w.shape == (500, 24)
    assert torch.allclose(w.sum(-1), torch.ones(500), atol=1e-5)
    # every tetrahedron is skinned to one joint, so samples carry one-hot weights and lie near that joint
    j = w.argmax(-1)
    assert torch.allclose(w.max(-1).values, torch.ones(500), atol=1e-5)
    assert ((pts - body.rest_joints[j]).norm(dim=-1) < 0.06).all()
    pts2, _ = sample_surface(body.rest_vertices, body.faces, body.skin_weights, 500, torch.Generator().manual_seed(0))
    assert torch.equal(pts, pts2)


def test_canonical_gaussians_init(body):
    g = CanonicalGaussians(body, num_points=300, feature_dim=8, init_opacity=0.1, seed=1)
    assert g.num_points == 300
    shapes = {n: tuple(getattr(g, n).shape) for n in PARAM_NAMES}
    assert shapes == {"means": (300, 3), "log_scales": (300, 3), "quats": (300, 4), "opacity_logits": (300,), "features": (300, 8)}
    assert torch.allclose(g.opacities(), torch.full((300,), 0.1), atol=1e-6)
    assert torch.allclose(g.rotations(), torch.tensor([1.0, 0, 0, 0]).expand(300, 4))
    assert (g.scales() > 0).all() and g.init_scale < 0.05
    # on the canonical surface: every point lies near a (canonical-pose) joint of its tetrahedron
    Jc = body.joints(body.canonical_pose())
    d = torch.cdist(g.means.detach(), Jc).min(-1).values
    assert (d < 0.06).all()
    assert torch.equal(g.means, CanonicalGaussians(body, num_points=300, feature_dim=8, seed=1).means)
    assert set(g.param_groups()) == set(PARAM_NAMES)


def test_checkpoint_with_other_count_resizes(body):
    small = CanonicalGaussians(body, num_points=50, feature_dim=4, seed=0)
    big = CanonicalGaussians(body, num_points=120, feature_dim=4, seed=2)
    wrapper = torch.nn.Module()
    wrapper.gaussians = big
    wrapper.load_state_dict({f"gaussians.{k}": v for k, v in small.state_dict().items()})
    assert wrapper.gaussians.num_points == 50
    for n in PARAM_NAMES:
        assert torch.equal(getattr(wrapper.gaussians, n), getattr(small, n))


# ---------------------------------------------------------------------- pose encoder
def test_pose_features_invariant_to_heading_but_not_to_spin():
    poses, transl = _poses()
    feats = pose_features(poses, transl)
    assert {k: v.shape[-1] for k, v in feats.items()} == PART_DIMS
    # rotate and shift the whole window about the world origin: root orientation and translation change, features not
    R0 = axis_angle_to_matrix(torch.tensor([0.0, 1.3, 0.0]))
    from realityavatar.geometry import matrix_to_axis_angle

    p2 = poses.clone()
    p2[:, :, 0] = matrix_to_axis_angle(R0 @ axis_angle_to_matrix(poses[:, :, 0]))
    t2 = (R0 @ transl[..., None]).squeeze(-1) + torch.tensor([1.0, 0.0, -2.0])
    feats2 = pose_features(p2, t2)
    for k in feats:
        assert torch.allclose(feats[k], feats2[k], atol=1e-5), k
    # a different spin history (only past root orientations differ) changes the torso features
    p3 = poses.clone()
    p3[:, 0, 0] += torch.tensor([0.0, 0.8, 0.0])
    feats3 = pose_features(p3, transl)
    assert not torch.allclose(feats3["torso"], feats["torso"])
    assert torch.allclose(feats3["left_arm"], feats["left_arm"])
    # the current frame's own root terms are zero (relative to itself)
    assert torch.allclose(feats["torso"][:, -1, 30:], torch.zeros(2, 9), atol=1e-6)


def test_pose_features_rejects_nan():
    poses, transl = _poses()
    poses[0, 1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        pose_features(poses, transl)


@pytest.mark.parametrize("split,zc", [(True, 16), (False, 16), (True, 0)])
def test_latentbone_encoder_options(split, zc):
    enc = LatentBoneEncoder(part_split=split, clothes_latent_dim=zc, out_dim=64)
    poses, transl = _poses()
    f = enc(poses, transl)
    assert f.shape == (2, 5, 64) and enc.out_dim == 64
    f.square().sum().backward()
    _all_grads(enc)
    names = dict(enc.named_parameters())
    if zc == 0:
        assert enc.z_c is None and not any("z_c" in n for n in names)
    else:
        assert enc.z_c.shape == (zc,)
    if split:
        assert set(enc.part_layers) == {"left_arm", "right_arm", "legs", "torso"}
        assert enc.part_layers["legs"][0].in_features == PART_DIMS["legs"] + zc
    else:
        assert not hasattr(enc, "part_layers")
        assert enc.input_layer[0].in_features == sum(PART_DIMS.values()) + zc


# ---------------------------------------------------------------------- temporal
def test_temporal_none_ignores_history_lstm_does_not():
    torch.manual_seed(0)
    f = torch.randn(3, 6, 32)
    perm = torch.cat([torch.tensor([3, 0, 4, 1, 2]), torch.tensor([5])])
    none, lstm, gru = NoTemporal(32, 16), RecurrentTemporal("lstm", 32, 16), RecurrentTemporal("gru", 32, 16)
    assert torch.equal(none(f), none(f[:, perm]))
    assert not torch.allclose(lstm(f), lstm(f[:, perm]))
    assert not torch.allclose(gru(f), gru(f[:, perm]))
    for m in (none, lstm, gru):
        h = m(f)
        assert h.shape == (3, 16) and m.out_dim == 16
        h.square().sum().backward()
        _all_grads(m)
    with pytest.raises(ValueError, match="temporal.kind"):
        RecurrentTemporal("transformer", 32, 16)


# ---------------------------------------------------------------------- motion-trend decoder
def test_motion_trend_decoder_identity_start_and_grads():
    torch.manual_seed(0)
    dec = MotionTrendDecoder(cond_dim=16, hidden_dim=32, feature_dim=16)
    x = torch.randn(100, 3) * 0.4
    log_s = torch.randn(100, 3) - 4
    q = torch.nn.functional.normalize(torch.randn(100, 4), dim=-1)
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
    _all_grads(dec)


def test_the_encoding_gives_the_means_no_gradient_path():
    """The decoder's encoding sees x_c detached: the means get their gradient from x_e = x_c + dx only."""
    torch.manual_seed(0)
    dec = MotionTrendDecoder(cond_dim=8, hidden_dim=16, feature_dim=4)
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


# ---------------------------------------------------------------------- skinning
def test_skinning_field_softmax_and_loss_grads(body):
    field = SkinningField(hidden_dim=32, num_layers=2)
    x = torch.randn(4, 50, 3)
    w = field(x)
    assert w.shape == (4, 50, 24)
    assert torch.allclose(w.sum(-1), torch.ones(4, 50), atol=1e-5) and (w >= 0).all()
    pts, tw = sample_surface(body.rest_vertices, body.faces, body.skin_weights, 64, torch.Generator().manual_seed(0))
    skinning_loss(field, pts, tw).backward()
    _all_grads(field)


def test_pretrain_skinning_lowers_loss(body):
    torch.manual_seed(0)
    field = SkinningField(hidden_dim=32, num_layers=2)
    pts, tw = sample_surface(body.rest_vertices, body.faces, body.skin_weights, 512, torch.Generator().manual_seed(5))
    field.fit_bounds(body.rest_vertices)
    before = float(skinning_loss(field, pts, tw).detach())
    pretrain_skinning(field, body.rest_vertices, body.faces, body.skin_weights, steps=40, batch=128, lr=1e-2)
    assert float(skinning_loss(field, pts, tw).detach()) < 0.5 * before


def test_lbs_identity_and_pure_rotation():
    g = torch.Generator().manual_seed(0)
    means = torch.randn(2, 30, 3, generator=g)
    quats = torch.nn.functional.normalize(torch.randn(30, 4, generator=g), dim=-1)
    w = torch.softmax(torch.randn(30, 24, generator=g), -1)
    A = torch.eye(4).expand(2, 24, 4, 4)
    m_o, q_o, rot = lbs_gaussians(means, quats, w, A)
    assert torch.allclose(m_o, means, atol=1e-6)
    assert torch.allclose(quat_to_matrix(q_o), quat_to_matrix(quats).expand(2, -1, -1, -1), atol=1e-5)
    assert torch.allclose(rot, torch.eye(3).expand(2, 30, 3, 3), atol=1e-6)
    # the same rigid motion for every bone: means and Gaussian rotations turn together
    R = axis_angle_to_matrix(torch.tensor([0.3, -1.1, 0.7]))
    t = torch.tensor([0.5, -0.2, 1.0])
    A = rigid(R, t).expand(2, 24, 4, 4)
    m_o, q_o, rot = lbs_gaussians(means, quats, w, A)
    assert torch.allclose(m_o, (R @ means[..., None]).squeeze(-1) + t, atol=1e-5)
    assert torch.allclose(quat_to_matrix(q_o), R @ quat_to_matrix(quats), atol=1e-5)
    # the quaternion itself is q_R ⊗ q (up to sign, which is the same rotation) and unit length
    expect = quat_multiply(matrix_to_quat(R), quats).expand(2, -1, -1)
    sign = torch.sign((q_o * expect).sum(-1, keepdim=True))
    assert torch.allclose(q_o, sign * expect, atol=1e-5) and torch.allclose(q_o.norm(dim=-1), torch.ones(2, 30))


def test_lbs_blend_of_two_rotations_gives_a_rotation():
    R1 = axis_angle_to_matrix(torch.tensor([0.0, 0.0, 0.0]))
    R2 = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2]))
    A = torch.eye(4).repeat(1, 24, 1, 1)
    A[0, 1, :3, :3] = R2
    w = torch.zeros(1, 24)
    w[0, 0] = w[0, 1] = 0.5
    quats = torch.tensor([[1.0, 0, 0, 0]])
    m_o, q_o, rot = lbs_gaussians(torch.tensor([[1.0, 0.0, 0.0]]), quats, w, A)
    # positions use the blended (shrunk) matrix exactly; the Gaussian rotation is its polar factor: 45 deg about z
    assert torch.allclose(m_o, (0.5 * (R1 + R2) @ torch.tensor([1.0, 0, 0]))[None, None], atol=1e-6)
    R45 = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 4]))
    assert torch.allclose(rot[0, 0], R45, atol=1e-5)
    assert torch.allclose(quat_to_matrix(q_o[0, 0]), R45, atol=1e-5)


# ---------------------------------------------------------------------- colour
def test_mlp_color_shapes_grads_and_novel_pose_latent():
    torch.manual_seed(0)
    col = MLPColor(feature_dim=8, fmt_dim=16, frame_latent_dim=4, num_frames=5, sh_degree=3, hidden_dim=64)
    feats = torch.randn(40, 8)
    dirs = torch.randn(2, 40, 3)
    f_mt = torch.randn(2, 40, 16)
    rgb = col(feats, dirs, f_mt, torch.tensor([1, 3]))
    assert rgb.shape == (2, 40, 3) and (rgb > 0).all() and (rgb < 1).all()
    rgb.sum().backward()
    _all_grads(col)
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
    no_fmt = MLPColor(feature_dim=8, fmt_dim=16, num_frames=5, use_fmt=False)
    assert no_fmt(feats, dirs, None, torch.tensor([0, 1])).shape == (2, 40, 3)


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


# ---------------------------------------------------------------------- density control
def _adam_with_state(g: CanonicalGaussians) -> torch.optim.Adam:
    groups = [{"params": ps, "name": n} for n, ps in g.param_groups().items()]
    opt = torch.optim.Adam(groups, lr=1e-3)
    for n in g.param_names:
        p = getattr(g, n)
        p.grad = torch.arange(p.numel(), dtype=torch.float32).reshape(p.shape) + 1.0
    opt.step()
    return opt


def _meta(n, high_idx, value=1e-2):
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    means2d.grad[0, high_idx, 0] = value
    return {"means2d": means2d, "radii": torch.ones(1, n, dtype=torch.int32)}


def test_density_clone_split_prune_with_optimizer_state(body):
    g = CanonicalGaussians(body, num_points=20, feature_dim=4, seed=0)
    assert g.param_names == PARAM_NAMES
    with torch.no_grad():
        g.log_scales[:10] = math.log(0.001)  # small -> clone
        g.log_scales[10:] = math.log(0.05)  # large -> split
        g.opacity_logits[:] = 2.0
        g.opacity_logits[19] = -8.0  # prune
    opt = _adam_with_state(g)
    old_avg = {n: opt.state[getattr(g, n)]["exp_avg"].clone() for n in g.param_names}
    old_means = g.means.detach().clone()
    old_scales = g.scales().detach().clone()
    dc = DensityControl(refine_start=0, refine_stop=100, refine_every=10, grad_threshold=2e-4, prune_opacity=0.05,
                        grow_scale3d=0.01, scene_scale=1.0, reset_every=0, max_points=1000)
    high = [0, 1, 2, 12, 13]  # 3 clones, 2 splits
    stats = dc.step_post_backward(g, opt, _meta(20, high), step=10, image_size=(64, 48))
    assert stats["cloned"] == 3 and stats["split"] == 2 and stats["pruned"] == 1
    assert g.num_points == 20 + 3 + 2 - 1
    # the optimizer now points at the new parameters and its rows follow them
    for n in g.param_names:
        p = getattr(g, n)
        assert any(p is q for grp in opt.param_groups for q in grp["params"])
        st = opt.state[p]["exp_avg"]
        assert st.shape[0] == g.num_points
    # layout: kept originals (not split, not pruned) first, then clones' zero rows, then split children's zero rows
    kept = [i for i in range(20) if i not in (12, 13, 19)]
    avg = opt.state[g.means]["exp_avg"]
    assert torch.equal(avg[: len(kept)], old_avg["means"][kept])
    assert (avg[len(kept):] == 0).all()
    assert torch.allclose(g.means[: len(kept)], old_means[kept])
    assert torch.allclose(g.means[len(kept): len(kept) + 3], old_means[[0, 1, 2]])  # clones copy
    assert torch.allclose(g.scales()[-4:], old_scales[[12, 13, 12, 13]] / 1.6, rtol=1e-5)  # split children
    # training continues with the edited optimizer
    for n in g.param_names:
        getattr(g, n).grad = torch.ones_like(getattr(g, n))
    opt.step()
    assert dc.grad2d.shape == (g.num_points,) and float(dc.grad2d.sum()) == 0.0


def test_density_cap_reset_state_and_disabled(body):
    g = CanonicalGaussians(body, num_points=20, feature_dim=4, seed=0)
    with torch.no_grad():
        g.log_scales[:] = math.log(0.001)
        g.opacity_logits[:] = 2.0
    opt = _adam_with_state(g)
    off = NoDensityControl(prune_opacity=0.02, refine_every=50)  # what a preset tuned for density control passes
    assert off.step_post_backward(g, opt, _meta(20, list(range(20))), 10, (64, 64)) == {} and g.num_points == 20
    with pytest.raises(TypeError, match="density=off: unknown option.*prune_opacty"):
        NoDensityControl(prune_opacty=0.02)
    dc = DensityControl(refine_start=0, refine_stop=100, refine_every=10, reset_every=5, max_points=24, prune_opacity=0.05)
    dc.step_post_backward(g, opt, _meta(20, list(range(20))), step=3, image_size=(64, 64))
    state = dc.state_dict()
    dc2 = DensityControl(refine_start=0, refine_stop=100, refine_every=10, reset_every=5, max_points=24)
    dc2.load_state_dict(state)
    assert torch.equal(dc2.grad2d, dc.grad2d) and dc2.grad2d.sum() > 0
    stats = dc.step_post_backward(g, opt, _meta(20, list(range(20))), step=10, image_size=(64, 64))
    assert stats["cloned"] == 4 and g.num_points == 24  # capped at max_points
    stats = dc.step_post_backward(g, opt, _meta(24, []), step=15, image_size=(64, 64))
    assert stats.get("reset") == 1 and (g.opacities() <= 0.1 + 1e-6).all()
    assert (opt.state[g.opacity_logits]["exp_avg"] == 0).all()


def test_density_gradient_of_a_multi_image_batch_is_scaled_by_its_images(body):
    """gsplat's rule: the loss is a mean over a batch's images, so a Gaussian seen by V samples (one meta each, as a
    batch of V images renders them) with 1/V of one image's gradient each accumulates what one image gives alone."""
    g = CanonicalGaussians(body, num_points=20, feature_dim=4, seed=0)
    kw = {"refine_start": 0, "refine_stop": 100, "refine_every": 10, "grad_threshold": 2e-4, "prune_opacity": 0.05,
          "grow_scale3d": 0.01, "scene_scale": 1.0, "reset_every": 0, "max_points": 1000}
    one, four = DensityControl(**kw), DensityControl(**kw)
    one.step_post_backward(g, None, _meta(20, [3], 1e-2), step=1, image_size=(64, 48))
    four.step_post_backward(g, None, [_meta(20, [3], 1e-2 / 4) for _ in range(4)], step=1, image_size=(64, 48))
    avg_one = one.grad2d / one.count.clamp_min(1)
    avg_four = four.grad2d / four.count.clamp_min(1)
    assert float(avg_one[3]) > 0 and torch.allclose(avg_four, avg_one, rtol=1e-6), (avg_one[3], avg_four[3])


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

    d = MotionTrendDecoder(cond_dim=8, hidden_dim=16, num_layers=2, feature_dim=4, num_freqs=6)
    assert d.encoding.alpha == 6.0  # a decoder nobody set (a module outside training) sees every band
    sched = Schedule(deform_start=10, deform_anneal=100)
    for step, alpha in ((0, 0.0), (10, 0.0), (60, 3.0), (110, 6.0), (500, 6.0), (None, 6.0)):
        d.set_window(sched.deform_window(step))
        assert d.encoding.alpha == alpha, (step, d.encoding.alpha)
    assert Schedule(deform_anneal=0).deform_window(0) == 1.0  # 0: every band from the start
