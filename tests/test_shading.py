"""World-lit shading (`shading=irradiance`): the normal grid, the irradiance map, heading dependence, wiring."""

from __future__ import annotations

import math

import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.model.shading import IrradianceShading, NoShading, vertex_normals


@pytest.fixture(scope="module")
def body():
    return instantiate(compose([]).body)


@pytest.fixture(scope="module")
def shading(body):
    s = IrradianceShading(voxel_size=0.04)
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
    s = IrradianceShading(voxel_size=0.04)
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
    s = IrradianceShading()
    opt = torch.optim.Adam(s.parameters(), lr=0.05)
    for _ in range(400):
        opt.zero_grad()
        loss = ((s.irradiance(n) - target) ** 2).mean()
        loss.backward()
        opt.step()
    rel = ((s.irradiance(n) - target).abs() / target).mean()
    assert float(rel) < 0.05


def test_shading_sends_no_gradient_to_the_geometry(shading):
    s = IrradianceShading(voxel_size=0.04)
    s.load_state_dict(shading.state_dict())
    x = (torch.randn(1, 20, 3) * 0.2).requires_grad_()
    rot = _rot_y(0.3).expand(1, 20, 3, 3).clone().requires_grad_()
    s(x, rot).sum().backward()
    assert x.grad is None and rot.grad is None
    assert s.coeffs.grad is not None and float(s.coeffs.grad.abs().sum()) > 0


def test_checkpoint_restores_the_normal_grid(shading):
    fresh = IrradianceShading(voxel_size=0.04)
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
    if choice == "none":
        assert s(torch.zeros(1, 3, 3), torch.eye(3).expand(1, 3, 3, 3)) is None and bool(s.built)
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
    assert isinstance(module.shading, IrradianceShading) and not bool(module.shading.built)
    assert "shading" in {g["name"] for g in module.param_groups()}
    module.on_fit_start()
    assert bool(module.shading.built) and "shading_grid" in module.run_info
    with torch.no_grad():
        module.shading.coeffs[3] = -2.0
    poses = torch.zeros(1, 3, 24, 3)
    turned = poses.clone()
    turned[..., 0, 1] = math.pi  # the root turned half a circle about the vertical axis
    viewmat = torch.eye(4)[None]
    viewmat[0, 2, 3] = 3.0
    idx = torch.zeros(1, dtype=torch.long)
    with torch.no_grad():
        posed = module.deform(poses, torch.zeros(1, 3, 3))
        rgb = module.shade(posed, viewmat, idx)
        light = module.shading(posed["x_e"], posed["rot"])
        posed_turned = module.deform(turned, torch.zeros(1, 3, 3))
        light_turned = module.shading(posed_turned["x_e"], posed_turned["rot"])
        module.shading = NoShading()
        base = module.shade(posed, viewmat, idx)
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
    plain = gaussians_for_export(module, poses, transl)["rgb"]  # coefficients 0: E = 1
    with torch.no_grad():
        module.shading.coeffs[0] = -1.0  # everything darker by exp(-Y_0)
    lit = gaussians_for_export(module, poses, transl)["rgb"]
    factor = math.exp(-0.28209479177387814)
    assert abs(float((lit / plain.clip(1e-6)).mean()) - factor) < 1e-3
    assert "sh" not in gaussians_for_export(module) and "rgb" in gaussians_for_export(module)


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


def test_jacobian_normals_follow_a_linear_field_and_keep_their_length():
    """normals=jacobian: a field x -> x + A x turns a normal n into cof(I + A) n (= F^-T n up to its length), and the
    result keeps |n_c| (short normals stay short)."""
    from realityavatar.model.shading import deformed_normals

    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 3, generator=g) * 0.3
    x = torch.randn(40, 3, generator=g)
    n = torch.nn.functional.normalize(torch.randn(40, 3, generator=g), dim=-1) * torch.rand(40, 1, generator=g)

    def field(p):
        return (p @ A.T)[None]

    out = deformed_normals(n, x, field(x), field, 0.005)[0]
    F_ = torch.eye(3) + A
    ref = (torch.linalg.inv(F_).T @ n.T).T * torch.sign(torch.det(F_))
    ref = torch.nn.functional.normalize(ref, dim=-1) * n.norm(dim=-1, keepdim=True)
    assert torch.allclose(out, ref, atol=1e-4)
    assert torch.allclose(deformed_normals(n, x, torch.zeros(1, 40, 3), lambda p: torch.zeros(1, len(p), 3), 0.005)[0], n)


def test_jacobian_normals_tilt_up_on_a_flaring_skirt():
    """The point of the option: a cylinder of cloth whose radius grows with the depth below its waist (a skirt's
    flare) has normals that tilt up, by the cone's angle; the body normal (horizontal) would not see it."""
    from realityavatar.model.shading import deformed_normals

    phi = torch.linspace(0, 2 * math.pi, 33)[:-1]
    y = torch.linspace(-0.5, -0.1, 5)
    P, Y = torch.meshgrid(phi, y, indexing="ij")
    radial = torch.stack([torch.cos(P), torch.zeros_like(P), torch.sin(P)], -1).reshape(-1, 3)
    x = 0.15 * radial + torch.stack([torch.zeros_like(Y), Y, torch.zeros_like(Y)], -1).reshape(-1, 3)
    k = 1.0  # radius grows 1 m per metre below y = 0: a 45° cone

    def flare(p):
        r = torch.nn.functional.normalize(p * torch.tensor([1.0, 0.0, 1.0]), dim=-1)
        return (k * (-p[:, 1:2]) * r)[None]

    n = deformed_normals(radial, x, flare(x), flare, 0.001)[0]
    assert torch.allclose(n[:, 1], torch.full((len(n),), math.sin(math.pi / 4)), atol=2e-3)  # tilted up by 45°
    assert float((n * radial).sum(-1).min()) > 0.7  # still outward


def test_jacobian_normals_in_the_module_send_no_gradient_and_change_the_light(body):
    """build_module with shading.normals=jacobian: the normals start as the body's at x_c (the decoder starts at the
    identity), a decoder that flares changes the light, and no gradient reaches the geometry through it."""
    from realityavatar.build import build_module

    cfg = compose(["gaussians.num_points=300", "shading=irradiance", "shading.normals=jacobian", "skinning=grid"])
    module = build_module(cfg, body, num_train_frames=2, scene_extent=1.0)
    module.on_fit_start()
    with torch.no_grad():
        module.shading.coeffs[1] = -1.0  # light from above (band 1 is -C1 y)
    poses, transl = torch.zeros(1, 3, 24, 3), torch.zeros(1, 3, 3)
    posed = module.deform(poses, transl)
    x_c = module.gaussians.means.detach()
    assert torch.allclose(posed["n_c"][0], module.shading.normals(x_c), atol=1e-3)
    with torch.no_grad():  # a decoder whose Δx flares: out bias 0, weight so that Δx grows with -y of its input
        out = module.deformer.out
        out.weight[:3].normal_(0, 0.05)
    posed = module.deform(poses, transl)
    assert (posed["n_c"][0] - module.shading.normals(x_c)).norm(dim=-1).max() > 0.05
    light = module.shading(posed["x_e"], posed["rot"], posed["n_c"])
    light.sum().backward()
    assert module.gaussians.means.grad is None and module.deformer.out.weight.grad is None
    assert module.shading.coeffs.grad is not None
    with pytest.raises(ValueError, match="shading.normals"):
        IrradianceShading(normals="mesh")


def test_learnt_normals_train_the_grid_and_not_the_geometry(shading):
    """shading.normals=learnt: the photometric gradient reaches the normal grid (and the light map), never x_e or the
    LBS rotation; with the body's normals the grid is not trained."""
    for normals, trained in (("learnt", True), ("body", False)):
        s = IrradianceShading(voxel_size=0.04, normals=normals)
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
    s = IrradianceShading(voxel_size=0.04, normals="learnt")
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
    grid = module.shading.grid
    module.on_fit_start()
    assert module.shading.grid is grid and grid.shape[2:] != (2, 2, 2)
    fresh = instantiate(cfg.shading)
    fresh.load_state_dict(module.shading.state_dict())
    assert fresh.grid.requires_grad and torch.equal(fresh.grid, module.shading.grid)
    assert "shading_normals" not in {g["name"] for g in build_module(
        compose(["gaussians.num_points=300", "shading=irradiance", "shading.normals=body"]), body, num_train_frames=2,
        scene_extent=1.0).param_groups()}


def test_normal_residuals_light_coincident_gaussians_apart(shading):
    """gaussians.normal_residual: two Gaussians at one canonical place (a skirt's and the thigh's under it) share the
    grid's normal; with different residuals they are lit differently, the residuals (not the geometry) get the
    gradient, and the summed normal stays at most unit length."""
    s = IrradianceShading(voxel_size=0.04, normals="body")
    s.load_state_dict(shading.state_dict())
    with torch.no_grad():
        s.coeffs[1] = -1.0  # brighter towards +y
    x = torch.tensor([[[0.1, 0.2, 0.05], [0.1, 0.2, 0.05]]], requires_grad=True)
    rot = torch.eye(3).expand(1, 2, 3, 3)
    same = s(x, rot)
    assert torch.allclose(same[0, 0], same[0, 1])
    r = torch.tensor([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], requires_grad=True)
    lit = s(x, rot, residual=r)
    assert torch.allclose(lit[0, 0], same[0, 0]) and float(lit[0, 1].mean()) > float(lit[0, 0].mean()) + 0.1
    lit.sum().backward()
    assert x.grad is None and float(r.grad.abs().sum()) > 0
    n = s.normals(x.detach()) + r.detach()
    assert float((n / n.norm(dim=-1, keepdim=True).clamp_min(1.0)).norm(dim=-1).max()) <= 1.0 + 1e-6


def test_normal_residuals_train_follow_density_control_and_reload(scenes_root, tmp_path):
    """A short run with gaussians.normal_residual=true (density control on, a garment sheet beside): the residuals
    train, stay one row per free Gaussian, have their own optimizer group and reload; refused without a light's
    normal."""
    from realityavatar.build import build_data, build_module, load_run
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    over = ["data=synthetic_ci", "trainer=ci", "iterations=30", "gaussians.num_points=800", "test_after_fit=false",
            "logger=none", "gaussians.normal_residual=true", "density.refine_start=5", "density.refine_every=5",
            "density.grad_threshold=0.0", "sheet=skirt", "sheet.rows=4", "sheet.cols=12", "sheet.per_cell=2"]
    cfg, choices = prepare_run(compose(over), tmp_path / "run")
    run(cfg, choices)
    _, module, _ = load_run(tmp_path / "run")
    g = module.gaussians
    assert g.num_points != 800 and g.normal_residuals.shape == (g.num_points, 3)
    assert module.sheet is not None and module.sheet.num_points == 96  # its Gaussians are lit without residuals
    assert float(g.normal_residuals.abs().max()) > 1e-4
    groups = {grp["name"]: grp for grp in module.param_groups()}
    assert groups["normal_residuals"]["lr"] == cfg.optim.lr.normal_residuals
    assert not compose([]).gaussians.normal_residual  # off by default
    bad = compose(over[:1] + ["gaussians.normal_residual=true", "shading=none"])
    body = instantiate(bad.body)
    dm = build_data(bad, body)
    with pytest.raises(ValueError, match="gaussians.normal_residual=true.*shading=irradiance"):
        build_module(bad, body, dm.num_train_frames, dm.scene_extent, data=dm)
