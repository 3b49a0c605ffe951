"""The I3D-Human/HumanNeRF reader on fixture folders in the exact layout, and its clear errors."""

from __future__ import annotations

import pickle
from contextlib import contextmanager

import numpy as np
import pytest
import torch
from PIL import Image

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.i3d import read_i3d
from realityavatar.data.records import SceneFormatError, load_record, undistort_grid
from tests.fixtures_data import RandomBody, pixel_in_mask, project, write_i3d


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
