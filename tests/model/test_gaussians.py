"""Canonical Gaussians: surface sampling, initialisation, a checkpoint with another count."""

from __future__ import annotations

import pytest
import torch

from realityavatar.geometry import (
    sample_surface,
)
from realityavatar.model.gaussians import PARAM_NAMES
from tests.fixtures_data import RandomBody
from tests.model.configured import component


@pytest.fixture(scope="module")
def body() -> RandomBody:
    return RandomBody(seed=3, pelvis=(0.0, 0.0, 0.0), spread=0.15)


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
    g = component("gaussians", body=body, num_points=300, feature_dim=8, init_opacity=0.1, seed=1)
    assert g.num_points == 300
    shapes = {n: tuple(getattr(g, n).shape) for n in PARAM_NAMES}
    assert shapes == {"means": (300, 3), "log_scales": (300, 3), "quats": (300, 4), "opacity_logits": (300,), "features": (300, 8)}
    assert torch.allclose(g.opacities(), torch.full((300,), 0.1), atol=1e-6)
    assert torch.equal(g.quats, torch.tensor([1.0, 0, 0, 0]).expand(300, 4))  # identity rotations (wxyz)
    assert (g.scales() > 0).all() and g.init_scale < 0.05
    # on the canonical surface: every point lies near a (canonical-pose) joint of its tetrahedron
    Jc = body.joints(body.canonical_pose())
    d = torch.cdist(g.means.detach(), Jc).min(-1).values
    assert (d < 0.06).all()
    assert torch.equal(g.means, component("gaussians", body=body, num_points=300, feature_dim=8, seed=1).means)
    assert set(g.param_groups()) == set(PARAM_NAMES)


def test_checkpoint_with_other_count_resizes(body):
    small = component("gaussians", body=body, num_points=50, feature_dim=4, seed=0)
    big = component("gaussians", body=body, num_points=120, feature_dim=4, seed=2)
    wrapper = torch.nn.Module()
    wrapper.gaussians = big
    wrapper.load_state_dict({f"gaussians.{k}": v for k, v in small.state_dict().items()})
    assert wrapper.gaussians.num_points == 50
    for n in PARAM_NAMES:
        assert torch.equal(getattr(wrapper.gaussians, n), getattr(small, n))
