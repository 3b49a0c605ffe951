"""Bring-your-own capture: the converter round trip, validation that reports every problem, the CLI."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.capture import CaptureError, convert, scan
from realityavatar.data.capture import main as capture_main
from realityavatar.data.i3d import read_i3d
from realityavatar.data.records import load_record
from tests.fixtures_data import SIZE, RandomBody, camera, pixel_in_mask, project


@pytest.fixture(scope="module")
def body():
    return RandomBody()


def write_capture(folder: Path, body, frames=range(6), cams=(0, 1, 2), seed=3):
    """A BYO capture: cameras.json, images/<cam>/<frame>.png, masks/<cam>/<frame>.png, smpl/<frame>.npz."""
    from tests.fixtures_data import draw, motion, world_pelvis

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
    cams["1"]["K"][0][0] = 0.0  # a zero focal length
    cams["2"]["R"] = (-np.asarray(cams["2"]["R"])).tolist()  # a mirrored camera
    (cap / "cameras.json").write_text(json.dumps(cams))
    (cap / "images" / "2" / "000001.jpg").write_bytes(b"not a jpeg")  # a corrupt image
    problems, *_ = scan(cap, train_views=[0, 1], test_views=[2, 7])
    text = "\n".join(problems)
    for needle in ("camera '0': missing K", "images/1: missing images for frames [3]",
                   "masks/2: missing masks for frames [5]", "camera 2: 6 images but 5 masks", "smpl/000002.npz: non-finite values",
                   "images/2/000001.jpg: corrupt", "test_views: camera 7 is not in cameras.json",
                   "camera '1': K has focal lengths fx, fy = 0,", "camera '2': R is a reflection (det < 0)"):
        assert needle in text, (needle, text)
    with pytest.raises(CaptureError) as e:
        convert(cap, tmp_path / "out", "bad", [0, 1], [2, 7], body=body)
    assert len(e.value.problems) == len(problems) >= 9
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
