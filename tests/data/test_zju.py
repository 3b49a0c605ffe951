"""The ZJU-MoCap (ARAH layout) reader on fixture folders, and its clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from realityavatar.data.records import SceneFormatError, load_record
from realityavatar.data.zju import read_zju
from tests.fixtures_data import RandomBody, camera, pixel_in_mask, project, write_zju


@pytest.fixture(scope="module")
def body():
    return RandomBody()


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


def test_zju_gap_in_model_numbering_is_refused(tmp_path, body):
    """Frame ids are positions in the sorted models/ list: with 000002.npz missing, 000001 and 000003 became
    neighbouring frames of the pose windows without a word. Evenly spaced numbering (every 2nd frame) still reads."""
    write_zju(tmp_path, "CoreView_377", body, n_frames=5, cams=("1", "2"))
    (tmp_path / "CoreView_377" / "models" / "000002.npz").unlink()
    with pytest.raises(SceneFormatError, match=r"models: the files are not evenly numbered \(000001\.npz is followed "
                                               r"by 000003\.npz\)"):
        read_zju(tmp_path / "CoreView_377", [1], [2], [0, 0, 1])
    even = tmp_path / "even"
    write_zju(even, "CoreView_377", body, n_frames=5, cams=("1", "2"))
    for stem in ("000001", "000003"):
        (even / "CoreView_377" / "models" / f"{stem}.npz").unlink()
        for cam in ("1", "2"):
            for ext in (".jpg", ".png"):
                (even / "CoreView_377" / cam / f"{stem}{ext}").unlink()
    scene = read_zju(even / "CoreView_377", [1], [2], [0, 0, 1])  # 000000, 000002, 000004
    assert scene.frames("train").tolist() == [0, 1, 2]


@pytest.mark.parametrize("field, value, match", [
    ("R", lambda R: -np.asarray(R), r"R is a reflection \(det < 0\)"),
    ("K", lambda K: np.asarray(K) * [[-1, 1, 1], [1, -1, 1], [1, 1, 1]], r"K has focal lengths fx, fy = -\d+"),
])
def test_zju_camera_that_is_no_pinhole_camera_names_it(tmp_path, body, field, value, match):
    import json

    write_zju(tmp_path, "CoreView_377", body, n_frames=2, cams=("1", "2"))
    path = tmp_path / "CoreView_377" / "cam_params.json"
    params = json.loads(path.read_text())
    params["2"][field] = value(params["2"][field]).tolist()
    path.write_text(json.dumps(params))
    with pytest.raises(SceneFormatError, match=r"cam_params\.json: camera '2' " + match):
        read_zju(tmp_path / "CoreView_377", [1], [2], [0, 0, 1])


def test_zju_windows_read_every_models_pose_not_only_the_images(tmp_path, body):
    """The audit of issue 57: ZJU's pose table holds every models/*.npz, so a novel-pose window reaches back into
    frames no split shows, exactly (t - k*s), clamped at frame 0 only; it is marked dense, so a gap would be an
    error rather than a snap."""
    from realityavatar.data.zju import read_zju

    w = write_zju(tmp_path, "CoreView_377", body, n_frames=12, cams=("1", "2"))
    scene = read_zju(tmp_path / "CoreView_377", ["1"], ["2"], [0, 6, 3], novel_pose_frames=[9, 12, 1])
    assert scene.frames("train").tolist() == [0, 3] and scene.frames("novel_pose").tolist() == [9, 10, 11]
    assert scene.poses.dense_every == 1
    p, t = scene.poses.window(11, 4, 4)  # targets -1 (frame 0), 3, 7, 11: 7 is in no split
    np.testing.assert_allclose(p.numpy(), w["pose"][[0, 3, 7, 11]], atol=1e-6)
    np.testing.assert_allclose(t.numpy(), w["trans"][[0, 3, 7, 11]], atol=1e-6)
