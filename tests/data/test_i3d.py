"""Readers on fixture folders written in the exact layouts: I3D-Human/HumanNeRF, ZJU-MoCap (ARAH), BYO capture, SMPL."""

from __future__ import annotations

import json
import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).parent))
from fixtures_data import SIZE, RandomBody, camera, project, write_i3d, write_zju

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.capture import CaptureError, convert, scan
from realityavatar.data.capture import main as capture_main
from realityavatar.data.i3d import read_i3d
from realityavatar.data.poses import PoseTable
from realityavatar.data.records import SceneFormatError, load_record, undistort_grid
from realityavatar.data.zju import read_zju


@pytest.fixture(scope="module")
def body():
    return RandomBody()


@pytest.fixture()
def i3d(tmp_path, body):
    w = write_i3d(tmp_path, "seq", body, train_frames=(0, 1, 2, 3), pose_frames=(4, 5), train_views=(0, 1),
                  test_views=(2,))
    return tmp_path, w


def pixel_in_mask(mask: np.ndarray, uv) -> bool:
    x, y = int(np.floor(uv[0])), int(np.floor(uv[1]))
    return 0 <= x < mask.shape[1] and 0 <= y < mask.shape[0] and bool(mask[y, x])


# ---------------------------------------------------------------- I3D-Human layout


def test_i3d_cameras_poses_splits_as_written(i3d, body):
    root, w = i3d
    scene = read_i3d(root, "seq", body.rest_joints[0])
    assert set(scene.splits) == {"train", "novel_view", "novel_pose"}
    assert scene.frames("train").tolist() == [0, 1, 2, 3] and scene.views("train") == [0, 1]
    assert scene.frames("novel_view").tolist() == [0, 1, 2, 3] and scene.views("novel_view") == [2]
    assert scene.frames("novel_pose").tolist() == [4, 5] and scene.views("novel_pose") == [2]
    for rec in scene.splits["train"] + scene.splits["novel_pose"]:
        K, E = w["cameras"][rec.view]
        np.testing.assert_allclose(rec.K, K)
        np.testing.assert_allclose(rec.viewmat, E)
        assert rec.image_path.name == f"frame_{rec.frame:06d}_view_{rec.view:02d}.png"
    # poses: the union of all splits, converted Rh/Th -> SMPL with the body's pelvis
    p_ref, t_ref = rh_th_to_smpl(torch.as_tensor(w["poses"]).reshape(-1, 24, 3), torch.as_tensor(w["Rh"]),
                                 torch.as_tensor(w["Th"]), body.rest_joints[0].double())
    assert scene.poses.frames.tolist() == w["frames"]
    torch.testing.assert_close(scene.poses.poses, p_ref.float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.poses.transl, t_ref.float(), atol=1e-5, rtol=0)
    # non-root joints are passed through untouched
    np.testing.assert_allclose(scene.poses.poses[:, 1:].numpy(), w["poses"].reshape(-1, 24, 3)[:, 1:], atol=1e-6)


def test_i3d_joint_projects_inside_its_mask(i3d, body):
    root, _ = i3d
    scene = read_i3d(root, "seq", body.rest_joints[0])
    for split, recs in scene.splits.items():
        for rec in recs:
            pose, transl = scene.poses.get(rec.frame)
            pelvis = body.joints(pose, transl)[0].numpy()
            _, mask, K = load_record(rec)
            assert pixel_in_mask(mask, project(K, rec.viewmat, pelvis)), (split, rec.frame, rec.view)


def test_i3d_wrong_pelvis_misplaces_the_joint(i3d, body):
    """The check above can fail: converting with a different pelvis moves the joint out of its disc."""
    root, _ = i3d
    scene = read_i3d(root, "seq", body.rest_joints[0] + torch.tensor([1.5, 1.5, 1.5]))
    misses = 0
    for rec in scene.splits["train"]:
        pose, transl = scene.poses.get(rec.frame)
        _, mask, K = load_record(rec)
        misses += not pixel_in_mask(mask, project(K, rec.viewmat, body.joints(pose, transl)[0].numpy()))
    assert misses > 0


def test_i3d_pelvis_falls_back_to_canonical_joints(i3d, body):
    root, _ = i3d
    a, b = read_i3d(root, "seq", None), read_i3d(root, "seq", body.rest_joints[0])
    torch.testing.assert_close(a.poses.transl, b.poses.transl)


def test_missing_scene_folder_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"scene folder .*nothere-train not found"):
        read_i3d(tmp_path, "nothere", torch.zeros(3), build_hint="build it with realityavatar-make-scene")


def test_missing_pickle_key_names_file_and_field(i3d, body):
    root, _ = i3d
    path = root / "seq-novelpose" / "mesh_infos.pkl"
    infos = pickle.loads(path.read_bytes())
    del infos[next(iter(infos))]["Th"]
    path.write_bytes(pickle.dumps(infos))
    with pytest.raises(SceneFormatError, match=r"seq-novelpose/mesh_infos\.pkl.*lacks key 'Th'"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_missing_camera_key_names_file(i3d, body):
    root, _ = i3d
    path = root / "seq-train" / "cameras.pkl"
    cams = pickle.loads(path.read_bytes())
    del cams[next(iter(cams))]["extrinsics"]
    path.write_bytes(pickle.dumps(cams))
    with pytest.raises(SceneFormatError, match=r"seq-train/cameras\.pkl.*lacks key 'extrinsics'"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_missing_pickle_file_and_truncated_pickle(i3d, body):
    root, _ = i3d
    (root / "seq-novelview" / "cameras.pkl").write_bytes(b"\x80\x04garbage")
    with pytest.raises(SceneFormatError, match=r"seq-novelview/cameras\.pkl: not a readable pickle"):
        read_i3d(root, "seq", body.rest_joints[0])
    (root / "seq-novelview" / "cameras.pkl").unlink()
    with pytest.raises(FileNotFoundError, match=r"seq-novelview/cameras\.pkl not found"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_nan_pose_is_reported_at_load(i3d, body):
    root, _ = i3d
    path = root / "seq-train" / "mesh_infos.pkl"
    infos = pickle.loads(path.read_bytes())
    name = "frame_000002_view_01"
    infos[name]["poses"] = infos[name]["poses"].copy()
    infos[name]["poses"][10] = np.nan
    path.write_bytes(pickle.dumps(infos))
    with pytest.raises(SceneFormatError, match=r"seq-train/mesh_infos\.pkl: non-finite .* frames \[2\]"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_corrupt_image_names_file(i3d, body):
    root, _ = i3d
    scene = read_i3d(root, "seq", body.rest_joints[0])
    rec = scene.splits["train"][1]
    rec.image_path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(OSError, match=rf"image .*{rec.image_path.name} is corrupt"):
        load_record(rec)


def test_mask_size_mismatch_names_both_files(i3d, body):
    root, _ = i3d
    rec = read_i3d(root, "seq", body.rest_joints[0]).splits["train"][0]
    Image.fromarray(np.zeros((10, 12), np.uint8)).save(rec.mask_path)
    with pytest.raises(SceneFormatError, match=rf"mask .*{rec.mask_path.name} is 12x10 but image"):
        load_record(rec)


# ---------------------------------------------------------------- pose windows


def test_pose_window_clamps_at_sequence_start():
    frames = np.arange(10, 20)
    poses = torch.arange(10, 20, dtype=torch.float32)[:, None, None].expand(10, 24, 3)
    table = PoseTable(frames, poses, torch.zeros(10, 3))
    p, t = table.window(12, window_len=4, window_step=1)
    assert t.shape == (4, 3)
    assert p[:, 0, 0].tolist() == [10, 10, 11, 12]  # t-3 = 9 is before the start: clamped to 10
    p, _ = table.window(19, window_len=3, window_step=4)
    assert p[:, 0, 0].tolist() == [11, 15, 19]
    p, _ = table.window(10, window_len=6, window_step=25)
    assert p[:, 0, 0].tolist() == [10] * 6


def test_pose_window_on_subsampled_table_takes_latest_earlier_frame():
    frames = np.array([0, 10, 20, 30])
    table = PoseTable(frames, torch.as_tensor(frames, dtype=torch.float32)[:, None, None].expand(4, 24, 3),
                      torch.zeros(4, 3))
    p, _ = table.window(30, window_len=3, window_step=7)  # targets 16, 23, 30
    assert p[:, 0, 0].tolist() == [10, 20, 30]
    with pytest.raises(KeyError, match="frame 25 has no pose"):
        table.window(25, 2, 1)


def test_pose_table_rejects_nan():
    poses = torch.zeros(3, 24, 3)
    poses[1, 4, 2] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite .* frames \[8\]"):
        PoseTable([7, 8, 9], poses, torch.zeros(3, 3), source="test")


# ---------------------------------------------------------------- ZJU-MoCap (ARAH layout)


def test_zju_cameras_poses_splits_and_masks(tmp_path, body):
    w = write_zju(tmp_path, "CoreView_377", body, n_frames=6, cams=("1", "2", "3"))
    scene = read_zju(tmp_path / "CoreView_377", [1], [2, 3], [0, 4, 1], [0, 4, 2], [4, 0, 1])
    assert scene.frames("train").tolist() == [0, 1, 2, 3] and scene.views("train") == [1]
    assert scene.frames("novel_view").tolist() == [0, 2] and scene.views("novel_view") == [2, 3]
    assert scene.frames("novel_pose").tolist() == [4, 5]
    torch.testing.assert_close(scene.poses.poses, torch.as_tensor(w["pose"], dtype=torch.float32))
    torch.testing.assert_close(scene.poses.transl, torch.as_tensor(w["trans"], dtype=torch.float32))
    for recs in scene.splits.values():
        for rec in recs:
            K, E = camera(rec.view)
            np.testing.assert_allclose(rec.viewmat, E, atol=1e-12)
            np.testing.assert_allclose(rec.K, K)
            _, mask, K2 = load_record(rec)
            assert pixel_in_mask(mask, project(K2, rec.viewmat, w["pelvis_world"][rec.frame]))
            assert 50 < mask.sum() < 120  # 0/1 label masks are read as the person, not as background


def test_zju_missing_image_and_overlapping_split(tmp_path, body):
    write_zju(tmp_path, "CoreView_377", body, n_frames=4, cams=("1", "2"))
    (tmp_path / "CoreView_377" / "2" / "000001.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"CoreView_377/2/000001\.jpg not found"):
        read_zju(tmp_path / "CoreView_377", [1], [2], [0, 0, 1], [0, 0, 1])
    with pytest.raises(ValueError, match="overlaps the training frames"):
        read_zju(tmp_path / "CoreView_377", [1], [2], [0, 3, 1], None, [2, 0, 1])
    with pytest.raises(FileNotFoundError, match="CoreView_999 not found"):
        read_zju(tmp_path / "CoreView_999", [1], [2], [0, 0, 1])


def test_zju_missing_model_key_names_file(tmp_path, body):
    write_zju(tmp_path, "CoreView_377", body, n_frames=3, cams=("1", "2"))
    f = tmp_path / "CoreView_377" / "models" / "000001.npz"
    d = dict(np.load(f))
    del d["pose_hand"]
    np.savez(f, **d)
    with pytest.raises(SceneFormatError, match=r"models/000001\.npz: the file lacks key 'pose_hand'"):
        read_zju(tmp_path / "CoreView_377", [1], [2], [0, 0, 1])


def test_undistort_grid_identity_and_barrel():
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    g0 = undistort_grid(K, np.zeros(5), 64, 64)[0]
    lin = torch.linspace(-1, 1, 64)
    torch.testing.assert_close(g0[..., 0], lin[None].expand(64, 64), atol=1e-5, rtol=0)
    g1 = undistort_grid(K, np.array([0.2, 0, 0, 0, 0]), 64, 64)[0]
    assert g1[0, 0, 0] < g0[0, 0, 0] and g1[0, 0, 1] < g0[0, 0, 1]  # corners sample further out (k1 > 0)
    torch.testing.assert_close(g1[32, 32], g0[32, 32], atol=0.02, rtol=0)  # centre barely moves


# ---------------------------------------------------------------- SMPL through smplx


def fake_smpl_arrays(n_verts: int = 40, seed: int = 0) -> dict:
    from realityavatar.body.base import SMPL_PARENTS

    rng = np.random.default_rng(seed)
    w = rng.random((n_verts, 24))
    return {
        "v_template": rng.normal(0, 0.3, (n_verts, 3)), "shapedirs": rng.normal(0, 0.01, (n_verts, 3, 10)),
        "posedirs": np.zeros((n_verts, 3, 207)), "J_regressor": rng.random((24, n_verts)) / n_verts,
        "weights": w / w.sum(1, keepdims=True), "f": rng.integers(0, n_verts, (30, 3)),
        "kintree_table": np.array([[4294967295] + list(SMPL_PARENTS[1:]), list(range(24))]),
    }


def test_smpl_missing_files_names_expected_files(tmp_path):
    from realityavatar.body.smpl import SMPLBody

    with pytest.raises(FileNotFoundError, match=r"SMPL_NEUTRAL\.pkl.*SMPL_NEUTRAL\.npz.*smpl\.is\.tue\.mpg\.de"):
        SMPLBody(model_dir=str(tmp_path))
    with pytest.raises(FileNotFoundError, match=r"SMPL_FEMALE\.pkl"):
        SMPLBody(model_dir=str(tmp_path / "nope"), gender="female")
    with pytest.raises(FileNotFoundError, match="body.model_dir is not set"):
        SMPLBody(model_dir=None)


def test_smpl_npz_loads_through_smplx(tmp_path):
    from realityavatar.body.smpl import SMPLBody

    a = fake_smpl_arrays()
    np.savez(tmp_path / "SMPL_NEUTRAL.npz", **a)
    betas = np.linspace(-1, 1, 10)
    np.savez(tmp_path / "000000.npz", betas=betas[None])  # ZJU models/*.npz store betas as [1,10]
    b = SMPLBody(model_dir=str(tmp_path), betas=str(tmp_path / "000000.npz"))
    v = a["v_template"] + a["shapedirs"] @ betas
    np.testing.assert_allclose(b.rest_vertices.numpy(), v, atol=1e-5)
    np.testing.assert_allclose(b.rest_joints.numpy(), a["J_regressor"] @ v, atol=1e-5)
    assert b.skin_weights.shape == (40, 24) and b.faces.shape == (30, 3)
    A = b(torch.zeros(24, 3), torch.zeros(3))
    torch.testing.assert_close(A, torch.eye(4).expand(24, 4, 4), atol=1e-5, rtol=0)


def test_smpl_chumpy_pickle_gives_clear_error(tmp_path, monkeypatch):
    from realityavatar.body.smpl import SMPLBody

    fake = types.ModuleType("chumpy")

    class Ch:  # stands in for chumpy.Ch inside an original SMPL pickle
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy", "Ch"
    fake.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", fake)
    data = {**fake_smpl_arrays(), "v_template": Ch()}
    (tmp_path / "SMPL_MALE.pkl").write_bytes(pickle.dumps(data))
    monkeypatch.delitem(sys.modules, "chumpy")
    with pytest.raises(RuntimeError, match=r"SMPL_MALE\.pkl: .*chumpy.*\.npz"):
        SMPLBody(model_dir=str(tmp_path), gender="male")


# ---------------------------------------------------------------- bring your own capture


def write_capture(folder: Path, body, frames=range(6), cams=(0, 1, 2), seed=3):
    """A BYO capture: cameras.json, images/<cam>/<frame>.png, masks/<cam>/<frame>.png, smpl/<frame>.npz."""
    from fixtures_data import draw, motion, world_pelvis

    poses, Rh, Th = motion(list(frames), seed)
    # half the frames in SMPL convention (poses[:3] = orientation, transl), half in EasyMocap placement (Rh, Th)
    pelvis_w = world_pelvis(body, poses, Rh, Th)
    smpl_pose, smpl_transl = rh_th_to_smpl(torch.as_tensor(poses).reshape(-1, 24, 3), torch.as_tensor(Rh),
                                           torch.as_tensor(Th), body.rest_joints[0].double())
    (folder / "smpl").mkdir(parents=True)
    cams_json = {}
    for c in cams:
        K, E = camera(c)
        cams_json[str(c)] = {"K": K.tolist(), "R": E[:3, :3].tolist(), "T": E[:3, 3].tolist(), "D": [0.0] * 5}
        (folder / "images" / str(c)).mkdir(parents=True)
        (folder / "masks" / str(c)).mkdir(parents=True)
        for i, f in enumerate(frames):
            img, mask = draw(project(K, E, pelvis_w[i]), (10, 200, 30))
            img[mask == 0] = (120, 120, 120)  # a real background the converter must black out
            Image.fromarray(img).save(folder / "images" / str(c) / f"{f:06d}.jpg", quality=98)
            Image.fromarray(mask).save(folder / "masks" / str(c) / f"{f:06d}.png")
    for i, f in enumerate(frames):
        if i % 2 == 0:
            np.savez(folder / "smpl" / f"{f:06d}.npz", poses=smpl_pose[i].reshape(72).numpy(),
                     transl=smpl_transl[i].numpy())
        else:
            (folder / "smpl" / f"{f:06d}.json").write_text(
                json.dumps({"poses": poses[i].tolist(), "Rh": Rh[i].tolist(), "Th": Th[i].tolist()}))
    (folder / "cameras.json").write_text(json.dumps(cams_json))
    return {"pose": smpl_pose.float(), "transl": smpl_transl.float(), "pelvis_world": pelvis_w}


def test_capture_converter_round_trips(tmp_path, body):
    w = write_capture(tmp_path / "cap", body)
    out = convert(tmp_path / "cap", tmp_path / "out", "mine", train_views=[0, 1], test_views=[2], novel_pose_from=4,
                  body=body)
    assert out == tmp_path / "out" / "mine-train"
    scene = read_i3d(tmp_path / "out", "mine", body.rest_joints[0])
    assert scene.frames("train").tolist() == [0, 1, 2, 3] and scene.views("train") == [0, 1]
    assert scene.frames("novel_view").tolist() == [0, 1, 2, 3] and scene.views("novel_view") == [2]
    assert scene.frames("novel_pose").tolist() == [4, 5] and scene.views("novel_pose") == [2]
    torch.testing.assert_close(scene.poses.poses, w["pose"], atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.poses.transl, w["transl"], atol=1e-5, rtol=0)
    for recs in scene.splits.values():
        for rec in recs:
            K, E = camera(rec.view)
            np.testing.assert_allclose(rec.K, K, atol=1e-5)
            np.testing.assert_allclose(rec.viewmat, E, atol=1e-5)
            img, mask, K2 = load_record(rec)
            assert pixel_in_mask(mask, project(K2, rec.viewmat, w["pelvis_world"][rec.frame]))
            assert img[~mask].max() == 0  # background blacked out, as the layout promises
    infos = pickle.loads((tmp_path / "out" / "mine-train" / "mesh_infos.pkl").read_bytes())
    assert set(infos["frame_000000_view_00"]) == {"poses", "Rh", "Th", "joints", "tpose_joints"}


def test_capture_validation_reports_every_problem_at_once(tmp_path, body, capsys):
    cap = tmp_path / "cap"
    write_capture(cap, body)
    (cap / "images" / "1" / "000003.jpg").unlink()  # a missing frame
    (cap / "masks" / "2" / "000005.png").unlink()  # a missing mask (counts now mismatch)
    d = dict(np.load(cap / "smpl" / "000002.npz"))
    d["transl"] = np.array([0.0, np.nan, 0.0])
    np.savez(cap / "smpl" / "000002.npz", **d)  # a non-finite value
    cams = json.loads((cap / "cameras.json").read_text())
    del cams["0"]["K"]  # a camera without intrinsics
    (cap / "cameras.json").write_text(json.dumps(cams))
    (cap / "images" / "2" / "000001.jpg").write_bytes(b"not a jpeg")  # a corrupt image
    problems, *_ = scan(cap, train_views=[0, 1], test_views=[2, 7])
    text = "\n".join(problems)
    for needle in ("camera '0': missing K", "images/1: missing images for frames [3]",
                   "masks/2: missing masks for frames [5]", "camera 2: 6 images but 5 masks", "smpl/000002.npz: non-finite values",
                   "images/2/000001.jpg: corrupt", "test_views: camera 7 is not in cameras.json"):
        assert needle in text, (needle, text)
    with pytest.raises(CaptureError) as e:
        convert(cap, tmp_path / "out", "bad", [0, 1], [2, 7], body=body)
    assert len(e.value.problems) == len(problems) >= 7
    assert not (tmp_path / "out").exists()  # nothing written for an invalid capture
    assert capture_main(["validate", str(cap)]) == 1
    assert "problem(s)" in capsys.readouterr().err


def test_capture_cli_converts(tmp_path, body, capsys):
    write_capture(tmp_path / "cap", body, frames=range(3), cams=(0, 1))
    assert capture_main(["validate", str(tmp_path / "cap")]) == 0
    rc = capture_main(["convert", str(tmp_path / "cap"), str(tmp_path / "out"), "--name", "cli", "--train-views", "0",
                       "--test-views", "1", "--novel-pose-from", "2"])
    assert rc == 0, capsys.readouterr().err
    assert "realityavatar-train data=capture" in capsys.readouterr().out
    scene = read_i3d(tmp_path / "out", "cli")  # written with the mannequin: pelvis from canonical_joints.pkl
    assert scene.frames("novel_pose").tolist() == [2]
    assert SIZE == load_record(scene.splits["train"][0])[0].shape[0]
