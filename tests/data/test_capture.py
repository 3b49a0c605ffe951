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
from realityavatar.data.capture import CaptureError, convert, scan, train_command
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
    (folder / "capture.json").write_text(json.dumps({"fps": 25}))
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
    problems = scan(cap, train_views=[0, 1], test_views=[2, 7]).problems
    text = "\n".join(problems)
    for needle in ("camera '0': missing K", "images/1: missing images for frames [3]",
                   "masks/2: missing masks for frames [5]", "camera 2: 6 images but 5 masks", "smpl/000002.npz: non-finite values",
                   "images/2/000001.jpg: corrupt", "--test-views: camera 7 is not in cameras.json",
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


# ---------------------------------------------------------------------------------------------------------------
# The embedded ci scene written as a user's capture folder, and the mistakes people make with one.


def scene_as_capture(prefix: Path, folder: Path, easymocap: bool = False) -> dict:
    """Write a built scene (<prefix>-train|-novelview|-novelpose) as docs/data.md's capture folder: capture.json (its
    meta's fps), cameras.json, images/<cam>/<frame>.png, masks/<cam>/<frame>.png, smpl/<frame>.json (EasyMocap's
    placement; `easymocap`: EasyMocap's own list-of-people form with nested arrays). The cameras that film every
    frame (a scene's evaluation-only cameras do not). Returns the scene's meta."""
    import shutil

    meta = json.loads(prefix.with_name(prefix.name + "-meta.json").read_text())
    cams, poses, shots = {}, {}, {}
    for suffix in ("train", "novelview", "novelpose"):
        split = prefix.with_name(f"{prefix.name}-{suffix}")
        cameras = pickle.loads((split / "cameras.pkl").read_bytes())
        infos = pickle.loads((split / "mesh_infos.pkl").read_bytes())
        for name, cam in cameras.items():
            frame, view = int(name.split("_")[1]), int(name.split("_")[3])
            E = np.asarray(cam["extrinsics"], float)
            cams[str(view)] = {"K": np.asarray(cam["intrinsics"], float).tolist(), "R": E[:3, :3].tolist(),
                               "T": E[:3, 3].tolist()}
            shots.setdefault(str(view), {})[frame] = (split, name)
            poses[frame] = {k: np.asarray(infos[name][k], float).reshape(-1).tolist() for k in ("poses", "Rh", "Th")}
    cams = {v: c for v, c in cams.items() if len(shots[v]) == len(poses)}
    for view in cams:
        for frame, (split, name) in shots[view].items():
            for kind in ("images", "masks"):
                (folder / kind / view).mkdir(parents=True, exist_ok=True)
                shutil.copy(split / kind / f"{name}.png", folder / kind / view / f"{frame:06d}.png")
    (folder / "smpl").mkdir()
    for frame, d in poses.items():
        body = [{"id": 0, **{k: [v] for k, v in d.items()}, "shapes": [[0.0] * 10]}] if easymocap else d
        (folder / "smpl" / f"{frame:06d}.json").write_text(json.dumps(body))
    (folder / "cameras.json").write_text(json.dumps(cams))
    (folder / "capture.json").write_text(json.dumps({"fps": meta["fps"]}))
    return meta


@pytest.fixture(scope="module")
def ci_capture(scenes_root, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("capture") / "ci"
    scene_as_capture(scenes_root / "skirt_spin_ci", folder)
    return folder


@pytest.fixture
def capture(ci_capture, tmp_path) -> Path:
    """A copy of the ci scene's capture folder to spoil."""
    import shutil

    return Path(shutil.copytree(ci_capture, tmp_path / "cap"))


def _edit_camera(cap: Path, cam: str, **fields) -> None:
    cams = json.loads((cap / "cameras.json").read_text())
    cams[cam].update({k: np.asarray(v).tolist() for k, v in fields.items()})
    (cap / "cameras.json").write_text(json.dumps(cams))


def _problems(cap: Path) -> str:
    return "\n".join(scan(cap).problems)


def test_the_ci_scene_as_a_capture_validates_with_a_summary(ci_capture, capsys):
    assert capture_main(["validate", str(ci_capture)]) == 0
    out = capsys.readouterr().out
    for needle in ("OK", "cameras [0, 1, 2, 3]: train [0, 1, 2], held out [3]", "frames: train 27,",
                   "novel pose 7 x 1 cameras", "images 64x64; fps 10; poses of frames 0..33 (34 files)",
                   "--test-views not given: camera 3 is held out", "--novel-pose-from not given: frames 27..33"):
        assert needle in out, (needle, out)


def test_camera_to_world_extrinsics_are_named(capture):
    cams = json.loads((capture / "cameras.json").read_text())
    R, T = np.asarray(cams["1"]["R"]), np.asarray(cams["1"]["T"])
    _edit_camera(capture, "1", R=R.T, T=-R.T @ T)  # the camera's pose in the world, not world-to-camera
    text = _problems(capture)
    assert "cameras.json camera '1': R, T look camera-to-world" in text, text
    assert "camera '0'" not in text and "camera '2'" not in text


@pytest.mark.parametrize("scale", [4, 2])
def test_intrinsics_of_the_full_resolution_camera_are_named(capture, scale):
    cams = json.loads((capture / "cameras.json").read_text())
    K = np.asarray(cams["2"]["K"])
    K[:2] *= scale  # calibrated at 256 px, images downscaled to 64
    _edit_camera(capture, "2", K=K)
    text = _problems(capture)
    assert "cameras.json camera '2': K's principal point" in text and "of its 64x64 images" in text, text


def test_a_body_far_larger_than_the_image_is_named(capture):
    cams = json.loads((capture / "cameras.json").read_text())
    K = np.asarray(cams["0"]["K"])
    K[0, 0] *= 4
    K[1, 1] *= 4  # focal lengths of the full-resolution camera, principal point already rescaled
    _edit_camera(capture, "0", K=K)
    text = _problems(capture)
    assert "cameras.json camera '0': a 1.7 m body" in text and "intrinsics of another resolution" in text, text


def test_mixed_image_sizes_within_a_camera_name_the_users_file(capture):
    from PIL import Image

    for kind in ("images", "masks"):
        p = capture / kind / "1" / "000005.png"
        Image.open(p).resize((32, 32)).save(p)
    text = _problems(capture)
    assert f"{capture / 'images' / '1' / '000005.png'}: 32x32, but camera 1's other 33 images are 64x64" in text, text


def test_camera_folders_not_named_as_cameras_json_list_the_names_found(capture):
    for kind in ("images", "masks"):
        for c in range(4):
            (capture / kind / str(c)).rename(capture / kind / f"{c:02d}")
    problems = scan(capture).problems
    hits = [p for p in problems if "no folder for camera(s)" in p]
    assert len(hits) == 1 and "['0', '1', '2', '3']" in hits[0] and "['00', '01', '02', '03']" in hits[0], problems


def test_a_capture_without_its_frame_rate_is_refused_before_anything_is_written(capture, tmp_path):
    (capture / "capture.json").unlink()
    text = _problems(capture)
    assert f"{capture / 'capture.json'} is missing: it gives the cameras' frame rate" in text, text
    with pytest.raises(CaptureError):
        convert(capture, tmp_path / "out", "nofps", body=RandomBody())
    assert not (tmp_path / "out").exists()
    (capture / "capture.json").write_text("{}")
    assert "capture.json: missing field 'fps'" in _problems(capture)
    assert scan(capture, fps=10).problems == []  # --fps instead


def test_easymocap_list_of_people_is_read(scenes_root, tmp_path):
    scene_as_capture(scenes_root / "skirt_spin_ci", tmp_path / "em", easymocap=True)
    cap = scan(tmp_path / "em")
    assert cap.problems == [] and sorted(cap.smpl) == list(range(34))
    infos = pickle.loads((scenes_root / "skirt_spin_ci-train" / "mesh_infos.pkl").read_bytes())
    np.testing.assert_allclose(cap.smpl[0]["Th"], np.asarray(infos["frame_000000_view_00"]["Th"]).reshape(3), atol=1e-6)
    assert cap.smpl[0]["betas"].shape == (10,)
    # its `shapes` kept for body=smpl: <name>-betas.npz, and the printed command reads it
    convert(tmp_path / "em", tmp_path / "out", "em", body=RandomBody())
    assert np.load(tmp_path / "out" / "em-betas.npz")["betas"].shape == (10,)
    assert f"body.betas={tmp_path / 'out' / 'em-betas.npz'}" in train_command(tmp_path / "out", "em", "smpl", "/smpl")
    # two people: the one chosen by --person, else the file is named with its ids
    p = tmp_path / "em" / "smpl" / "000000.json"
    people = json.loads(p.read_text())
    p.write_text(json.dumps([*people, {**people[0], "id": 4, "Th": [[9.0, 9.0, 9.0]]}]))
    assert f"{p}: 2 people (field 'id': [0, 4]); choose one with --person ID" in _problems(tmp_path / "em")
    assert scan(tmp_path / "em", person=4).smpl[0]["Th"].tolist() == [9.0, 9.0, 9.0]


def test_a_pose_file_with_a_missing_field_names_the_file_and_the_field(capture):
    p = capture / "smpl" / "000003.json"
    d = json.loads(p.read_text())
    del d["Th"]
    p.write_text(json.dumps(d))
    assert f"{p}: missing field 'Th' ([3], EasyMocap) or 'transl' ([3], SMPL)" in _problems(capture)
    p.write_text(json.dumps({"poses": "x"}))
    assert f"{p}: field 'poses' is not an array of numbers" in _problems(capture)


def test_convert_never_writes_an_empty_split(capture, tmp_path, capsys):
    for flags, needle in (([], "--test-views is empty"),
                          (["--novel-pose-from", "99"], "--novel-pose-from 99: no frame at or after it"),
                          (["--novel-pose-from", "0"], "--novel-pose-from 0: no training frame before it"),
                          (["--test-views", "0", "1", "2", "3"], "are all held out")):
        args = ["--test-views"] if not flags else flags
        rc = capture_main(["convert", str(capture), str(tmp_path / "out"), "--name", "x", *args])
        assert rc == 1 and needle in capsys.readouterr().err, flags
        assert not (tmp_path / "out").exists(), flags


def test_the_ci_scene_as_a_users_capture_validates_converts_trains_evaluates_exports(ci_capture, tmp_path, capsys):
    """The user's whole path: validate; convert with no split flags (defaults printed) and with the documented flags;
    the printed train command run as printed (a few steps), then evaluate and export with threads=1."""
    import shlex
    import subprocess

    from realityavatar.build import build_data
    from realityavatar.config import compose
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.export import main as export_main
    from tests.helpers import ROOT

    assert capture_main(["validate", str(ci_capture)]) == 0
    out = tmp_path / "converted"
    assert capture_main(["convert", str(ci_capture), str(out), "--name", "mine"]) == 0
    printed = capsys.readouterr().out
    assert "--test-views not given: camera 3 is held out" in printed and "frames 27..33" in printed
    command = next(line for line in printed.splitlines() if "realityavatar-train data=capture" in line)
    assert json.loads((out / "mine-meta.json").read_text())["fps"] == 10
    # the documented flags: the scene's own split
    assert capture_main(["convert", str(ci_capture), str(out), "--name", "doc", "--train-views", "0", "1", "3",
                         "--test-views", "2", "--novel-pose-from", "24"]) == 0
    dm = build_data(compose(["data=capture", f"data.root={out}", "data.sequence=doc"]), RandomBody())
    assert dm.fps == 10.0 and dm.scene.views("train") == [0, 1, 3] and dm.scene.views("novel_view") == [2]
    assert dm.scene.frames("novel_pose").tolist() == list(range(24, 34))
    run = tmp_path / "run"
    r = subprocess.run([*shlex.split(command), "iterations=3", "trainer=ci", "gaussians.num_points=300", "threads=1",
                        "eval.save_video=false", "eval.fps_frames=2", "eval.fps_warmup=1", f"hydra.run.dir={run}"],
                       capture_output=True, text=True, timeout=900, check=False, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "weights_only` was not set" not in r.stdout + r.stderr
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["config"]["data"] == "capture" and metrics["iterations"] == 3
    assert np.isfinite(metrics["test/novel_view/psnr"]) and np.isfinite(metrics["test/novel_pose/psnr"])
    assert evaluate_main([f"run_dir={run}", "threads=1", "eval.save_video=false", "eval.fps_frames=2"]) == 0
    assert export_main([f"run_dir={run}", "threads=1", f"out={tmp_path / 'c.ply'}"]) == 0
    assert (tmp_path / "c.ply").is_file()
