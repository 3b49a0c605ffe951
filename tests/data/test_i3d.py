"""The I3D-Human/HumanNeRF reader on fixture folders in the exact layout, and its clear errors."""

from __future__ import annotations

import logging
import pickle
from contextlib import contextmanager

import numpy as np
import pytest
import torch
from PIL import Image

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.i3d import read_i3d
from realityavatar.data.records import SceneFormatError, load_record, undistort_grid
from tests.fixtures_data import RandomBody, pixel_in_mask, project, write_i3d, write_i3d_release


@pytest.fixture(scope="module")
def body():
    return RandomBody()


@pytest.fixture()
def i3d(tmp_path, body):
    w = write_i3d(tmp_path, "seq", body, train_frames=(0, 1, 2, 3), pose_frames=(4, 5), train_views=(0, 1),
                  test_views=(2,))
    return tmp_path, w


@contextmanager
def edited(path):
    """A fixture pickle to change in place: yields its entries and writes them back."""
    entries = pickle.loads(path.read_bytes())
    yield entries
    path.write_bytes(pickle.dumps(entries))


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


@pytest.mark.parametrize("file, key, match", [
    ("seq-novelpose/mesh_infos.pkl", "Th", r"seq-novelpose/mesh_infos\.pkl.*lacks key 'Th'"),
    ("seq-train/cameras.pkl", "extrinsics", r"seq-train/cameras\.pkl.*lacks key 'extrinsics'"),
])
def test_missing_pickle_key_names_file_and_field(i3d, body, file, key, match):
    root, _ = i3d
    with edited(root / file) as entries:
        del entries[next(iter(entries))][key]
    with pytest.raises(SceneFormatError, match=match):
        read_i3d(root, "seq", body.rest_joints[0])


def test_missing_pickle_file_and_truncated_pickle(i3d, body):
    root, _ = i3d
    (root / "seq-novelview" / "cameras.pkl").write_bytes(b"\x80\x04garbage")
    with pytest.raises(SceneFormatError, match=r"seq-novelview/cameras\.pkl: not a readable pickle"):
        read_i3d(root, "seq", body.rest_joints[0])
    (root / "seq-novelview" / "cameras.pkl").unlink()
    with pytest.raises(FileNotFoundError, match=r"seq-novelview/cameras\.pkl not found"):
        read_i3d(root, "seq", body.rest_joints[0])


@pytest.mark.parametrize("extrinsics, match", [
    (np.zeros((4, 4)), r"is not a rotation \(\|R R\^T - I\| = 1\)"),        # a zeroed matrix was read as a camera
    (np.diag([1.0, 1.0, -1.0, 1.0]), r"is a reflection \(det < 0\)"),           # a mirrored image
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]), r"has a last row \[0\.0, 0\.0, 1\.0, 1\.0\]"),
])
def test_extrinsics_that_are_no_rigid_transform_name_the_entry(i3d, body, extrinsics, match):
    root, _ = i3d
    with edited(root / "seq-novelview" / "cameras.pkl") as cams:
        cams["frame_000001_view_02"]["extrinsics"] = extrinsics
    with pytest.raises(SceneFormatError, match=r"seq-novelview/cameras\.pkl: entry 'frame_000001_view_02'\['extrinsics'\] "
                                               + match):
        read_i3d(root, "seq", body.rest_joints[0])


def test_intrinsics_without_positive_focal_lengths_name_the_entry(i3d, body):
    root, _ = i3d
    with edited(root / "seq-train" / "cameras.pkl") as cams:
        cams["frame_000002_view_01"]["intrinsics"] = np.diag([0.0, 0.0, 1.0])
    with pytest.raises(SceneFormatError, match=r"seq-train/cameras\.pkl: entry 'frame_000002_view_01'\['intrinsics'\] "
                                               r"has focal lengths fx, fy = 0, 0, expected both > 0"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_a_mask_without_its_image_names_it(i3d, body):
    """An image lost in a copy: its mask, camera and pose entries are still there, and the split was read without that
    frame and view, without a word."""
    root, _ = i3d
    (root / "seq-novelpose" / "images" / "frame_000005_view_02.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"seq-novelpose/images: no image for the mask\(s\) "
                                                r"frame_000005_view_02\.png in .*seq-novelpose/masks"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_nan_pose_is_reported_at_load(i3d, body):
    root, _ = i3d
    with edited(root / "seq-train" / "mesh_infos.pkl") as infos:
        name = "frame_000002_view_01"
        infos[name]["poses"] = infos[name]["poses"].copy()
        infos[name]["poses"][10] = np.nan
    with pytest.raises(SceneFormatError, match=r"seq-train/mesh_infos\.pkl: non-finite .* frames \[2\]"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_views_that_disagree_on_a_frames_fit_are_refused(i3d, body):
    """Per-image entries of one frame carry one world-frame fit; a per-camera fit would be read as the first view's."""
    root, _ = i3d
    with edited(root / "seq-train" / "mesh_infos.pkl") as infos:
        name = "frame_000002_view_01"  # its own dict: the writer's views of a frame share one, and pickle keeps that
        infos[name] = dict(infos[name], Th=infos[name]["Th"] + 0.01)
    with pytest.raises(SceneFormatError, match=r"seq-train/mesh_infos\.pkl: entries 'frame_000002_view_00' and "
                                               r"'frame_000002_view_01' give frame 2 different Th \(by up to 0\.01\)"):
        read_i3d(root, "seq", body.rest_joints[0])


def test_splits_that_disagree_on_a_frames_pose_are_refused(i3d, body):
    root, _ = i3d
    with edited(root / "seq-novelview" / "mesh_infos.pkl") as infos:
        for name in [n for n in infos if n.startswith("frame_000001")]:
            infos[name]["poses"] = infos[name]["poses"] + 0.05
    with pytest.raises(ValueError, match=r"frame 1 has different poses in .*seq-train/mesh_infos\.pkl and "
                                         r".*seq-novelview/mesh_infos\.pkl"):
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


def test_undistort_grid_identity_and_barrel():
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    g0 = undistort_grid(K, np.zeros(5), 64, 64)[0]
    lin = torch.linspace(-1, 1, 64)
    torch.testing.assert_close(g0[..., 0], lin[None].expand(64, 64), atol=1e-5, rtol=0)
    g1 = undistort_grid(K, np.array([0.2, 0, 0, 0, 0]), 64, 64)[0]
    assert g1[0, 0, 0] < g0[0, 0, 0] and g1[0, 0, 1] < g0[0, 0, 1]  # corners sample further out (k1 > 0)
    torch.testing.assert_close(g1[32, 32], g0[32, 32], atol=0.02, rtol=0)  # centre barely moves


# ---------------------------------------------------------------------- the release layout: dense frameid_pose.pkl

def _dense_smpl(w, body, frames):
    """The fixture's dense motion at `frames`, converted as the reader converts it: poses [N,24,3], transl [N,3]."""
    idx = np.asarray(frames)
    p, t = rh_th_to_smpl(torch.as_tensor(w["poses"][idx]).reshape(-1, 24, 3), torch.as_tensor(w["Rh"][idx]),
                         torch.as_tensor(w["Th"][idx]), body.rest_joints[0].double())
    return p.float(), t.float()


@pytest.mark.parametrize("frame_interval", [1, 3])
def test_release_windows_hold_the_dense_poses(tmp_path, body, frame_interval):
    """Image folders every 5th / 10th frame, frameid_pose.pkl dense: every window of every split holds the poses of
    frames t - k*s (read as Dyco reads the file: entry (t - k*s) // frame_interval, targets before 0 on frame 0;
    the last entry the frame's own fit), where snapping to the stored image frames would give other poses."""
    w = write_i3d_release(tmp_path, "rel", body, frame_interval=frame_interval)
    write_i3d_release(tmp_path / "sparse", "rel", body, frameid_pose=False)  # the same motion, without the file
    scene = read_i3d(tmp_path, "rel", body.rest_joints[0], frame_interval=frame_interval)
    snapped = read_i3d(tmp_path / "sparse", "rel", body.rest_joints[0]).poses
    assert scene.meta["pose_windows"].startswith("exact") and snapped.dense_every is None
    T, s = 6, 7
    differs = 0
    for split, recs in scene.splits.items():
        for f in sorted({r.frame for r in recs}):
            targets = np.maximum(f - s * np.arange(T - 1, -1, -1), 0) // frame_interval * frame_interval
            targets[-1] = f
            p_ref, t_ref = _dense_smpl(w, body, targets)
            p, t = scene.poses.window(f, T, s)
            where = f"{split} frame {f}"
            assert torch.allclose(p, p_ref, atol=1e-5, rtol=0), (where, (p - p_ref).abs().max())
            assert torch.allclose(t, t_ref, atol=1e-5, rtol=0), (where, (t - t_ref).abs().max())
            differs += not torch.allclose(snapped.window(f, T, s)[0], p_ref, atol=1e-5)
    assert differs > 0, "the fixture cannot tell exact windows from snapped ones"


def test_release_without_frameid_pose_warns_windows_are_approximate(tmp_path, body, caplog):
    write_i3d_release(tmp_path, "rel", body, frameid_pose=False)
    with caplog.at_level(logging.WARNING, logger="realityavatar.data.i3d"):
        scene = read_i3d(tmp_path, "rel", body.rest_joints[0])
    assert scene.poses.dense_every is None and scene.meta["pose_windows"].startswith("approximate")
    assert "no frameid_pose.pkl in rel-train, rel-novelview, rel-novelpose" in caplog.text
    assert "approximate" in caplog.text


def test_folders_holding_every_frame_need_no_frameid_pose(i3d, body, caplog):
    """The synthetic scenes' folders hold every frame from 0: their windows are exact without the file, no warning."""
    root, _ = i3d
    with caplog.at_level(logging.WARNING, logger="realityavatar.data.i3d"):
        scene = read_i3d(root, "seq", body.rest_joints[0])
    assert scene.meta["pose_windows"].startswith("exact") and "frameid_pose" not in caplog.text


def test_a_window_target_without_a_pose_names_the_file_and_frame(tmp_path, body):
    """frameid_pose.pkl cut short: the window of a later frame reads a frame the file does not hold."""
    write_i3d_release(tmp_path, "rel", body)
    for folder in ("rel-train", "rel-novelview", "rel-novelpose"):
        with edited(tmp_path / folder / "frameid_pose.pkl") as entries:
            del entries[30:]
    scene = read_i3d(tmp_path, "rel", body.rest_joints[0])
    scene.poses.window(35, 6, 7)  # targets 0, 1, 14, 21, 28 and the frame's own fit: all there
    with pytest.raises(KeyError, match=r"rel-train/frameid_pose\.pkl.*no pose for frame 33, which the pose window of "
                                       r"frame 40 reads"):
        scene.poses.window(40, 6, 7)


@pytest.mark.parametrize("entry, match", [
    ({"poses": np.zeros((22, 3)), "Rh": np.zeros(3), "Th": np.zeros(3)}, r"entry 4 \(frame 4\) has poses \(22, 3\)"),
    ({"poses": np.zeros((23, 3)), "Th": np.zeros(3)}, r"entry 4 \(frame 4\).*lacks key 'Rh'"),
])
def test_bad_frameid_pose_entry_names_file_and_entry(tmp_path, body, entry, match):
    write_i3d_release(tmp_path, "rel", body)
    with edited(tmp_path / "rel-novelpose" / "frameid_pose.pkl") as entries:
        entries[4] = entry
    with pytest.raises(SceneFormatError, match=r"rel-novelpose/frameid_pose\.pkl.*" + match):
        read_i3d(tmp_path, "rel", body.rest_joints[0])


def test_frameid_pose_that_disagrees_with_mesh_infos_is_refused(tmp_path, body):
    """A file of another sequence (or shifted by a frame_interval mistake) gives the images' frames other poses."""
    write_i3d_release(tmp_path, "rel", body)
    with edited(tmp_path / "rel-train" / "frameid_pose.pkl") as entries:
        entries[15] = dict(entries[15], Th=entries[15]["Th"] + 0.2)
    with pytest.raises(ValueError, match=r"frame 15 has different poses in .*rel-train/mesh_infos\.pkl and "
                                         r".*rel-train/frameid_pose\.pkl"):
        read_i3d(tmp_path, "rel", body.rest_joints[0])


def test_frameid_pose_in_72_values_reads_like_23_by_3(tmp_path, body):
    w = write_i3d_release(tmp_path, "rel", body)
    a = read_i3d(tmp_path, "rel", body.rest_joints[0]).poses.window(45, 6, 7)
    for folder in ("rel-train", "rel-novelview", "rel-novelpose"):
        with edited(tmp_path / folder / "frameid_pose.pkl") as entries:
            for k, e in enumerate(entries):
                e["poses"] = w["poses"][k].astype(np.float32)  # [72], root zero
    b = read_i3d(tmp_path, "rel", body.rest_joints[0]).poses.window(45, 6, 7)
    torch.testing.assert_close(a, b)


def test_write_release_keeps_the_chosen_frames_and_the_whole_motion(i3d, body, tmp_path):
    """A scene of every frame (the builder's) written as a release: sparse image folders, the same windows."""
    import json

    from realityavatar.data.i3d import write_release

    root, _ = i3d
    (root / "seq-meta.json").write_text(json.dumps({"frames": {"train": [0, 4], "novel_pose": [4, 6]}}))
    out = write_release(root / "seq", tmp_path / "release", train_every=2, novel_every=3)
    full = read_i3d(root, "seq", body.rest_joints[0])
    rel = read_i3d(out.parent, "seq", body.rest_joints[0])
    assert rel.frames("train").tolist() == [0, 2] and rel.frames("novel_view").tolist() == [0, 3]
    assert rel.frames("novel_pose").tolist() == [4]
    assert rel.poses.dense_every == 1 and json.loads((out.parent / "seq-meta.json").read_text())["release"]
    for f in (2, 3, 4):
        torch.testing.assert_close(rel.poses.window(f, 3, 1), full.poses.window(f, 3, 1))
    with pytest.raises(ValueError, match="train_every: expected a whole number >= 1"):
        write_release(root / "seq", tmp_path / "release", train_every=0)


def test_i3d_reader_passes_frame_interval(tmp_path, body):
    from realityavatar.data.datamodule import AvatarDataModule
    from realityavatar.data.i3d import I3DReader

    w = write_i3d_release(tmp_path, "rel", body, frame_interval=3)
    dm = AvatarDataModule(str(tmp_path), "rel", I3DReader(frame_interval=3), body=body, window_len=3, window_step=4)
    dm.setup("fit")
    item = next(it for it in dm.datasets["novel_pose"] if it["frame"] == 50)
    p_ref, _ = _dense_smpl(w, body, [42, 45, 50])  # 42 // 3 * 3, 46 // 3 * 3, the frame itself
    torch.testing.assert_close(item["poses"], p_ref, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match=r"data\.reader\.frame_interval: expected a whole number >= 1"):
        I3DReader(frame_interval=0)


def test_make_scene_release_arguments_are_checked_before_building():
    from realityavatar.data.make_scene import main

    with pytest.raises(SystemExit, match=r"--release: expected TRAIN,NOVEL \(two whole numbers >= 1\), got '5'"):
        main(["--release", "5", "--release-root", "x"])
    with pytest.raises(SystemExit, match="--release needs --release-root"):
        main(["--release", "5,5"])
