"""World-lit shading (`shading=irradiance`): the normal grid, the irradiance map, heading dependence, wiring."""

from __future__ import annotations

import math

import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.model.shading import IrradianceShading, NoShading, vertex_normals
from realityavatar.render import eval_sh
from tests.model.configured import component


def irradiance(**kwargs) -> IrradianceShading:
    """shading=irradiance as configured, with the body's normals (as built) unless a test says otherwise."""
    return component("shading", "irradiance", **{"normals": "body", **kwargs})


@pytest.fixture(scope="module")
def body():
    return instantiate(compose([]).body)


@pytest.fixture(scope="module")
def shading(body):
    s = irradiance(voxel_size=0.04)
    s.init_from_body(body.canonical_vertices().detach(), body.faces)
    return s


def _rot_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_vertex_normals_point_out_of_a_cube():
    v = torch.tensor([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    # 12 triangles, counter-clockwise seen from outside
    f = torch.tensor([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    n = vertex_normals(v, f)
    assert ((n * (v - 0.5)).sum(-1) > 0.5).all()
    assert torch.allclose(n.norm(dim=-1), torch.ones(8))


def test_normal_grid_holds_the_body_normals_near_its_surface(body, shading):
    v = body.canonical_vertices().detach()
    n = vertex_normals(v, body.faces)
    g = torch.Generator().manual_seed(0)
    idx = torch.randperm(v.shape[0], generator=g)[:500]
    looked_up = shading.normals(v[idx] + 0.01 * n[idx])
    cos = torch.nn.functional.cosine_similarity(looked_up, n[idx], dim=-1)
    assert float(cos.median()) > 0.95
    assert float(looked_up.norm(dim=-1).max()) <= 1.0 + 1e-5


def test_zero_coefficients_leave_the_colour_alone(shading):
    x = torch.randn(2, 50, 3) * 0.3
    rot = _rot_y(0.7).expand(2, 50, 3, 3)
    assert torch.allclose(shading(x, rot), torch.ones(2, 50, 3))


def test_same_canonical_gaussian_is_lit_differently_after_the_body_turns(body, shading):
    """The point of the option: the pose features do not see the heading, the light does."""
    s = irradiance(voxel_size=0.04)
    s.load_state_dict(shading.state_dict())
    with torch.no_grad():
        s.coeffs[3] = -3.0  # a degree-1 term (gsplat's band 3 is -C1 x): light from +x
    v = body.canonical_vertices().detach()
    n = vertex_normals(v, body.faces)
    side = (n[:, 0] > 0.95) & (v[:, 1] > v[:, 1].median())  # upper body, facing +x
    x = (v[side] + 0.01 * n[side])[None]
    with torch.no_grad():
        facing, away = (s(x, _rot_y(a).expand(1, x.shape[1], 3, 3)).mean() for a in (0.0, math.pi))
    assert float(facing / away) > 2.0


def test_irradiance_map_fits_a_lambertian_light():
    """Degree-2 log-irradiance holds ambient + diffuse max(0, n.l) (the synthetic scenes' light) to a few percent."""
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1)
    light = torch.nn.functional.normalize(torch.tensor([0.35, 0.82, 0.45]), dim=0)
    target = (0.4 + 0.6 * (n @ light).clamp_min(0))[:, None].expand(-1, 3)
    s = irradiance()
    opt = torch.optim.Adam(s.parameters(), lr=0.05)
    for _ in range(400):
        opt.zero_grad()
        loss = ((s.irradiance(n) - target) ** 2).mean()
        loss.backward()
        opt.step()
    rel = ((s.irradiance(n) - target).abs() / target).mean()
    assert float(rel) < 0.05


def test_shading_sends_no_gradient_to_the_geometry(shading):
    s = irradiance(voxel_size=0.04)
    s.load_state_dict(shading.state_dict())
    x = (torch.randn(1, 20, 3) * 0.2).requires_grad_()
    rot = _rot_y(0.3).expand(1, 20, 3, 3).clone().requires_grad_()
    s(x, rot).sum().backward()
    assert x.grad is None and rot.grad is None
    assert s.coeffs.grad is not None and float(s.coeffs.grad.abs().sum()) > 0


def test_checkpoint_restores_the_normal_grid(shading):
    fresh = irradiance(voxel_size=0.04)
    assert not bool(fresh.built)
    fresh.load_state_dict(shading.state_dict())
    assert bool(fresh.built) and fresh.grid.shape == shading.grid.shape
    x = torch.randn(30, 3) * 0.3
    assert torch.equal(fresh.normals(x), shading.normals(x))


@pytest.mark.parametrize("choice, cls", [("none", NoShading), ("irradiance", IrradianceShading)])
def test_shading_option_composes_instantiates_and_switches_off(choice, cls):
    cfg = compose([f"shading={choice}"])
    s = instantiate(cfg.shading)
    assert isinstance(s, cls)
    if choice == "none":  # a null component: the colour (and SH coefficients) it is given, unchanged
        rgb, sh = torch.rand(1, 3, 3), torch.randn(3, 16, 3)
        assert s.apply(rgb, torch.zeros(1, 3, 3), torch.eye(3).expand(1, 3, 3, 3)) is rgb and bool(s.built)
        assert s.apply_sh(sh, torch.zeros(1, 3, 3)) is sh
    else:
        assert "shading" in cfg.optim.lr


def test_unknown_shading_option_is_refused():
    with pytest.raises(Exception, match="shading"):
        compose(["shading=phong"])


def test_module_builds_the_grid_before_step_0_and_multiplies_the_colour(body):
    """build_module wires the option; on_fit_start fills the grid; shade() = the colour model's rgb x E(n_w)."""
    from realityavatar.build import build_module

    cfg = compose(["gaussians.num_points=300", "shading=irradiance", "skinning=grid"])
    module = build_module(cfg, body, num_train_frames=2, scene_extent=1.0)
    assert isinstance(module.avatar.shading, IrradianceShading) and not bool(module.avatar.shading.built)
    assert "shading" in {g["name"] for g in module.param_groups()}
    module.on_fit_start()
    assert bool(module.avatar.shading.built) and "shading_grid" in module.run_info
    with torch.no_grad():
        module.avatar.shading.coeffs[3] = -2.0
    poses = torch.zeros(1, 3, 24, 3)
    turned = poses.clone()
    turned[..., 0, 1] = math.pi  # the root turned half a circle about the vertical axis
    viewmat = torch.eye(4)[None]
    viewmat[0, 2, 3] = 3.0
    idx = torch.zeros(1, dtype=torch.long)
    with torch.no_grad():
        posed = module.avatar.deform(module.avatar.pose_inputs(poses, torch.zeros(1, 3, 3)))
        rgb = module.avatar.shade(posed, viewmat, idx)
        light = module.avatar.shading(posed["x_e"], posed["rot"])
        posed_turned = module.avatar.deform(module.avatar.pose_inputs(turned, torch.zeros(1, 3, 3)))
        light_turned = module.avatar.shading(posed_turned["x_e"], posed_turned["rot"])
        module.avatar.shading = NoShading()
        base = module.avatar.shade(posed, viewmat, idx)
    assert torch.allclose(rgb, base * light)
    assert not torch.allclose(light, torch.ones_like(light))
    assert (light_turned - light).abs().max() > 0.5  # same canonical Gaussians and pose features, other heading


def test_export_bakes_the_light_of_the_pose(body):
    """What export writes and the viewer streams carries the shading factor of that pose (and none with shading off)."""
    from realityavatar.build import build_module
    from realityavatar.export import gaussians_for_export

    module = build_module(compose(["gaussians.num_points=200", "shading=irradiance"]), body, num_train_frames=2,
                          scene_extent=1.0)
    module.on_fit_start()
    poses, transl = torch.zeros(3, 24, 3), torch.zeros(3, 3)
    plain = gaussians_for_export(module.avatar, poses, transl)["rgb"]  # coefficients 0: E = 1
    with torch.no_grad():
        module.avatar.shading.coeffs[0] = -1.0  # everything darker by exp(-Y_0)
    lit = gaussians_for_export(module.avatar, poses, transl)["rgb"]
    factor = math.exp(-0.28209479177387814)
    assert abs(float((lit / plain.clip(1e-6)).mean()) - factor) < 1e-3
    assert "sh" not in gaussians_for_export(module.avatar) and "rgb" in gaussians_for_export(module.avatar)


def test_grids_share_the_nearest_sample_query_only_for_the_same_voxel_centres(body):
    """diffuse_to_grid reuses the last k-d tree query when the samples and voxels match: a box shifted by less than
    a voxel (same voxel counts, other centres) must not take the cached query."""
    from realityavatar.model import skinning
    from realityavatar.model.skinning import diffuse_to_grid

    v = body.canonical_vertices().detach()
    n = vertex_normals(v.float(), body.faces)
    args = (0.08, 2, 0, 0.1, 400_000)  # voxel 8 cm, k, smooth_iters, smooth_ramp, max_voxels
    a = diffuse_to_grid(v, body.faces, n, args[0], 0.30, *args[1:])[0]
    shifted = diffuse_to_grid(v, body.faces, n, args[0], 0.301, *args[1:])[0]  # same counts, centres 1 mm apart
    assert shifted.shape == a.shape
    skinning._KNN_CACHE.clear()
    fresh = diffuse_to_grid(v, body.faces, n, args[0], 0.301, *args[1:])[0]
    assert torch.equal(shifted, fresh)
    skinning._KNN_CACHE.clear()
    assert torch.equal(diffuse_to_grid(v, body.faces, n, args[0], 0.30, *args[1:])[0], a)


def test_learnt_normals_train_the_grid_and_not_the_geometry(shading):
    """shading.normals=learnt: the photometric gradient reaches the normal grid (and the light map), never x_e or the
    LBS rotation; with the body's normals the grid is not trained."""
    for normals, trained in (("learnt", True), ("body", False)):
        s = irradiance(voxel_size=0.04, normals=normals)
        s.load_state_dict(shading.state_dict())
        with torch.no_grad():
            s.coeffs[1] = -1.0
        x = (torch.randn(1, 20, 3) * 0.2).requires_grad_()
        rot = _rot_y(0.3).expand(1, 20, 3, 3).clone().requires_grad_()
        s(x, rot).sum().backward()
        assert x.grad is None and rot.grad is None
        assert s.coeffs.grad is not None
        assert (s.grid.grad is not None and float(s.grid.grad.abs().sum()) > 0) == trained
        assert ("shading_normals" in s.param_groups()) == trained


def test_learnt_normals_learn_the_normal_the_light_needs(body, shading):
    """Points on the torso's side (body normal horizontal) under a light from above, with a target as bright as an
    upward normal: training the grid alone tilts their looked-up normal up, and it stays at most unit length."""
    s = irradiance(voxel_size=0.04, normals="learnt")
    s.load_state_dict(shading.state_dict())
    with torch.no_grad():
        s.coeffs[1] = -1.0  # band 1 is -C1 y: brighter towards +y
    v = body.canonical_vertices().detach()
    n = vertex_normals(v, body.faces)
    side = (n[:, 1].abs() < 0.2) & (v[:, 1] > v[:, 1].median())  # upper body, normal horizontal
    x = (v[side] + 0.01 * n[side])[:200][None]
    rot = torch.eye(3).expand(1, x.shape[1], 3, 3)
    target = s.irradiance(torch.tensor([[0.0, 1.0, 0.0]])).detach()
    assert float(s.normals(x)[..., 1].median()) < 0.3
    opt = torch.optim.Adam([s.grid], lr=0.05)
    for _ in range(150):
        opt.zero_grad()
        ((s(x, rot) - target) ** 2).mean().backward()
        opt.step()
    looked_up = s.normals(x)
    assert float(looked_up[..., 1].median()) > 0.8
    assert float(looked_up.norm(dim=-1).max()) <= 1.0 + 1e-5


def test_learnt_normal_grid_is_one_parameter_through_build_and_checkpoint(body):
    """The optimizer is built before on_fit_start fills the grid: the grid must stay the same Parameter (its data
    replaced), carry its own learning rate, and load back from a checkpoint of another resolution."""
    from realityavatar.build import build_module

    cfg = compose(["gaussians.num_points=300", "shading=irradiance", "shading.normals=learnt", "skinning=grid"])
    module = build_module(cfg, body, num_train_frames=2, scene_extent=1.0)
    groups = {g["name"]: g for g in module.param_groups()}
    assert groups["shading_normals"]["lr"] == cfg.optim.lr.shading_normals
    grid = module.avatar.shading.grid
    module.on_fit_start()
    assert module.avatar.shading.grid is grid and grid.shape[2:] != (2, 2, 2)
    fresh = instantiate(cfg.shading)
    fresh.load_state_dict(module.avatar.shading.state_dict())
    assert fresh.grid.requires_grad and torch.equal(fresh.grid, module.avatar.shading.grid)
    assert "shading_normals" not in {g["name"] for g in build_module(
        compose(["gaussians.num_points=300", "shading=irradiance", "shading.normals=body"]), body, num_train_frames=2,
        scene_extent=1.0).param_groups()}


def test_lit_sh_coefficients_are_the_lit_colour(shading):
    """apply_sh (export's SH colour in canonical space): along any direction the lit coefficients give the light
    times the colour of the unlit ones."""
    s = irradiance(voxel_size=0.04)
    s.load_state_dict(shading.state_dict())
    with torch.no_grad():
        s.coeffs.normal_(0, 0.3)
    g = torch.Generator().manual_seed(0)
    x_e, sh = torch.randn(1, 40, 3, generator=g) * 0.2, torch.randn(40, 16, 3, generator=g) * 0.3
    d = torch.nn.functional.normalize(torch.randn(1, 40, 3, generator=g), dim=-1)
    with torch.no_grad():
        light = s(x_e, torch.eye(3).expand(1, 40, 3, 3))
        lit = torch.clamp_min(eval_sh(3, s.apply_sh(sh, x_e)[None], d) + 0.5, 0.0)
    assert torch.allclose(lit, light * torch.clamp_min(eval_sh(3, sh[None], d) + 0.5, 0.0), atol=1e-5)
