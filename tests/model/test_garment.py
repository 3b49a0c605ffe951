"""The physics garment (sheet=physics): its cloth, what it reads from the masks, its Gaussians, new motions, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.model.garment import camera_up, inside_share, tube

FAST = ["sheet.search.rollouts=3", "sheet.flare_every=6", "sheet.gaussians=500", "sheet.around=16", "sheet.rings=6"]


def test_the_cloth_is_a_closed_tube_of_outward_triangles():
    pts, tris = tube(16, 6, 0.15, 0.45, 0.5, seed=0, noise=0.0)
    assert pts.shape == (96, 3) and tris.shape == (2 * 16 * 5, 3)
    t = pts[tris]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    radial = t.mean(1) * [1, 1, 0]
    assert (np.einsum("fi,fi->f", n, radial) > 0).all()  # every triangle faces out
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), 1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert count.max() == 2 and (count == 1).sum() == 2 * 16  # a tube: only the waist and hem rings are open
    assert np.allclose(np.linalg.norm(pts[:16, :2], axis=1), 0.15)  # the waist ring
    hem = pts[-16:]
    assert np.allclose(np.linalg.norm(hem[:, :2], axis=1), 0.45)
    assert np.allclose(np.hypot(0.45 - 0.15, hem[:, 2]), 0.5)  # the cone's side is the cloth's length


def _rec(viewmat):
    return type("Rec", (), {"viewmat": viewmat})


def test_up_comes_from_the_cameras_image_axes():
    from realityavatar.data.synthetic.cameras import look_at

    up = np.array([0.2, 0.9, -0.1])
    up /= np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    # four cameras on a ring about the subject, above it and looking down at it: their image-up tilts, their
    # image-right stays level
    recs = [_rec(look_at(3 * (np.cos(t) * a + np.sin(t) * b) + 0.6 * up, np.zeros(3), up))
            for t in (0.0, 1.0, 2.5, 4.0)]
    ds = type("DS", (), {"records": recs})
    assert np.allclose(camera_up(ds), up, atol=1e-6)
    one_way = type("DS", (), {"records": [recs[0], recs[0]]})
    with pytest.raises(ValueError, match="which way is up"):
        camera_up(one_way)


@pytest.fixture(scope="module")
def ci_garment(scenes_root):
    cfg = compose(["data=synthetic_ci", "sheet=physics", *FAST])
    from realityavatar.build import build_data

    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    return body, dm, instantiate(cfg.sheet, body=body, data=dm), cfg


def test_the_garment_size_read_from_the_masks_is_the_simulated_skirts(ci_garment):
    """The scene's own cloth (its meta, which the model never reads) against what the masks gave."""
    _, dm, g, _ = ci_garment
    truth = dm.scene.meta["garment_params"]
    s = g.state["shape"]
    assert s["waist_radius"] == pytest.approx(truth["waist_radius"], rel=0.15)
    assert s["length"] == pytest.approx(truth["length"], rel=0.15)
    pattern_hem = truth["waist_radius"] + truth["length"] * np.sin(np.radians(truth["flare_deg"]))
    assert s["hem_radius"] == pytest.approx(pattern_hem, rel=0.2)
    assert np.allclose(g.state["up"], [0.0, 1.0, 0.0], atol=1e-6)
    assert g.state["search"]["rollouts"] == 3 and np.isfinite(g.state["search"]["loss"])
    assert len(g.track_frames) == len(dm.scene.poses) and g.track.shape[1] == 16 * 6


def test_gaussians_sit_on_their_material_point_in_every_frame(ci_garment):
    _, _, g, _ = ci_garment
    with torch.no_grad():
        g.shift_logit.zero_()
    frames = g.track_frames[[0, 10, -1]]
    ref = {"means": torch.zeros(3, 0, 3), "f_mt": torch.zeros(3, 0, 4), "weights": torch.zeros(3, 0, 24)}
    out = g.splats(ref, {"frame": frames})
    V = g.track[frames - g.track_frames[0]]
    expect = (g.bary[None, :, :, None] * V[:, g.faces[g.tri]]).sum(2)
    assert torch.allclose(out["means"], expect, atol=1e-6)
    assert out["means"].shape == (3, g.num_gaussians, 3) and out["f_mt"].shape == (3, g.num_gaussians, 4)
    with pytest.raises(KeyError, match="frame 9999 was not simulated"):
        g.splats(ref, {"frame": torch.tensor([9999])})
    with pytest.raises(ValueError, match="need 'frame'"):
        g.splats(ref, {})


def test_the_cloth_is_lit_the_same_from_either_side(ci_garment):
    _, _, g, _ = ci_garment
    ref = {"means": torch.zeros(1, 0, 3), "f_mt": torch.zeros(1, 0, 4), "weights": torch.zeros(1, 0, 24)}
    posed = g.splats(ref, {"frame": g.track_frames[:1]})
    with torch.no_grad():
        g.light.normal_(0, 0.3)
    centre = posed["means"][0].mean(0)
    a = g.lit(posed, (centre + torch.tensor([3.0, 0.0, 0.0]))[None])
    b = g.lit(posed, (centre - torch.tensor([3.0, 0.0, 0.0]))[None])
    facing_a = ((posed["means"] - centre - torch.tensor([3.0, 0, 0])) * posed["garment_normals"]).sum(-1) > 0
    facing_b = ((posed["means"] - centre + torch.tensor([3.0, 0, 0])) * posed["garment_normals"]).sum(-1) > 0
    same = facing_a == facing_b  # seen from the same side by both cameras: the same colour
    assert torch.allclose(a[same], b[same]) and not torch.allclose(a[~same], b[~same])
    with torch.no_grad():
        g.light.zero_()


def test_a_checkpoint_rebuilds_the_garment_without_the_data(ci_garment):
    body, _, g, cfg = ci_garment
    fresh = instantiate(cfg.sheet, body=body, data=None)
    fresh.load_state_dict(g.state_dict())
    assert fresh.state == g.state and torch.equal(fresh.track, g.track)
    ref = {"means": torch.zeros(1, 0, 3), "f_mt": torch.zeros(1, 0, 4), "weights": torch.zeros(1, 0, 24)}
    a = fresh.splats(ref, {"frame": g.track_frames[5:6]})["means"]
    assert torch.equal(a, g.splats(ref, {"frame": g.track_frames[5:6]})["means"])


def test_a_new_motion_is_simulated_and_a_blow_up_is_named(ci_garment):
    from realityavatar.data.poses import PoseTable

    body, dm, g, cfg = ci_garment
    fresh = instantiate(cfg.sheet, body=body, data=None)
    fresh.load_state_dict(g.state_dict())
    table = dm.scene.poses
    n = 12
    motion = PoseTable.from_sequence(table.poses[:n].clone(), table.transl[:n].clone())
    record = fresh.drive(body, motion)
    assert record["frames"] == n and fresh.track.shape == (n, g.track.shape[1], 3)
    assert torch.equal(fresh.track_frames, torch.arange(n))
    # the same first frames as the training motion's: the same cloth (deterministic solver)
    assert torch.allclose(fresh.track, g.track[:n], atol=1e-5)
    # cloth through the body is named: a torso collider 4 cm wider than the waist leaves the pinned ring inside it
    fresh.state["radii"] = [*g.state["radii"][:5], g.state["shape"]["waist_radius"] + 0.04]
    record = fresh.drive(body, motion)
    assert record["inside"] == list(range(n))
    # a blow-up is named: a torso collider 0.5 m wide throws the cloth off in the pre-roll
    fresh.state["radii"] = [*g.state["radii"][:5], 0.5]
    with pytest.raises(RuntimeError, match=r"sheet=physics on pose sequence: cloth simulation unstable at frame 0"):
        fresh.drive(body, motion)
    gap = PoseTable(np.array([0, 1, 3]), table.poses[:3], table.transl[:3])
    with pytest.raises(ValueError, match="skips frames"):
        fresh.drive(body, gap)


def test_the_residual_moves_training_frames_only_and_trains(ci_garment, scenes_root):
    from realityavatar.build import build_module

    body, dm, _, _ = ci_garment
    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300", "sheet=physics", *FAST,
                   "sheet.residual=true"])
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    g = module.avatar.sheet
    assert g.offsets.shape == (dm.num_train_frames, g.track.shape[1], 3)
    with torch.no_grad():
        g.offsets.fill_(0.01)
    f = g.train_frames[:1]
    moved = g.vertices(f, torch.tensor([0]))
    plain = g.vertices(f, torch.tensor([-1]))
    assert torch.allclose(moved - plain, torch.full_like(plain, 0.01))
    with torch.no_grad():
        g.offsets.zero_()
    from torch.utils.data import default_collate

    module.on_fit_start()
    batch = module.device_batch(default_collate([dm.datasets["train"][0]]))
    total, terms, _, _ = module.training_loss(batch, step=0)
    assert torch.isfinite(total) and {"garment_stretch", "garment_smooth", "garment_temporal"} <= set(terms)
    total.backward()
    assert g.offsets.grad is not None and float(g.offsets.grad.abs().sum()) > 0
    assert float(g.albedo.grad.abs().sum()) > 0


def test_inside_share_counts_cloth_inside_a_collider():
    J = np.zeros((1, 24, 3))
    J[0, 3 - 3] = [0.0, 0.0, 0.0]
    J[0, 6] = [0.0, 1.0, 0.0]  # the torso capsule: pelvis (0) -> spine2 (6) along +y, radius 0.2
    for j in (1, 2, 4, 5, 7, 8):
        J[0, j] = [5.0 + j, 0.0, 0.0]  # the other colliders far away
    V = np.array([[[0.1, 0.5, 0.0], [0.195, 0.5, 0.0], [0.3, 0.5, 0.0], [0.0, 1.15, 0.0]]])
    share = inside_share(V, J, [0.01] * 5 + [0.2])
    assert share.tolist() == [0.5]  # 10 cm deep and 5 cm deep past the end: inside; 0.5 cm deep, outside: not
