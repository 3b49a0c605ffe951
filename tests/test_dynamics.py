"""Garment-motion mechanisms: silhouette chamfer, hull-seeded Gaussians, deformation graph, history dependence."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.losses import NoSilhouette, SilhouetteChamfer, mask_distance, project_points
from realityavatar.model.deform import NodeDeformer, apply_deformation


def _camera(H: int = 32):
    K = torch.tensor([[float(H), 0.0, H / 2], [0.0, float(H), H / 2], [0.0, 0.0, 1.0]])
    E = torch.eye(4)
    E[2, 3] = 2.0  # camera 2 m in front of the origin, looking down +z
    return K, E


def test_mask_distance_is_euclidean():
    m = torch.zeros(9, 9)
    m[4, 4] = 1
    d = mask_distance(m)
    assert d[4, 4] == 0 and d[4, 7] == pytest.approx(3.0) and d[0, 0] == pytest.approx(np.hypot(4, 4))


def test_outside_term_pulls_a_gaussian_whose_footprint_misses_the_mask():
    """A centre 10 px left of the mask (no footprint overlap) gets a gradient towards the mask."""
    H = 32
    K, E = _camera(H)
    mask = torch.zeros(H, H, 1)
    mask[10:22, 20:30] = 1
    alpha = mask.clone()  # everything covered: only the outside term acts
    x = torch.tensor([[(10 - H / 2) * 2.0 / H, (16 - H / 2) * 2.0 / H, 0.0]], requires_grad=True)  # projects to (10,16)
    uv, _ = project_points(x, E, K)
    assert torch.allclose(uv, torch.tensor([[10.0, 16.0]]), atol=1e-4)
    loss_fn = SilhouetteChamfer(weight=1.0)
    terms = loss_fn(x, E, K, mask, alpha)
    assert float(terms["sil_outside"]) == pytest.approx((10 / H) ** 2, rel=0.05)
    assert float(terms["sil_coverage"]) == 0.0
    loss_fn.total(terms).backward()
    assert x.grad[0, 0] < 0  # descending the loss moves +x, towards the mask
    assert abs(float(x.grad[0, 1])) < abs(float(x.grad[0, 0])) * 0.2


def test_coverage_term_pulls_the_nearest_centre_to_uncovered_mask_pixels():
    H = 32
    K, E = _camera(H)
    mask = torch.zeros(H, H, 1)
    mask[14:18, 24:28] = 1  # a flared hem nobody covers
    alpha = torch.zeros(H, H, 1)
    x = torch.tensor([[0.0, 0.0, 0.0], [-0.5, 0.0, 0.0]], requires_grad=True)  # project to (16,16) and (8,16)
    mask_in = mask.clone()
    mask_in[16, 16] = 1  # keep both centres' outside term small: only coverage should move them
    mask_in[16, 8] = 1
    terms = SilhouetteChamfer(weight=1.0, outside_weight=0.0)(x, E, K, mask_in, alpha)
    assert float(terms["sil_coverage"]) > 0
    SilhouetteChamfer(weight=1.0, outside_weight=0.0).total(terms).backward()
    assert x.grad[0, 0] < 0, "the nearest centre must be pulled towards the uncovered pixels (+x)"
    assert float(x.grad[1].abs().sum()) == 0.0, "a farther centre is not the nearest to any uncovered pixel"


def test_no_silhouette_is_off():
    assert NoSilhouette()(torch.zeros(3, 3), torch.eye(4), torch.eye(3), torch.ones(4, 4, 1), torch.ones(4, 4, 1)) == {}


def test_node_deformer_starts_at_identity_and_moves_neighbourhoods_coherently():
    torch.manual_seed(0)
    d = NodeDeformer(num_nodes=32, k=4, cond_dim=8, encoding="frequency")
    x = torch.rand(400, 3)
    h = torch.randn(1, 8)
    out = d(x, h)
    xe, _, q = apply_deformation(x, torch.zeros(400, 3), torch.tensor([1.0, 0, 0, 0]).expand(400, 4), out)
    assert torch.allclose(xe[0], x, atol=1e-6) and torch.allclose(q[0, :, 0], torch.ones(400), atol=1e-6)
    with torch.no_grad():
        d.out.bias[:3] += torch.tensor([0.1, 0.0, 0.0])  # every node translates 10 cm along x
    out = d(x, h)
    assert torch.allclose(out["dx"][0], torch.tensor([0.1, 0.0, 0.0]).expand(400, 3), atol=1e-5)
    # One node's translation moves its neighbourhood, not far-away Gaussians.
    node_out = {"dx": torch.zeros(1, 32, 3), "ds": torch.zeros(1, 32, 3), "f_mt": torch.zeros(1, 32, d.feature_dim),
                "dq": torch.tensor([1.0, 0, 0, 0]).expand(1, 32, 4)}
    node_out["dx"][0, 0, 0] = 0.1
    moved = d.blend(x, node_out)["dx"][0]
    dist = (x - d.nodes[0]).norm(dim=-1)
    near, far = dist.argsort()[:5], dist.argsort()[-50:]
    assert moved[near, 0].min() > 0.03 and moved[far].abs().max() < 1e-6


def test_node_deformer_nodes_are_saved_with_the_checkpoint():
    d = NodeDeformer(num_nodes=16, k=2, cond_dim=4, encoding="frequency")
    d(torch.rand(100, 3), torch.zeros(1, 4))
    e = NodeDeformer(num_nodes=16, k=2, cond_dim=4, encoding="frequency")
    e.load_state_dict(d.state_dict())
    assert bool(e.nodes_fitted) and torch.equal(e.nodes, d.nodes) and float(e.sigma) == float(d.sigma)


@pytest.mark.parametrize("group,on,off", [("silhouette", "chamfer", "none"), ("gaussians", "hull", "default"),
                                          ("deformer", "motion_trend_nodes", "motion_trend"), ("skinning", "grid", "mlp")])
def test_each_mechanism_composes_and_switches_off(group, on, off):
    from realityavatar.body import build_body

    body = build_body("mannequin")
    for opt in (on, off):
        cfg = compose([f"{group}={opt}", "gaussians.num_points=200"])
        kw = {"body": body} if group == "gaussians" else {}
        obj = instantiate(cfg[group], **kw)
        name = type(obj).__name__
        assert (name in ("SilhouetteChamfer", "HullGaussians", "NodeDeformer", "SkinningGrid")) == (opt == on), \
            (group, opt, name)


def test_hull_gaussians_seed_the_garment_from_the_masks(scenes_root):
    """On the ci scene (a skirt), garment Gaussians lie away from the body and project inside every training mask."""
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "gaussians=hull", "gaussians.num_points=2000", "trainer=ci"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    g = module.gaussians
    n_g = g.num_garment_points
    assert n_g == 600, n_g
    from realityavatar.model.hull import hull_views

    views = hull_views(dm)
    A = body.canonical_transforms(views.pose, views.transl)
    # Posed by the nearest body vertex's weights, as they were canonicalised.
    from scipy.spatial import cKDTree

    can = body.canonical_vertices().detach().numpy()
    _, nearest = cKDTree(can).query(g.means.detach()[-n_g:].numpy())
    T = torch.einsum("nj,jab->nab", body.skin_weights[torch.from_numpy(nearest)], A)
    posed = (T[:, :3, :3] @ g.means.detach()[-n_g:, :, None]).squeeze(-1) + T[:, :3, 3]
    body_posed = body.posed_vertices(views.pose, views.transl).numpy()
    dist, _ = cKDTree(body_posed).query(posed.numpy())
    assert np.median(dist) > 0.02, "garment seeds should not sit on the body"
    inside = []
    for mask, K, E in zip(views.masks, views.Ks, views.viewmats):
        uv, _ = project_points(posed.double(), torch.from_numpy(E), torch.from_numpy(K))
        u, v = uv[:, 0].round().long().clamp(0, mask.shape[1] - 1), uv[:, 1].round().long().clamp(0, mask.shape[0] - 1)
        inside.append(torch.from_numpy(mask)[v, u].float().mean())
    assert min(inside) > 0.9, inside


@pytest.mark.parametrize("temporal", ["lstm", "none"])
def test_trained_model_depends_on_motion_history(scenes_root, tmp_path, temporal):
    """Same current pose, different histories (standing vs spinning into it): a trained LSTM model poses the
    Gaussians differently; the w/o-LSTM model cannot (its output is a function of the current frame only)."""
    from realityavatar.build import load_run
    from realityavatar.config import prepare_run
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
    from realityavatar.train import run

    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=30", f"temporal={temporal}",
                                        "gaussians.num_points=800", "test_after_fit=false", "logger=none"]),
                               tmp_path / "run")
    run(cfg, choices)
    _, module, _ = load_run(tmp_path / "run")
    T = module.run_info.get("window_len", 6)
    still = torch.zeros(1, T, 24, 3)
    transl = torch.zeros(1, T, 3)
    yaw = torch.linspace(-3.0, 0.0, T)  # spinning about the vertical axis, arriving at the same final pose
    spin = still.clone()
    spin[0, :, 0] = matrix_to_axis_angle(axis_angle_to_matrix(torch.stack([torch.zeros(T), yaw, torch.zeros(T)], -1)))
    with torch.no_grad():
        a = module.deform(still, transl)["means"]
        b = module.deform(spin, transl)["means"]
    diff = (a - b).norm(dim=-1)
    # 30 CPU steps move the zero-initialised decoder output only a little (~1e-5 m here); the sweep-scale effect is
    # measured by ablations/probe.py. What must hold: with an LSTM the history moves every Gaussian, without it none.
    if temporal == "none":
        assert float(diff.max()) == 0.0
    else:
        assert float(diff.min()) > 1e-7 and float(diff.mean()) > 2e-6, f"history moved the Gaussians {float(diff.mean()):.2e} m"


def test_nearest_index_matches_the_dense_argmin():
    from realityavatar.losses import nearest_index

    g = torch.Generator().manual_seed(0)
    pts, q = torch.rand(3000, 2, generator=g) * 128, torch.rand(500, 2, generator=g) * 128
    assert torch.equal(nearest_index(q, pts), torch.cdist(q.double(), pts.double()).argmin(1))


def test_skinning_grid_follows_the_body_and_blends_between_the_legs():
    """Built from the body: on the surface it reproduces the body's dominant bone about as well as the MLP's pre-fit
    does; half-way between the two thighs a point takes both thighs' weights (the MLP's nearest-side weights tear
    a skirt apart there); gradients reach the query positions; a checkpoint restores the grid's shape and box."""
    from realityavatar.body import build_body
    from realityavatar.geometry import sample_surface
    from realityavatar.model.skinning import SkinningGrid

    body = build_body("mannequin")
    v = body.canonical_vertices().detach()
    grid = SkinningGrid(voxel_size=0.04)
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
    (grid(x) * torch.randn(10, 24)).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    fresh = SkinningGrid(voxel_size=0.04)
    fresh.load_state_dict(grid.state_dict())
    assert torch.equal(fresh(p[:50]), grid(p[:50]).detach())


def test_coverage_density_clones_the_gaussians_uncovered_pixels_pull(scenes_root):
    """density=coverage: the Gaussians the silhouette chamfer's uncovered mask pixels pulled at least coverage_min
    times since the last refine are cloned (the most pulled first, at most coverage_clones), the rest are not."""
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300", "density=coverage",
                   "density.coverage_clones=3", "density.coverage_min=3", "density.grad_threshold=1e9",
                   "density.prune_opacity=0.0"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    d, g = module.density, module.gaussians
    # The chamfer reports which Gaussians uncovered pixels pulled: a mask nothing covers pulls some of them.
    K, E = _camera(32)
    mask = torch.zeros(32, 32, 1)
    mask[4:12, 4:12] = 1
    module.silhouette(g.means.detach(), E, K, mask, torch.zeros(32, 32, 1))
    assert module.silhouette.last_pulled is not None and module.silhouette.last_pulled.numel() == 64
    pulled = torch.tensor([7, 7, 7, 7, 7, 42, 42, 42, 99, 99, 5])  # 7: 5x, 42: 3x, 99: 2x, 5: 1x
    d.observe_coverage(pulled, g.num_points)
    d.grad2d, d.count = torch.zeros(300), torch.zeros(300)
    before = g.means.detach().clone()
    stats = d.refine(g, None, step=100)
    assert stats["coverage_cloned"] == 2 and g.num_points == 302
    assert torch.equal(g.means.detach()[300], before[7]) and torch.equal(g.means.detach()[301], before[42])
    assert float(d.demand.sum()) == 0.0 and d.demand.shape[0] == 302
    assert int(compose(["density=coverage"]).density.coverage_min) >= 1


def test_one_frame_from_several_cameras_is_deformed_once(scenes_root):
    """A frame_views batch (one pose window, several cameras) runs the networks once: the posed Gaussians of every
    sample equal deform() of that window alone, and the parameters' gradient is the sum over the samples."""
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    torch.manual_seed(0)
    for p in module.deformer.parameters():  # the decoder starts at zero output: give it something to move
        p.data.normal_(0.0, 0.05)
    J = body.joints(body.canonical_pose()[None])[0]  # the decoder's vertical axis (offsets=cylindrical)
    assert torch.allclose(module.deformer.axis_origin, J[0])
    assert torch.allclose(module.deformer.axis_dir, torch.nn.functional.normalize(J[12] - J[0], dim=0))
    T = module.run_info.get("window_len", 6)
    poses = 0.3 * torch.randn(1, T, 24, 3)
    transl = torch.randn(1, T, 3) * 0.1
    calls = []
    hook = module.deformer.register_forward_hook(lambda m, i, o: calls.append(i[1].shape[0]))
    one = module.deform(poses, transl)
    shared = module.deform_shared(poses.expand(3, -1, -1, -1), transl.expand(3, -1, -1))
    hook.remove()
    assert calls == [1, 1], calls
    assert shared["B"] == 3 and shared["means"].shape[0] == 3
    for k in ("means", "quats", "scales", "rot", "weights", "x_e"):
        assert torch.equal(shared[k][2], one[k][0]), k
    # two different windows are deformed separately
    other = torch.cat([poses, poses + 0.1])
    both = module.deform_shared(other, transl.expand(2, -1, -1))
    assert not torch.equal(both["means"][0], both["means"][1])
    # gradients: three samples sharing one pass = three times one sample's
    w = next(module.deformer.parameters())
    g1 = torch.autograd.grad(module.deform(poses, transl)["means"].sum(), w)[0]
    g3 = torch.autograd.grad(module.deform_shared(poses.expand(3, -1, -1, -1), transl.expand(3, -1, -1))["means"].sum(),
                             w)[0]
    err = float((g3 - 3 * g1).abs().max() / (3 * g1).abs().max())
    assert err < 1e-5, err


def test_cylindrical_offsets_turn_and_flare_about_the_body_axis():
    """deformer.offsets=cylindrical: (dr, dtheta, dh) move a point to radius r + dr, azimuth phi + dtheta and height
    h + dh about the axis, the Gaussian's rotation turns by dtheta; zero outputs are the identity; the option composes
    and a wrong value is refused. (The module's axis, pelvis towards neck: test_one_frame_from_several_cameras_...)"""
    from realityavatar.geometry import quat_to_matrix
    from realityavatar.model.deform import MotionTrendDecoder

    d = MotionTrendDecoder(cond_dim=8, encoding="frequency", hidden_dim=16, num_layers=2, feature_dim=4,
                           offsets="cylindrical")
    d.set_axis(torch.tensor([1.0, 0.0, 2.0]), torch.tensor([0.0, 2.0, 0.0]))  # vertical (y) axis through x=1, z=2
    x = torch.tensor([[1.5, 0.3, 2.0], [1.0, -0.2, 1.0]])  # r = 0.5 at phi = 0 (+x); r = 1 towards -z
    o = torch.tensor([[[0.1, math.pi / 2, 0.05], [0.0, math.pi, -0.1]]])
    dx, twist = d._cylindrical(x, o)
    moved = x + dx[0]
    # +x turned by +90 deg about +y goes to -z: radius 0.6; -z turned by 180 deg goes to +z
    assert torch.allclose(moved[0], torch.tensor([1.0, 0.35, 2.0 - 0.6]), atol=1e-6), moved[0]
    assert torch.allclose(moved[1], torch.tensor([1.0, -0.3, 3.0]), atol=1e-6), moved[1]
    R = quat_to_matrix(twist[0, 0])
    assert torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)
    out = d(x, torch.zeros(1, 8))  # zero-initialised output rows: the identity
    assert float(out["dx"].abs().max()) == 0.0
    assert torch.allclose(out["dq"], torch.tensor([1.0, 0.0, 0.0, 0.0]).expand_as(out["dq"]))
    with torch.no_grad():
        d.out.bias[1] = math.pi / 2  # every Gaussian swirls a quarter turn: its rotation turns with it
    out = d(x, torch.zeros(1, 8))
    R = quat_to_matrix(out["dq"][0, 0])
    assert torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)
    assert torch.allclose((x + out["dx"][0])[1], torch.tensor([0.0, -0.2, 2.0]), atol=1e-6)
    cfg = compose(["deformer.offsets=cylindrical"])
    dec = instantiate(cfg.deformer)
    assert dec.offsets == "cylindrical"
    with pytest.raises(ValueError, match="deformer.offsets"):
        MotionTrendDecoder(offsets="polar")


def test_gaussian_codes_let_coincident_gaussians_move_apart():
    """gaussians.deform_code_dim / deformer.gaussian_code_dim: two Gaussians at the same canonical position with
    different codes get different offsets (the position encoding alone cannot separate them); the decoder starts at
    the identity, refuses missing or mis-sized codes, the config keeps both sizes in step, and the deformation graph
    refuses per-Gaussian codes."""
    from realityavatar.model.deform import MotionTrendDecoder

    d = MotionTrendDecoder(cond_dim=8, encoding="frequency", hidden_dim=16, num_layers=2, feature_dim=4,
                           gaussian_code_dim=3, auto_bounds=False)
    x = torch.tensor([[0.1, 0.2, 0.3], [0.1, 0.2, 0.3]])
    codes = torch.tensor([[0.5, -0.2, 0.1], [-0.4, 0.3, 0.0]], requires_grad=True)
    h = torch.randn(2, 8)
    assert float(d(x, h, codes=codes)["dx"].detach().abs().max()) == 0.0  # zero-initialised output rows: the identity
    with torch.no_grad():
        d.out.weight.normal_(0.0, 0.5)
    out = d(x, h, codes=codes)
    assert float((out["dx"][:, 0] - out["dx"][:, 1]).norm(dim=-1).min()) > 1e-4
    out["dx"].sum().backward()
    assert float(codes.grad.abs().sum()) > 0  # the codes are learnt through the offsets
    d0 = MotionTrendDecoder(cond_dim=8, encoding="frequency", hidden_dim=16, num_layers=2, feature_dim=4,
                            auto_bounds=False)
    with torch.no_grad():
        d0.out.weight.normal_(0.0, 0.5)
    same = d0(x, h)["dx"]
    assert torch.allclose(same[:, 0], same[:, 1], atol=1e-6)  # without codes: one offset per position
    with pytest.raises(ValueError, match="gaussian_code_dim=3 needs codes"):
        d(x, h)
    with pytest.raises(ValueError, match="gaussian_code_dim=3 needs codes"):
        d(x, h, codes=torch.zeros(2, 4))
    cfg = compose(["gaussians.deform_code_dim=6"])
    assert cfg.deformer.gaussian_code_dim == 6 and compose([]).deformer.gaussian_code_dim == 0
    with pytest.raises(ValueError, match="per-Gaussian decoder"):
        NodeDeformer(num_nodes=8, cond_dim=4, encoding="frequency", gaussian_code_dim=3)


def test_gaussian_codes_train_and_must_agree_with_the_decoder(scenes_root, tmp_path):
    """A short run with per-Gaussian codes trains them (they leave their initial values), density control keeps
    them aligned, the checkpoint reloads; a decoder sized differently from the Gaussians' codes is refused by name."""
    from realityavatar.build import build_data, build_module, load_run
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    over = ["data=synthetic_ci", "trainer=ci", "iterations=30", "gaussians.num_points=800", "test_after_fit=false",
            "logger=none", "gaussians.deform_code_dim=4"]
    cfg, choices = prepare_run(compose(over), tmp_path / "run")
    run(cfg, choices)
    _, module, _ = load_run(tmp_path / "run")
    g = module.gaussians
    assert g.deform_codes.shape == (g.num_points, 4)
    init = CanonicalGaussiansInit(module.body, g)
    assert float((g.deform_codes[: init.shape[0]] - init).abs().max()) > 1e-5
    bad = compose(over[:1] + ["gaussians.deform_code_dim=4", "deformer.gaussian_code_dim=2"])
    body = instantiate(bad.body)
    dm = build_data(bad, body)
    with pytest.raises(ValueError, match=r"gaussians.deform_code_dim \(4\) and deformer.gaussian_code_dim \(2\)"):
        build_module(bad, body, dm.num_train_frames, dm.scene_extent, data=dm)


def CanonicalGaussiansInit(body, g):
    """The deformation codes a fresh CanonicalGaussians with g's settings starts from (same seed draws)."""
    from realityavatar.model.gaussians import CanonicalGaussians

    return CanonicalGaussians(body, num_points=800, feature_dim=g.feature_dim, seed=0,
                              deform_code_dim=g.deform_code_dim).deform_codes.detach()


def test_frame_codes_pick_a_shape_per_training_frame():
    """deformer.frame_code_dim (the diagnostic per-frame code): different training frames give different offsets
    for the same h_t; a frame not trained on (-1) or no index takes the mean code; out-of-range indices and negative
    sizes are refused; the codes get their own optimizer group (optim.lr.deformer_codes)."""
    from realityavatar.model.deform import MotionTrendDecoder

    d = MotionTrendDecoder(cond_dim=8, encoding="frequency", hidden_dim=16, num_layers=2, feature_dim=4,
                           frame_code_dim=3, num_frames=5)
    with torch.no_grad():
        d.out.weight.normal_(0.0, 0.5)
        d.frame_codes.weight.normal_(0.0, 1.0)
    x, h = torch.rand(6, 3), torch.randn(1, 8).expand(2, -1)
    out = d(x, h, torch.tensor([0, 3]))["dx"]
    assert float((out[0] - out[1]).abs().max()) > 1e-4
    mean = d(x, h, torch.tensor([-1, -1]))["dx"]
    assert torch.allclose(mean, d(x, h)["dx"]) and torch.allclose(mean[0], mean[1])
    with pytest.raises(IndexError, match="out of range for 5 training frames"):
        d(x, h, torch.tensor([5, 0]))
    with pytest.raises(ValueError, match="frame_code_dim"):
        MotionTrendDecoder(frame_code_dim=-1)
    assert set(d.param_groups()) == {"deformer", "deformer_codes"}
    assert d.param_groups()["deformer_codes"] == [d.frame_codes.weight]


def test_training_opens_the_coarse_to_fine_window_and_a_checkpoint_keeps_it(scenes_root, tmp_path, monkeypatch):
    """Every training step sets the decoder's window from schedule.deform_anneal, and load_run puts a checkpoint's
    window back where its step had it: a run stopped mid-anneal (20 of 40 steps) renders with half its bands, as it
    trained, not with bands it never trained."""
    from realityavatar.build import load_run
    from realityavatar.config import compose, prepare_run
    from realityavatar.model.module import AvatarModule
    from realityavatar.train import run

    assert compose([]).schedule.deform_anneal == compose([]).iterations // 2
    steps = []
    orig = AvatarModule.set_progress
    monkeypatch.setattr(AvatarModule, "set_progress", lambda self, step: (steps.append(step), orig(self, step))[1])
    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=20", "schedule.deform_anneal=40",
                                        "gaussians.num_points=300", "eval.max_frames_per_split=1",
                                        "eval.save_video=false", "eval.save_images=0"]), tmp_path / "run")
    run(cfg, choices)
    assert [s for s in steps if s is not None][:20] == list(range(20))
    _, module, _ = load_run(tmp_path / "run")
    assert module.deformer.encoding.alpha == module.deformer.encoding.num_freqs * 20 / 40


@pytest.mark.parametrize("query_at", ["deformed", "canonical"])
def test_skinning_query_at_reads_the_weights_where_it_says(scenes_root, query_at):
    """skinning.query_at: "deformed" reads each point's weights at x_c + dx (3DGS-Avatar), "canonical" at x_c, so
    a point the decoder moves 40 cm keeps the bones it was laid out on; an unknown value names the field."""
    from torch.utils.data import default_collate

    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=200", f"skinning.query_at={query_at}"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    assert module.skinning.query_at == query_at
    module.skinning.init_from_body(body.canonical_vertices().detach(), body.faces, body.skin_weights)  # as on_fit_start
    forward = module.deformer.forward

    def far(*args, **kwargs):  # the decoder moves every point 40 cm along x
        out = forward(*args, **kwargs)
        return {**out, "dx": out["dx"] + torch.tensor([0.4, 0.0, 0.0])}

    module.deformer.forward = far
    b = default_collate([dm.datasets["train"][0]])
    with torch.no_grad():
        posed = module.deform(b["poses"], b["transl"], frame_idx=b["frame_idx"])
        at_rest, moved = module.skinning(module.gaussians.means), module.skinning(posed["x_e"][0])
    expected, other = (at_rest, moved) if query_at == "canonical" else (moved, at_rest)
    assert torch.allclose(posed["weights"][0], expected, atol=1e-6)
    assert (posed["weights"][0] - other).abs().max() > 0.1
    from realityavatar.model.skinning import SkinningField, SkinningGrid

    with pytest.raises(ValueError, match=r"skinning \(grid\)\.query_at"):
        SkinningGrid(query_at="rest")
    with pytest.raises(ValueError, match=r"skinning \(mlp\)\.query_at"):
        SkinningField(query_at="rest")
