"""Tests of the synthetic scene generator: layout, masks, joint projections, Rh/Th, determinism, cache, bad
parameters, and the hysteresis of the simulated garment."""

import hashlib
import json
import os
import pickle
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from realityavatar.body import MannequinBody, rh_th_to_smpl
from realityavatar.data.synthetic import build_scene, resolve_params, scene_paths
from realityavatar.data.synthetic.cameras import eval_cameras, look_at, novel_view_ids, ring_cameras
from realityavatar.data.synthetic.motions import MOTIONS, make_motion
from realityavatar.geometry import axis_angle_to_matrix


@pytest.fixture(scope="module")
def body():
    return MannequinBody()


@pytest.fixture(scope="module")
def ci_scene(scenes_root):
    """The session's ci scene (conftest.scenes_root, built once with these arguments): this call finds it cached."""
    return build_scene("ci", scenes_root, seed=0, progress=False)


def _tree_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _load(path):
    with open(path, "rb") as f:
        return pickle.load(f)


def test_layout(ci_scene):
    paths = scene_paths(ci_scene)
    meta = json.loads(paths["meta"].read_text())
    p = meta["params"]
    assert meta["cameras"]["train"] == [0, 1, 3] and meta["cameras"]["novel_view"] == [2, 4, 5]
    assert meta["cameras"]["eval_only"] == [4, 5] and meta["cameras"]["novel_pose"] == [0, 1, 2, 3]
    n_tr, n_np = p["train_frames"], p["novel_frames"]
    expect = {"train": n_tr * 3, "novel_view": n_tr * 3, "novel_pose": n_np * 4}
    for split, count in expect.items():
        d = paths[split]
        images = sorted(x.name for x in (d / "images").iterdir())
        masks = sorted(x.name for x in (d / "masks").iterdir())
        assert len(images) == count and images == masks
        cams, infos = _load(d / "cameras.pkl"), _load(d / "mesh_infos.pkl")
        assert sorted(cams) == sorted(infos) == [n[:-4] for n in images]
        name = images[0][:-4]
        assert name.startswith("frame_") and "_view_" in name
        c, m = cams[name], infos[name]
        assert c["intrinsics"].shape == (3, 3) and c["extrinsics"].shape == (4, 4) and c["distortions"].shape == (5,)
        assert m["poses"].shape == (72,) and np.all(m["poses"][:3] == 0)
        assert m["Rh"].shape == m["Th"].shape == (3,)
        assert m["joints"].shape == m["tpose_joints"].shape == (24, 3)
        assert _load(d / "canonical_joints.pkl")["joints"].shape == (24, 3)
        frames = {int(n[6:12]) for n in cams}
        assert frames == (set(range(n_tr)) if split != "novel_pose" else set(range(n_tr, n_tr + n_np)))
        img = imageio.imread(d / "images" / images[0])
        assert img.shape == (p["height"], p["width"], 3) and img.dtype == np.uint8
    g = np.load(paths["garment"])
    assert g["vertices"].shape[0] == n_tr + n_np and g["vertices"].shape[2] == 3
    assert g["faces"].max() < g["vertices"].shape[1] and list(g["frames"]) == list(range(n_tr + n_np))
    assert meta["seed"] == 0 and meta["body"] == "mannequin" and meta["versions"]["mujoco"]


def test_masks_match_silhouettes(ci_scene):
    for split in ("train", "novel_view", "novel_pose"):
        d = scene_paths(ci_scene)[split]
        for img_path in sorted((d / "images").iterdir()):
            rgb = imageio.imread(img_path)
            mask = imageio.imread(d / "masks" / img_path.name)
            assert set(np.unique(mask)) <= {0, 255}
            # Masks are the pixels at least half covered (supersample > 1): every one is lit, and a lit pixel
            # outside the mask is an edge pixel or a part thinner than half a pixel, within 2 px of the mask.
            lit, inside = rgb.max(-1) > 0, mask > 0
            assert lit[inside].all(), img_path.name
            near = np.pad(inside, 2)
            near = np.max([near[dy:dy + inside.shape[0], dx:dx + inside.shape[1]] for dy in range(5) for dx in range(5)], 0)
            assert not (lit & ~near).any(), img_path.name
            assert 0.03 < (mask > 0).mean() < 0.6  # the subject is in view and not clipped to a sliver


def test_joints_project_inside_masks(ci_scene, body):
    # Pelvis and head joints (world = R(Rh) joints + Th) fall on the subject in every camera and frame.
    for split in ("train", "novel_view", "novel_pose"):
        d = scene_paths(ci_scene)[split]
        cams, infos = _load(d / "cameras.pkl"), _load(d / "mesh_infos.pkl")
        for name, cam in cams.items():
            info = infos[name]
            R = axis_angle_to_matrix(torch.tensor(info["Rh"], dtype=torch.float64)).numpy()
            world = info["joints"][[0, 15]] @ R.T + info["Th"]
            x = (cam["extrinsics"][:3, :3] @ world.T).T + cam["extrinsics"][:3, 3]
            uv = (cam["intrinsics"] @ x.T).T
            uv = uv[:, :2] / uv[:, 2:]
            mask = imageio.imread(d / "masks" / f"{name}.png")
            H, W = mask.shape
            for u, v in uv:
                assert 0 <= u < W and 0 <= v < H, name
                assert mask[int(v), int(u)] == 255, (name, u, v)


def test_rh_th_readback_reproduces_world_joints(ci_scene, body):
    d = scene_paths(ci_scene)["novel_pose"]
    infos = _load(d / "mesh_infos.pkl")
    for name in sorted(infos)[::7]:
        m = infos[name]
        pose = torch.tensor(m["poses"]).reshape(24, 3)
        assert torch.allclose(body.joints(pose), torch.tensor(m["joints"]), atol=1e-5)  # stored in the body frame
        R = axis_angle_to_matrix(torch.tensor(m["Rh"]))
        world = torch.tensor(m["joints"]) @ R.T + torch.tensor(m["Th"])
        smpl_pose, transl = rh_th_to_smpl(pose, torch.tensor(m["Rh"]), torch.tensor(m["Th"]), body.rest_joints[0])
        assert torch.allclose(body.joints(smpl_pose, transl), world, atol=1e-4)
        assert torch.allclose(torch.tensor(m["tpose_joints"]), body.rest_joints)


def test_feet_on_ground_and_garment_near_body(ci_scene, body):
    infos = _load(scene_paths(ci_scene)["train"] / "mesh_infos.pkl")
    m = infos["frame_000000_view_00"]
    v = body.posed_vertices(torch.tensor(m["poses"]).reshape(24, 3)).numpy()
    R = axis_angle_to_matrix(torch.tensor(m["Rh"], dtype=torch.float64)).numpy()
    world = v @ R.T + m["Th"]
    assert abs(world[:, 1].min()) < 0.02  # soles on y = 0 (world y up)
    g = np.load(scene_paths(ci_scene)["garment"])["vertices"][0]
    assert 0.2 < g[:, 1].min() < 1.0 and g[:, 1].max() < 1.3  # a skirt: from about knee to waist height


def test_determinism_cache_and_other_seed(ci_scene, tmp_path, monkeypatch):
    root_a = ci_scene.parent  # frames ray cast by one process per core (scene._rendered_frames)
    root_b = tmp_path / "b"
    with monkeypatch.context() as m:
        m.setattr(os, "sched_getaffinity", lambda pid: {0})  # one core: every frame in this process
        prefix_b = build_scene("ci", root_b, seed=0, progress=False)
    assert _tree_hashes(root_a) == _tree_hashes(root_b)  # same seed -> byte-identical files
    meta = scene_paths(prefix_b)["meta"]
    stamp = meta.stat().st_mtime_ns
    assert build_scene("ci", root_b, seed=0, progress=False) == prefix_b  # cached: nothing rewritten
    assert meta.stat().st_mtime_ns == stamp
    build_scene("ci", root_b, seed=1, progress=False)  # parameters changed -> rebuilt in place
    hb = _tree_hashes(root_b)
    ha = _tree_hashes(root_a)
    assert json.loads(meta.read_text())["seed"] == 1
    assert hb[f"{prefix_b.name}-garment.npz"] != ha[f"{prefix_b.name}-garment.npz"]
    changed = [k for k in ha if k.endswith(".png") and ha[k] != hb.get(k)]
    assert len(changed) > 0.5 * sum(k.endswith(".png") for k in ha)
    assert not [p for p in root_b.iterdir() if p.name.startswith(".tmp")]


def blas_threads(f: int) -> int:
    """Stands in for scene._render_frame in the frame workers (module level: the pool pickles it by name)."""
    from threadpoolctl import threadpool_info

    return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1)


def test_frame_workers_run_blas_on_one_thread(monkeypatch):
    """Each frame worker has a core: BLAS's own threads (one per core, in every worker) would only contend."""
    from realityavatar.data.synthetic import scene

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: the frames are cast in this process")
    monkeypatch.setattr(scene, "_render_frame", blas_threads)
    assert list(scene._rendered_frames({}, 4)) == [1, 1, 1, 1]


@pytest.mark.parametrize("overrides, match", [
    ({"cameras": 0}, "cameras"),
    ({"train_frames": -3}, "train_frames"),
    ({"novel_frames": -1}, "novel_frames"),
    ({"motion": "dance"}, "motion"),
    ({"garment": "cape"}, "garment"),
    ({"sequence": "cape_spin"}, "sequence"),
    ({"width": 0}, "width"),
    ({"novel_view_cameras": 4}, "novel_view_cameras"),
    ({"fps": 0}, "fps"),
    ({"colour": 1}, "unknown keys"),
    ({"ambient": -0.1}, "ambient"),
    ({"ambient": 0.0, "diffuse": 0.0}, "ambient"),
    ({"supersample": 0}, "supersample"),
    ({"supersample": 9}, "supersample"),
    ({"supersample": 2.5}, "supersample"),
])
def test_bad_parameters_raise_before_writing(tmp_path, overrides, match):
    root = tmp_path / "never"
    with pytest.raises(ValueError, match=match):
        build_scene("ci", root, seed=0, overrides=overrides, progress=False)
    assert not root.exists()


def test_light_parameters_shade_the_images(tmp_path):
    """ambient=1, diffuse=0 renders the albedo alone: every lit pixel at least as bright as under the default light,
    the masks the same."""
    from realityavatar.data.synthetic.render import render_views

    V = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0]])
    F = np.array([[0, 1, 2]])
    K = np.array([[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]])
    E = np.eye(4)[None].copy()
    E[0, 2, 3] = 2.0
    tex = lambda f, bary: np.full((len(f), 3), 0.5)  # a flat grey albedo
    lit, m1, _ = render_views([(V, F, tex)], K, E, 32, 32, ambient=0.4, diffuse=0.6)
    flat, m2, _ = render_views([(V, F, tex)], K, E, 32, 32, ambient=1.0, diffuse=0.0)
    assert (m1 == m2).all() and m1.any()
    inside = m1 > 0
    assert (flat[inside] == 128).all()  # 0.5 albedo x 1.0
    assert lit[inside].max() < 128  # the light (0.35, 0.82, 0.45) meets this triangle's normal obliquely


def _striped_quad(period_px: float):
    """A quad filling a 16x16 view 2 m away, its albedo stripes of `period_px` pixels along x (white | black)."""
    V = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    K = np.array([[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]])  # 2 m away: a pixel is 1/8 m on the quad
    E = np.eye(4)[None].copy()
    E[0, 2, 3] = 2.0
    px = 2.0 / 16.0  # metres per pixel on the quad

    def tex(f, bary):
        x = np.einsum("pk,pkc->pc", bary, V[f])[:, 0] + 8 * px
        on = np.floor(x / (period_px * px) * 2) % 2 == 0
        return np.where(on[:, None], 1.0, 0.1) * np.ones((len(f), 3))

    return [(V, F, tex)], K, E


def test_supersample_integrates_each_pixel():
    """Stripes of half a pixel: one ray per pixel centre always lands on the same stripe (aliasing: a flat, wrong
    colour), s x s rays average both stripes like a camera's pixel; supersample=1 is the centre ray exactly."""
    from realityavatar.data.synthetic.render import render_views

    parts, K, E = _striped_quad(period_px=0.5)
    one, m1, _ = render_views(parts, K, E, 16, 16, ambient=1.0, diffuse=0.0, supersample=1)
    four, m4, _ = render_views(parts, K, E, 16, 16, ambient=1.0, diffuse=0.0, supersample=4)
    assert m1.all() and m4.all()
    assert np.unique(one).size == 1 and one.max() in (26, 255)  # every centre hits the same stripe
    assert np.abs(four.astype(float) - 0.55 * 255).max() <= 1.0  # (1.0 + 0.1) / 2 per pixel
    with pytest.raises(ValueError, match="supersample"):
        render_views(parts, K, E, 16, 16, supersample=0)


def test_supersample_masks_half_covered_pixels():
    """A triangle edge through the view: the s x s mask keeps the pixels at least half covered, and the edge pixels'
    colour is the covered fraction of the albedo."""
    from realityavatar.data.synthetic.render import render_views

    V = np.array([[-1.0, -1.0, 0.0], [0.0 + 0.3 / 16, -1.0, 0.0], [0.0 + 0.3 / 16, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])  # x < 0.01875 m: pixel column 8 is 0.15 covered (1/8 m per pixel, 2 m away)
    K = np.array([[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]])
    E = np.eye(4)[None].copy()
    E[0, 2, 3] = 2.0
    tex = lambda f, bary: np.full((len(f), 3), 1.0)
    rgb, mask, part = render_views([(V, F, tex)], K, E, 16, 16, ambient=1.0, diffuse=0.0, supersample=4)
    assert (mask[0, :, :8] == 255).all() and (mask[0, :, 8:] == 0).all()
    assert ((part[0] == 1) == (mask[0] == 255)).all()  # one part: its label is the mask
    assert (rgb[0, :, :8] == 255).all() and (rgb[0, :, 9:] == 0).all()
    assert np.abs(rgb[0, :, 8].astype(float) - 0.25 * 255).max() <= 1.0  # 4 x 4 grid: 1 of 4 columns inside


def test_unknown_preset_and_short_spin(tmp_path):
    with pytest.raises(ValueError, match="preset"):
        build_scene("huge", tmp_path / "x")
    with pytest.raises(ValueError, match="too short"):
        build_scene("ci", tmp_path / "x", overrides={"train_frames": 8}, progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("supersample", [1, 4])
def test_part_labels_name_the_first_surface_hit(supersample):
    """Two parts, the second (the 'garment') a square in front of the left half of the first: each pixel is labelled
    with the part its rays see first (1 + index), the garment where it covers the first part too, 0 off both; with
    s x s rays a pixel goes to the part that covers at least half of it."""
    from realityavatar.data.synthetic.render import render_views

    back = (np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]),
            np.array([[0, 1, 2], [0, 2, 3]]), lambda f, b: np.full((len(f), 3), 0.5))
    # in front (z = -0.5: nearer the camera at z = -2), x in [-0.6, -0.1) m at z = 0 maps to columns 3.2 .. 7.2
    front = (np.array([[-0.45, -0.45, -0.5], [-0.075, -0.45, -0.5], [-0.075, 0.45, -0.5], [-0.45, 0.45, -0.5]]),
             np.array([[0, 1, 2], [0, 2, 3]]), lambda f, b: np.full((len(f), 3), 0.9))
    K = np.array([[[8.0, 0, 8], [0, 8.0, 8], [0, 0, 1]]])  # 2 m away: a pixel is 1/4 m at z = 0
    E = np.eye(4)[None].copy()
    E[0, 2, 3] = 2.0
    rgb, mask, part = render_views([back, front], K, E, 16, 16, ambient=1.0, diffuse=0.0, supersample=supersample)
    assert (part[0][mask[0] == 0] == 0).all()
    assert (part[0][rgb[0, ..., 0] == 230] == 2).all() and (part[0] == 2).sum() > 0  # 0.9 albedo: the front square
    assert (part[0][rgb[0, ..., 0] == 128] == 1).all() and (part[0] == 1).sum() > (part[0] == 2).sum()
    assert set(np.unique(part[0])) == {0, 1, 2}


def test_scene_writes_garment_labels_inside_the_masks(tmp_path):
    """Every image of a built scene has a garment label (garment_masks/), inside its mask, showing the skirt in every
    held-out image; the reader attaches it to each record."""
    from PIL import Image

    from realityavatar.data.i3d import read_i3d

    prefix = build_scene("ci", tmp_path, seed=0, progress=False)
    scene = read_i3d(tmp_path, prefix.name)
    for split in ("train", "novel_view", "novel_pose"):
        for rec in scene.splits[split]:
            g = np.asarray(Image.open(rec.garment_path)) > 0
            m = np.asarray(Image.open(rec.mask_path)) > 0
            assert not (g & ~m).any(), rec.garment_path
            assert split == "train" or g.sum() > 20, rec.garment_path
    missing = scene.splits["novel_view"][0].garment_path
    missing.unlink()
    with pytest.raises(FileNotFoundError, match="garment label .* not found"):
        read_i3d(tmp_path, prefix.name)


def test_failure_mid_write_leaves_no_scene(tmp_path, monkeypatch):
    from realityavatar.data.synthetic import scene

    calls = {"n": 0}
    real = scene.render_views

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] > 3:
            raise RuntimeError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(scene, "render_views", flaky)
    with pytest.raises(RuntimeError, match="disk full"):
        build_scene("ci", tmp_path, seed=0, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_eval_cameras_two_elevations_apart_from_training():
    """The demo's 8 evaluation-only cameras, as far from the subject as the ring's: 4 on the ring's height, 4 at 40
    degrees, each >= 30 degrees from every
    training camera and apart from the ring's held-out ones; each looks at the target (it projects to the centre)."""
    Ks, E = ring_cameras(6, 2.8, 1.2, 0.9, 256, 256)
    train, held = [0, 2, 3, 5], [1, 4]
    K8, E8 = eval_cameras(E[train], E[held], 8, 2.8, 1.2, 0.9, Ks[0])
    target = np.array([0.0, 0.9, 0.0])

    def direction(V):
        d = -V[:3, :3].T @ V[:3, 3] - target
        return d / np.linalg.norm(d)

    eyes = np.stack([-V[:3, :3].T @ V[:3, 3] for V in E8])
    assert np.allclose(np.linalg.norm(eyes - target, axis=1), np.hypot(2.8, 0.3))  # the ring's distance: its scale

    dirs = np.stack([direction(V) for V in E8])
    elev = np.degrees(np.arcsin(dirs[:, 1]))
    assert np.allclose(np.sort(elev), [6.1] * 4 + [40] * 4, atol=0.2)
    sep = np.degrees(np.arccos(np.clip(dirs @ np.stack([direction(E[c]) for c in train + held]).T, -1, 1)))
    assert sep[:, :4].min() >= 30 - 1e-6 and sep[:, 4:].min() > 10  # apart from training and the ring's held-out
    assert len({tuple(np.round(d, 6)) for d in dirs}) == 8
    for K, V in zip(K8, E8):
        x = V[:3, :3] @ target + V[:3, 3]
        assert np.allclose((K @ x)[:2] / x[2], 128)
    with pytest.raises(ValueError, match="eval_cameras: expected an even count"):
        eval_cameras(E[train], E[held], 3, 2.8, 1.2, 0.9, Ks[0])


def test_cameras_opencv_convention():
    Ks, E = ring_cameras(6, 2.8, 1.2, 0.9, 256, 256)
    assert novel_view_ids(6, 2) == [1, 4]
    target = np.array([0.0, 0.9, 0.0])
    for K, V in zip(Ks, E):
        assert np.allclose(V[:3, :3] @ V[:3, :3].T, np.eye(3), atol=1e-9)
        for point, check in ((target, lambda u, v: abs(u - 128) < 1e-6 and abs(v - 128) < 1e-6),
                             (target + [0, 0.5, 0], lambda u, v: v < 128)):  # world up -> image up (y down)
            x = V[:3, :3] @ point + V[:3, 3]
            assert x[2] > 0
            u, v = (K @ x)[:2] / x[2]
            assert check(u, v)
    E0 = look_at(np.array([0.0, 1.0, 3.0]), np.zeros(3))
    assert np.allclose(-E0[:3, :3].T @ E0[:3, 3], [0, 1, 3])


@pytest.mark.parametrize("name", MOTIONS)
def test_motions_shapes_and_split(name, body):
    m = make_motion(name, 25.0, 100, 30, body.rest_joints[0].numpy(), 0.95, seed=0)
    assert m.pose.shape == (130, 24, 3) and m.Rh.shape == m.Th.shape == (130, 3)
    assert np.all(m.pose[:, 0] == 0) and np.isfinite(m.pose).all()
    # The held-out continuation holds poses not seen in training.
    assert np.abs(m.pose[100:] - m.pose[99]).max() + np.abs(m.Rh[100:] - m.Rh[99]).max() > 0.05
    other = make_motion(name, 25.0, 100, 30, body.rest_joints[0].numpy(), 0.95, seed=1)
    assert not np.array_equal(m.Rh, other.Rh) or not np.array_equal(m.pose, other.pose)


def test_garment_hysteresis_after_spin(body):
    """Same body pose before the spin and after the abrupt stop, yet the hem differs (> 5 cm mean) and keeps
    swinging after the stop with a speed that decays."""
    from realityavatar.data.synthetic.cloth import simulate_garment
    from realityavatar.data.synthetic.scene import body_sequence

    fps = 25.0
    rest = body.rest_vertices.numpy()
    pelvis = body.rest_joints[0].numpy().astype(np.float64)
    m = make_motion("spin", fps, 110, 1, pelvis, float(pelvis[1] - rest[:, 1].min()), seed=0)
    a, s = m.events["spin_start_frame"], m.events["spin_stop_frame"]
    # Identical body pose and placement (the yaw differs by exactly one turn).
    assert np.array_equal(m.pose[a], m.pose[s]) and np.array_equal(m.Rh[a], m.Rh[s])
    assert np.array_equal(m.Th[a], m.Th[s])
    assert np.array_equal(m.pose[s], m.pose[-1]) and np.array_equal(m.Rh[s], m.Rh[-1])  # still after the stop
    _, _, joints, rots = body_sequence(body, m)
    g = simulate_garment(joints, rots, fps, "skirt", None, seed=0)
    ring = g.uv[:, 1] == g.uv[:, 1].max()  # the hem ring (v = 1)
    hem = g.vertices[:, ring]  # [F,H,3]
    diff = np.linalg.norm(hem[a] - hem[s], axis=-1).mean()
    assert diff > 0.05, f"hem differs by only {diff:.3f} m at identical poses"
    speed = np.linalg.norm(np.diff(hem, axis=0), axis=-1).mean(1) * fps  # [F-1] m/s, speed[f] from f to f+1
    early = speed[s:s + int(0.5 * fps)].mean()
    late = speed[s + int(1.5 * fps):s + int(2.3 * fps)].mean()
    assert early > 0.3, f"hem nearly still right after the stop ({early:.3f} m/s)"
    assert late < 0.5 * early, f"hem speed does not decay ({early:.3f} -> {late:.3f} m/s)"


def test_resolve_params_names():
    p = resolve_params("demo", sequence="dress_walk")
    assert p["garment"] == "dress" and p["motion"] == "walk" and p["name"] == "dress_walk_demo"
    assert p["width"] == 256 and p["cameras"] == 6 and p["novel_view_cameras"] == 2


def test_two_builds_of_one_scene_at_once_ray_cast_it_once(tmp_path, monkeypatch):
    """The jobs of a sweep that find the scene missing at the same moment: one writes it, the other waits for it and
    reuses it (before, both ray cast it and replaced each other's files under a reader)."""
    import multiprocessing as mp

    from realityavatar.data.synthetic import cloth, scene

    ctx = mp.get_context("fork")
    both_checked = ctx.Barrier(2, timeout=120)  # both are past the first "is it built?" before either writes
    simulate, write, log = cloth.simulate_garment, scene._write, tmp_path / "writers.txt"

    def simulate_then_meet(*a, **k):
        out = simulate(*a, **k)
        both_checked.wait()
        return out

    def logged_write(*a, **k):
        with open(log, "a") as f:
            f.write(f"{os.getpid()}\n")
        return write(*a, **k)

    monkeypatch.setattr(cloth, "simulate_garment", simulate_then_meet)  # build_scene imports it when it runs
    monkeypatch.setattr(scene, "_write", logged_write)
    small = {"width": 16, "height": 16, "supersample": 1, "train_frames": 16, "novel_frames": 4}
    jobs = [ctx.Process(target=build_scene, args=("ci", tmp_path / "scenes"),
                        kwargs={"seed": 0, "overrides": small, "progress": False}) for _ in range(2)]
    for j in jobs:
        j.start()
    for j in jobs:
        j.join(300)
    assert [j.exitcode for j in jobs] == [0, 0]
    assert len(log.read_text().split()) == 1  # one process wrote the scene
    prefix = build_scene("ci", tmp_path / "scenes", seed=0, overrides=small, progress=False)
    assert scene.is_built(prefix, json.loads(scene_paths(prefix)["meta"].read_text())["params_hash"])
