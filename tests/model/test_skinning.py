"""Skinning: the MLP field and its pre-fit, the grid built from the body, LBS, where the weights are read."""

from __future__ import annotations

import math

import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.geometry import (
    axis_angle_to_matrix,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    rigid,
    sample_surface,
)
from realityavatar.model.skinning import lbs_gaussians, pretrain_skinning, skinning_loss
from tests.fixtures_data import RandomBody
from tests.helpers import assert_all_grads
from tests.model.configured import component


@pytest.fixture(scope="module")
def body() -> RandomBody:
    return RandomBody(seed=3, pelvis=(0.0, 0.0, 0.0), spread=0.15)


def test_skinning_field_softmax_and_loss_grads(body):
    field = component("skinning", "mlp", "skinning.hidden_dim=32", "skinning.num_layers=2")
    x = torch.randn(4, 50, 3)
    w = field(x)
    assert w.shape == (4, 50, 24)
    assert torch.allclose(w.sum(-1), torch.ones(4, 50), atol=1e-5) and (w >= 0).all()
    pts, tw = sample_surface(body.rest_vertices, body.faces, body.skin_weights, 64, torch.Generator().manual_seed(0))
    skinning_loss(field, pts, tw).backward()
    assert_all_grads(field)


def test_pretrain_skinning_lowers_loss(body):
    torch.manual_seed(0)
    field = component("skinning", "mlp", "skinning.hidden_dim=32", "skinning.num_layers=2")
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


def test_skinning_grid_follows_the_body_and_blends_between_the_legs():
    """Built from the body: on the surface it reproduces the body's dominant bone about as well as the MLP's pre-fit
    does; half-way between the two thighs a point takes both thighs' weights (the MLP's nearest-side weights tear
    a skirt apart there); gradients reach the query positions; a checkpoint restores the grid's shape and box."""
    from realityavatar.body import build_body
    from realityavatar.geometry import sample_surface
    body = build_body("mannequin")
    v = body.canonical_vertices().detach()
    grid = component("skinning", "grid", "skinning.voxel_size=0.04")
    info = grid.init_from_body(v, body.faces, body.skin_weights)
    p, w = sample_surface(v, body.faces, body.skin_weights, 5000, torch.Generator().manual_seed(1))
    with torch.no_grad():
        pred = grid(p)
    assert torch.allclose(pred.sum(-1), torch.ones(len(p)), atol=1e-5)
    assert (pred.argmax(-1) == w.argmax(-1)).float().mean() > 0.85
    assert info["surface_fit"] < 0.2
    # between the knees: left and right thigh/knee joints (SMPL 1/4 left, 2/5 right) share the weight
    j = body.joints(body.canonical_pose()).detach()
    mid = ((j[4] + j[5]) / 2 + (j[1] + j[2]) / 2) / 2  # between the thighs, half-way down
    wm = grid(mid[None])[0]
    left, right = float(wm[[1, 4]].sum()), float(wm[[2, 5]].sum())
    assert left > 0.25 and right > 0.25, (left, right)
    x = p[:10].clone().requires_grad_()
    g = torch.randn(10, 24, generator=torch.Generator().manual_seed(2))
    (grid(x) * g).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    fresh = component("skinning", "grid", "skinning.voxel_size=0.04")
    fresh.load_state_dict(grid.state_dict())
    assert torch.equal(fresh(p[:50]), grid(p[:50]).detach())
    # stored channels last (a lookup reads each corner's 24 weights together): the same values and gradients as the
    # plain layout
    assert grid.grid.is_contiguous(memory_format=torch.channels_last_3d) and fresh.grid.stride() == grid.grid.stride()
    plain = component("skinning", "grid", "skinning.voxel_size=0.04")
    plain.load_state_dict(grid.state_dict())
    plain.grid.data = plain.grid.data.contiguous()
    x2 = p[:10].clone().requires_grad_()
    (plain(x2) * g).sum().backward()
    assert torch.equal(plain(p[:50]), grid(p[:50]).detach()) and torch.equal(x2.grad, x.grad)


@pytest.mark.parametrize("query", ["AtDeformed", "AtCanonical"])
def test_skinning_query_reads_the_weights_where_it_says(scenes_root, query):
    """skinning.query: AtDeformed reads each point's weights at x_c + dx (3DGS-Avatar), AtCanonical at x_c, so a
    point the decoder moves 40 cm keeps the bones it was laid out on."""
    from torch.utils.data import default_collate

    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=200",
                   f"skinning.query._target_=realityavatar.model.skinning.{query}"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    assert type(module.avatar.skinning.query).__name__ == query
    module.avatar.skinning.init_from_body(body.canonical_vertices().detach(), body.faces, body.skin_weights, steps=0)
    forward = module.avatar.deformer.forward

    def far(*args, **kwargs):  # the decoder moves every point 40 cm along x
        out = forward(*args, **kwargs)
        return {**out, "dx": out["dx"] + torch.tensor([0.4, 0.0, 0.0])}

    module.avatar.deformer.forward = far
    b = default_collate([dm.datasets["train"][0]])
    with torch.no_grad():
        posed = module.avatar.deform(b)
        at_rest, moved = module.avatar.skinning(module.avatar.gaussians.means), module.avatar.skinning(posed["x_e"][0])
    expected, other = (at_rest, moved) if query == "AtCanonical" else (moved, at_rest)
    assert torch.allclose(posed["weights"][0], expected, atol=1e-6)
    assert (posed["weights"][0] - other).abs().max() > 0.1


def test_grid_query_finds_the_neighbours_of_scipys_default_tree(monkeypatch):
    """The body grids' nearest-sample query uses a sliding-midpoint k-d tree (7x faster far from the body): the same
    neighbours as scipy's default tree, so the grid is the same bit for bit."""
    from scipy.spatial import cKDTree

    from realityavatar.body import build_body
    from realityavatar.model import skinning

    body = build_body("mannequin")
    v = body.canonical_vertices().detach()

    def build():
        skinning._KNN_CACHE.clear()
        return skinning.diffuse_to_grid(v, body.faces, body.skin_weights, 0.08, 0.3, 8, 2, 0.1, 400_000)[0]

    grid = build()
    monkeypatch.setattr("scipy.spatial.cKDTree", lambda pts, **kw: cKDTree(pts))  # scipy's default tree
    assert torch.equal(build(), grid)
    skinning._KNN_CACHE.clear()
