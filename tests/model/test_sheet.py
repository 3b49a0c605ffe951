"""The garment sheet: Gaussians on its cells, the rest layout, training beside the free Gaussians, export, strain, basis."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.body import build_body
from realityavatar.config import compose
from tests.model.configured import component


@pytest.fixture(scope="module")
def sheet():
    return component("sheet", "skirt", body=build_body("mannequin"), rows=3, cols=8, per_cell=3, profile="canonical")


def test_sheet_gaussians_sit_on_their_cells_in_the_cells_frame(sheet):
    V = sheet.vertices[None].double()
    with torch.no_grad():
        sheet.normal_offset.zero_()
    placed = sheet.place(V)
    c = V[0, sheet.corners]  # [M,4,3]
    a, b = sheet.ab[:, 0:1].double(), sheet.ab[:, 1:2].double()
    expect = (1 - a) * (1 - b) * c[:, 0] + a * (1 - b) * c[:, 1] + (1 - a) * b * c[:, 2] + a * b * c[:, 3]
    assert torch.allclose(placed["means"][0], expect, atol=1e-12)
    from realityavatar.geometry import quat_to_matrix

    R = quat_to_matrix(placed["quats"][0])
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-6)
    t_u = (1 - b) * (c[:, 1] - c[:, 0]) + b * (c[:, 3] - c[:, 2])
    assert torch.allclose((R[..., 2] * t_u).sum(-1), torch.zeros(len(t_u), dtype=R.dtype), atol=1e-6)  # normal ⟂ ring
    # the sheet opens: scaled by 2 about its centre, every tangent scale doubles, the normal scale does not
    centre = V[0].mean(0)
    wide = sheet.place(centre + 2 * (V - centre))
    ratio = wide["scales"][0] / placed["scales"][0]
    assert torch.allclose(ratio[:, :2], torch.full_like(ratio[:, :2], 2.0), rtol=1e-6)
    assert torch.allclose(ratio[:, 2], torch.ones_like(ratio[:, 2]))


def test_moving_one_vertex_moves_only_the_gaussians_of_its_cells(sheet):
    V = sheet.vertices[None].clone()
    k = sheet.cols + 2  # a vertex of the second ring
    moved = V.clone()
    moved[0, k] += torch.tensor([0.0, 0.0, 0.1])
    d = (sheet.place(moved)["means"] - sheet.place(V)["means"]).norm(dim=-1)[0].detach()
    touches = (sheet.corners == k).any(-1)
    assert touches.sum() == 4 * sheet.per_cell  # a vertex inside the grid belongs to four cells
    assert float(d[~touches].max()) == 0.0 and float(d[touches].min()) > 0.0


def test_canonical_sheet_spans_the_hips_to_the_knees_around_the_body(sheet):
    body = build_body("mannequin")
    J = body.joints(body.canonical_pose()[None])[0]
    axis = torch.nn.functional.normalize(J[12] - J[0], dim=0)
    rel = sheet.vertices.reshape(sheet.rows + 1, sheet.cols, 3) - J[0]
    h = rel @ axis
    assert float(h[0].mean()) == pytest.approx(0.08, abs=1e-5)
    assert float(h[-1].mean()) == pytest.approx(float(((J[[4, 5]] - J[0]) @ axis).mean()), abs=1e-5)
    r = (rel - h[..., None] * axis).norm(dim=-1)
    assert float(r.std(1).max()) < 1e-5  # each ring is a circle about the axis
    verts = body.canonical_vertices()
    hv = (verts - J[0]) @ axis
    rv = (verts - J[0] - hv[:, None] * axis).norm(dim=-1)
    knee = (hv - h[-1, 0]).abs() < 0.05
    assert float(r[-1, 0]) > float(torch.quantile(rv[knee], 0.9))  # outside the legs
    with pytest.raises(ValueError, match="bottom"):
        component("sheet", "skirt", body=body, profile="canonical", top_offset=-1.0)
    with pytest.raises(ValueError, match="sheet.profile"):
        component("sheet", "skirt", body=body, profile="hull")


def _ci_sheet_module(rows: int = 6, per_cell: int = 1):
    """body, data module and an untrained module with a rest-layout sheet (12 columns) on the CI scene; a fresh one
    per call (canonicalise changes the sheet)."""
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300", "sheet=skirt", f"sheet.rows={rows}",
                   "sheet.cols=12", f"sheet.per_cell={per_cell}"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    return body, dm, build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)


def test_rest_sheet_is_laid_out_at_the_hem_and_poses_back_onto_its_layout(scenes_root):
    """profile=rest on the CI scene's skirt: hem found in the rest frame's hull below the top ring, radii around
    the legs; after canonicalise the module's own skinning poses the vertices back onto the layout."""
    from realityavatar.model.skinning import lbs_gaussians

    body, _, module = _ci_sheet_module()
    sh = module.avatar.sheet
    lay = sh.layout
    assert lay["profile"] == "rest" and -0.9 < lay["bottom"] < 0.08 - 0.15
    assert all(0.05 < r < 0.4 for r in lay["radii"])
    assert not bool(sh.canonical_done)
    module.on_fit_start()
    assert bool(sh.canonical_done) and module.run_info["sheet"]["canonicalise"]["residual_max_m"] < 1e-3
    A = body.canonical_transforms(sh.rest_pose[None], sh.rest_transl[None])
    q = torch.zeros(1, sh.vertices.shape[0], 4)
    q[..., 0] = 1.0
    posed = lbs_gaussians(sh.vertices[None], q, module.avatar.skinning(sh.vertices[None]), A)[0][0]
    assert float((posed - sh.posed_rest).norm(dim=-1).max()) < 1e-3
    first = sh.vertices.clone()
    module.on_fit_start()  # once per run
    assert torch.equal(first, sh.vertices)
    # the stretch cap is measured against the rest layout's cells, not the canonical ones, which the star pose's
    # spread legs widen (a cap against those bound nothing under poses spreading the legs further)
    rest_u, rest_v = sh._cell_frame(sh.posed_rest[None])[3:]
    can_u = sh._cell_frame(sh.vertices[None])[3:][0]
    assert float((can_u / rest_u).max()) > 2.0  # the canonical cells between the legs are wider than at rest
    V = sh.vertices[None]
    centre = V[0].mean(0)
    with torch.no_grad():
        torn = sh.place(centre + 20.0 * (V - centre))["scales"][0]
    rel = sh.log_scales.exp().detach()
    assert torch.all(torn[:, 0:1] <= sh.max_stretch * rest_u[0] * rel[:, 0:1] * (1 + 1e-5))
    assert torch.all(torn[:, 1:2] <= sh.max_stretch * rest_v[0] * rel[:, 1:2] * (1 + 1e-5))


def test_sheet_trains_beside_the_free_gaussians_and_reloads(scenes_root, tmp_path):
    from realityavatar.build import load_run
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    assert compose([]).sheet._target_.endswith("NoSheet")  # off by default: a source with no points
    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=10", "sheet=skirt",
                                        "sheet.rows=4", "sheet.cols=12", "sheet.per_cell=2", "sheet.basis=4",
                                        "+loss.sheet_strain._target_=realityavatar.losses.SheetStrain",
                                        "+loss.sheet_strain.weight=0.1",
                                        "gaussians.num_points=300", "density.refine_start=2", "density.refine_every=2",
                                        "eval.max_frames_per_split=1", "eval.save_video=false",
                                        "eval.save_images=0"]), tmp_path / "run")
    run(cfg, choices)
    _, module, _ = load_run(tmp_path / "run")
    assert module.avatar.sheet.num_points == 4 * 12 * 2 and "sheet_strain" in module.losses
    import json

    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert np.isfinite(m["test/novel_view/psnr"])
    assert m["num_gaussians"] == module.avatar.gaussians.num_points  # density control edited the free Gaussians only
    assert m["num_sheet_gaussians"] == 96 and m["sheet"]["profile"] == "rest"
    assert not math.isclose(float(module.avatar.sheet.opacity_logits.std()), 0.0)  # the sheet was trained
    assert float(module.avatar.sheet.basis.abs().max()) > 0  # its motion basis too (zero at the start), and it reloads
    groups = {g["name"]: g["lr"] for g in module.param_groups()}
    assert groups["sheet_basis"] == groups["sheet_coeff"] == groups["deformer"]


def test_export_and_viewer_frames_carry_the_sheet(scenes_root):
    """A run with a sheet exports (and the viewer streams) the free Gaussians and the sheet's, canonical and posed,
    every field with the same count."""
    from realityavatar.export import gaussians_for_export

    _, dm, module = _ci_sheet_module(rows=4, per_cell=2)
    n = module.avatar.gaussians.num_points + module.avatar.sheet.num_points
    batch = next(iter(dm.train_dataloader()))
    for poses, transl in ((None, None), (batch["poses"][0], batch["transl"][0])):
        out = gaussians_for_export(module.avatar, poses, transl)
        assert {k: v.shape[0] for k, v in out.items()} == {k: n for k in out}, {k: v.shape for k, v in out.items()}
        assert np.isfinite(out["means"]).all() and np.isfinite(out["rgb"]).all()
    can = gaussians_for_export(module.avatar)["means"][module.avatar.gaussians.num_points:]
    assert np.allclose(can, module.avatar.sheet.place(module.avatar.sheet.vertices[None])["means"][0].detach().numpy(), atol=1e-6)


def test_a_cell_torn_open_caps_its_gaussians_stretch():
    """Under a pose the garment cannot follow (a cell pulled 20x its size) the tangent scales stop at max_stretch
    times the reference cell's (here, profile=canonical, the canonical one); below the cap they follow the cell."""
    sh = component("sheet", "skirt", body=build_body("mannequin"), rows=3, cols=8, per_cell=2, profile="canonical", max_stretch=5.0)
    V = sh.vertices[None]
    centre = V[0].mean(0)
    base = sh.place(V)["scales"][0].detach()
    for k, expect in ((3.0, 3.0), (20.0, 5.0)):
        got = sh.place(centre + k * (V - centre))["scales"][0].detach()
        assert torch.allclose(got[:, :2] / base[:, :2], torch.full_like(got[:, :2], expect), rtol=1e-5)
    free = component("sheet", "skirt", body=build_body("mannequin"), rows=3, cols=8, per_cell=2, profile="canonical", max_stretch=0)
    got = free.place(centre + 20.0 * (V - centre))["scales"][0].detach()
    assert torch.allclose(got[:, :2] / base[:, :2], torch.full_like(got[:, :2], 20.0), rtol=1e-5)


def test_strain_penalises_stretch_down_the_sheet_not_around_it():
    """sheet.strain: zero for the reference layout, for rings widened 3x (a flare) and for columns within
    strain_free; positive, and pulling the vertices back together, for columns stretched beyond it."""
    sh = component("sheet", "skirt", body=build_body("mannequin"), rows=3, cols=8, per_cell=1, profile="canonical", strain_free=0.2)
    V = sh.vertices[None].double()
    G = V.reshape(1, sh.rows + 1, sh.cols, 3)
    axis_xz = G.mean(2, keepdim=True)[..., [0, 2]]  # each ring's centre
    wide = G.clone()
    wide[..., [0, 2]] = axis_xz + 3.0 * (G[..., [0, 2]] - axis_xz)  # every ring 3x wider, heights kept
    assert float(sh.strain(V)) == 0.0
    top = G[:, :1]
    within = (top + 1.15 * (G - top)).reshape(1, -1, 3)  # 15 % longer down the sheet (and around it)
    assert float(sh.strain(within)) == 0.0
    long = (top + 2.0 * (G - top)).reshape(1, -1, 3).requires_grad_(True)  # columns 2x long
    s = sh.strain(long)
    assert float(s.detach()) == pytest.approx(0.8**2, rel=1e-9)  # every edge down the sheet: excess 2 - 1.2
    s.backward()
    down = (long.grad.reshape(1, sh.rows + 1, sh.cols, 3)[:, -1] * (G[:, -1] - G[:, -2])).sum(-1)
    assert torch.all(down > 0)  # descending the loss moves the hem ring back up its column
    assert float(sh.strain(wide.reshape(1, -1, 3))) < float(s.detach())  # a 3x flare costs less than 2x long columns
    with pytest.raises(ValueError, match="strain"):
        component("sheet", "skirt", body=build_body("mannequin"), rows=3, cols=8, per_cell=1, profile="canonical", strain_free=-1.0)


def test_motion_basis_is_a_linear_map_of_the_temporal_state():
    """sheet.basis: zero offsets at the start, a gradient that reaches the basis there, offsets sum_k c_k(h) B_k
    that differ between temporal states; basis=0 adds no parameters."""
    body = build_body("mannequin")
    assert not hasattr(component("sheet", "skirt", body=body, rows=3, cols=8, per_cell=1, profile="canonical"), "basis")
    sh = component("sheet", "skirt", body=body, rows=3, cols=8, per_cell=1, profile="canonical", basis=4, cond_dim=8)
    h = torch.randn(3, 8, generator=torch.Generator().manual_seed(0))
    o = sh.basis_offsets(h)
    assert o.shape == (3, sh.vertices.shape[0], 3) and float(o.abs().max()) == 0.0
    sh.basis_offsets(h).sum().backward()
    assert float(sh.basis.grad.abs().max()) > 0
    with torch.no_grad():
        sh.basis.normal_(generator=torch.Generator().manual_seed(1))
        o = sh.basis_offsets(h)
        expect = torch.einsum("bk,kpd->bpd", sh.coeff(h), sh.basis)
    assert torch.allclose(o, expect) and not torch.allclose(o[0], o[1])
    with pytest.raises(ValueError, match="basis"):
        component("sheet", "skirt", body=body, rows=3, cols=8, per_cell=1, profile="canonical", basis=-1)


def _sliding(rows: int = 2, cols: int = 8, frames: int = 3):
    """A canonical SlidingSheet (no data: its per-frame tables are set here) with distinct features per Gaussian."""
    sh = component("sheet", "skirt_slide", body=build_body("mannequin"), rows=rows, cols=cols, profile="canonical")
    sh.live = torch.tensor([0.0] + [1.0] * (frames - 1))
    sh.slide = torch.nn.Parameter(torch.zeros(frames, rows + 1))
    with torch.no_grad():
        sh.features.copy_(torch.arange(rows * cols * sh.feature_dim, dtype=torch.float32).reshape(rows * cols, -1))
    return sh


def test_sliding_sheet_reads_each_rows_colours_further_back_around_the_ring():
    """A slide of one column's angle reads the previous column's features (the texture turns with +angle); half a
    column reads the mean of two neighbours; a frame held still (live 0), not trained on (-1) or unslid reads its own."""
    sh = _sliding()
    G = sh.features.detach().reshape(2, 8, -1)
    with torch.no_grad():
        sh.slide[1] = 2 * math.pi / 8
        sh.slide[2] = 0.5 * 2 * math.pi / 8
        sh.slide[0] = 2 * math.pi / 8  # frame 0 is held still: no effect
    out = sh.colour_features(torch.tensor([1, 2, 0, -1])).detach().reshape(4, 2, 8, -1)
    assert torch.equal(out[0], torch.roll(G, 1, dims=1))
    assert torch.allclose(out[1], 0.5 * (G + torch.roll(G, 1, dims=1)))
    assert torch.equal(out[2], G) and torch.equal(out[3], G)
    plain = component("sheet", "skirt", body=build_body("mannequin"), rows=2, cols=8, profile="canonical")
    assert plain.colour_features(torch.tensor([1])) is plain.features  # the plain sheet: one texture for all frames
    bare = component("sheet", "skirt_slide", body=build_body("mannequin"), rows=2, cols=8, profile="canonical")
    with pytest.raises(ValueError, match="no training frames"):  # neither data nor a checkpoint
        bare.colour_features(torch.tensor([0]))
    with pytest.raises(ValueError, match="per_cell"):
        component("sheet", "skirt_slide", body=build_body("mannequin"), rows=2, cols=8, per_cell=2,
                  profile="canonical")


def test_slide_smoothness_is_zero_for_a_steady_turn_and_not_for_a_kink():
    from types import SimpleNamespace

    from realityavatar.losses import SheetSlideSmooth

    sh = _sliding(rows=3, frames=6)
    term = SheetSlideSmooth(0.1)
    out = SimpleNamespace(avatar=SimpleNamespace(sheet=sh))
    with torch.no_grad():  # linear in the frame (from the still frame 0's zero) and in the ring: no second difference
        sh.slide.copy_(torch.arange(6.0)[:, None] * 0.01 * (1 + torch.arange(4.0))[None])
    assert float(term(out)[0].detach()) < 1e-12
    with torch.no_grad():
        sh.slide[3, 2] += 0.05
    value, logged = term(out)
    assert float(value.detach()) > 0 and math.isclose(float(value.detach()), 0.1 * float(logged["sheet_slide"]), rel_tol=1e-6)


def test_frames_whose_root_did_not_turn_in_the_window_are_held_still(scenes_root):
    """On the CI scene's spin: the rest frames before it and the frames long after its stop are held still, the spin's
    are not; a frame is live exactly when its pose window's root turned between two entries."""
    from realityavatar.build import build_data
    from realityavatar.geometry import axis_angle_to_matrix
    from realityavatar.model.sheet import moving_frames

    cfg = compose(["data=synthetic_ci", "trainer=ci", "sheet=skirt_slide"])
    dm = build_data(cfg, instantiate(cfg.body))
    live = moving_frames(dm, 0.5)
    ds = dm.datasets["train"]
    assert len(live) == len(ds.train_frame_index) and live[0] == 0 and 0 < int(live.sum()) < len(live)
    for frame, k in ds.train_frame_index.items():
        poses, _ = ds.poses.window(frame, ds.window_len, ds.window_step)
        R = axis_angle_to_matrix(poses[:, 0].double())
        turned = float((R[0].T @ R[-1] - torch.eye(3, dtype=R.dtype)).abs().max()) > 1e-3
        assert bool(live[k]) == turned, frame


def test_sliding_sheet_trains_its_slide_on_the_turning_frames_and_reloads(scenes_root, tmp_path):
    from realityavatar.build import load_run
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=12", "sheet=skirt_slide",
                                        "sheet.rows=4", "sheet.cols=12", "gaussians.num_points=300",
                                        "eval.max_frames_per_split=1", "eval.save_video=false",
                                        "eval.save_images=0"]), tmp_path / "run")
    run(cfg, choices)
    _, module, _ = load_run(tmp_path / "run")
    sh = module.avatar.sheet
    assert type(sh).__name__ == "SlidingSheet" and "sheet_slide" in module.losses  # the sheet brings its term
    assert sh.slide.shape == (len(sh.live), 5) and 0 < int(sh.live.sum()) < len(sh.live)
    still = sh.live == 0
    assert float(sh.slide[~still].abs().max()) > 0  # learnt where the body turned
    assert float(sh.slide[still].abs().max()) == 0  # frames held still get no gradient
    groups = {g["name"]: g["lr"] for g in module.param_groups()}
    assert groups["sheet_slide"] == 1e-2
