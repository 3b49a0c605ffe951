"""The motion-file reader (data/motion.py): AMASS / SMPL-X / SMPL layouts, resampling to the run's frame rate, the
up-axis turn, placement, and errors that name the file and field."""

from __future__ import annotations

import numpy as np
import pytest

from realityavatar.data.motion import Stage, load_motion
from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from tests.fixtures_data import MOTION_LAYOUTS, write_motion

Y, Z = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])


def stage(fps: float = 10.0, up=Y, ground: float = 0.0, centre=(0.0, 0.9, 0.0)) -> Stage:
    return Stage(np.asarray(up, float), ground, np.asarray(centre, float), fps)


@pytest.fixture(scope="module")
def body():
    from realityavatar.body import build_body

    return build_body("mannequin")


def root_speed(table, fps: float, up) -> np.ndarray:
    """The root's turn about `up` between consecutive frames, in rad/s: [F-1]."""
    R = axis_angle_to_matrix(table.poses[:, 0].double())
    return matrix_to_axis_angle(R[1:] @ R[:-1].transpose(-1, -2)).numpy() @ up * fps


@pytest.mark.parametrize("run_fps", [10.0, 25.0, 50.0])
def test_resampling_keeps_the_root_angular_speed_and_the_timing(body, tmp_path, run_fps):
    known = write_motion(tmp_path / "spin.npz", "amass_smplh", fps=120.0, seconds=1.0, omega=3.0)
    table = load_motion(tmp_path / "spin.npz", body, stage(run_fps), up="z", place="keep")
    assert len(table) == int(run_fps) + 1  # one second at the run's rate, both ends included
    np.testing.assert_allclose(root_speed(table, run_fps, Y), known["omega"], rtol=1e-4)
    t = np.arange(len(table)) / run_fps  # the knee bends and straightens once a second
    np.testing.assert_allclose(table.poses[:, 4, 0].numpy(), 0.5 * (1 - np.cos(2 * np.pi * t)), atol=1e-3)
    np.testing.assert_allclose(table.transl[-1, 0] - table.transl[0, 0], 0.2, atol=1e-5)  # 0.2 m/s along x


def test_layouts_read_the_same_body_pose(body, tmp_path):
    tables = {}
    for layout in MOTION_LAYOUTS:
        write_motion(tmp_path / f"{layout}.npz", layout)
        tables[layout] = load_motion(tmp_path / f"{layout}.npz", body, stage(120.0), up="z", place="keep")
    ref = tables["smpl"]  # SMPL's own 24 joints, hands (22-23) zero
    for layout, table in tables.items():
        np.testing.assert_allclose(table.poses.numpy(), ref.poses.numpy(), atol=1e-5, err_msg=layout)
        np.testing.assert_allclose(table.transl.numpy(), ref.transl.numpy(), atol=1e-5, err_msg=layout)
    assert not ref.poses[:, 22:].any()


@pytest.mark.parametrize("dataset_up", [Y, -Y, Z], ids=["y", "-y", "z"])
@pytest.mark.parametrize("up", ["z", "auto"])
def test_up_axis_turns_a_z_up_file_upright_in_the_datasets_world(body, tmp_path, dataset_up, up):
    write_motion(tmp_path / "amass.npz", "amass_smplh")
    table = load_motion(tmp_path / "amass.npz", body, stage(up=dataset_up, centre=0.9 * dataset_up), up=up)
    joints = body.joints(table.poses, table.transl).numpy()
    head = joints[:, 15] - joints[:, 0]
    assert (head @ dataset_up > 0.9 * np.linalg.norm(head, axis=1)).all()
    # read as y-up, the same file lies on its side or back in every one of these worlds
    table = load_motion(tmp_path / "amass.npz", body, stage(up=dataset_up, centre=0.9 * dataset_up), up="y")
    joints = body.joints(table.poses, table.transl).numpy()
    head = joints[:, 15] - joints[:, 0]
    assert (np.abs(head @ dataset_up) < 0.5 * np.linalg.norm(head, axis=1)).all()


def test_placement_stands_the_motion_where_the_subject_stood(body, tmp_path):
    known = write_motion(tmp_path / "amass.npz", "amass_smplh", offset=(4.0, -3.0, 0.95))
    st = stage(centre=(0.5, 0.9, -1.0), ground=0.1)
    joints = {}
    for place in ("subject", "keep"):
        table = load_motion(tmp_path / "amass.npz", body, st, up="z", place=place)
        joints[place] = body.joints(table.poses, table.transl).numpy()
    pelvis = joints["subject"][:, 0]
    np.testing.assert_allclose(pelvis.mean(0)[[0, 2]], [0.5, -1.0], atol=1e-5)  # over the subject's mean pelvis
    assert joints["subject"][..., 1].min() == pytest.approx(0.1, abs=1e-5)  # its lowest point on the ground
    # keep: the file's coordinates (pelvis = rest pelvis + trans, as in SMPL) turned z-up -> y-up: (x,y,z) -> (x,z,-y)
    x, y, z = body.rest_joints[0].numpy() + known["trans"][0]
    np.testing.assert_allclose(joints["keep"][0, 0], [x, z, -y], atol=1e-5)


def _bad(tmp_path, change):
    write_motion(tmp_path / "walk.npz", "amass_smplh")
    fields = dict(np.load(tmp_path / "walk.npz"))
    change(fields)
    np.savez(tmp_path / "bad.npz", **fields)
    return tmp_path / "bad.npz"


def _nan(key, frame):
    def change(f):
        f[key] = f[key].copy()
        f[key][frame] = np.nan
    return change


@pytest.mark.parametrize("change, message", [
    (lambda f: f.update(poses=f["poses"][:, :150]), r"bad\.npz: field 'poses' must be .*\[F,156\].*got \(121, 150\)"),
    (lambda f: f.update(poses=f["poses"][:0]), r"bad\.npz: field 'poses' must be .*no frames"),
    (lambda f: f.pop("mocap_framerate"), r"bad\.npz: no frame rate: .*'mocap_framerate'.*fps="),
    (lambda f: f.update(mocap_framerate=np.array(0.0)), r"bad\.npz: field 'mocap_framerate' must be one frame rate > 0"),
    (_nan("poses", 5), r"bad\.npz: field 'poses' has non-finite values \(NaN/inf\) at frames \[5\]"),
    (_nan("trans", 7), r"bad\.npz: field 'trans' has non-finite values \(NaN/inf\) at frames \[7\]"),
    (lambda f: f.update(trans=f["trans"][:-1]), r"bad\.npz: field 'trans' must be \[121,3\], got \(120, 3\)"),
    (lambda f: f.update(global_orient=f.pop("poses")[:, :3], body_pose=np.zeros((121, 60))),
     r"bad\.npz: field 'body_pose' must be \[121,63\] or \[121,69\]"),
    (lambda f: f.pop("poses"), r"bad\.npz: no pose field: expected 'poses'.*'global_orient' \+ 'body_pose'"),
], ids=["shape", "empty", "no-rate", "zero-rate", "nan-pose", "nan-trans", "trans-frames", "body_pose", "no-pose"])
def test_bad_files_name_the_file_and_field(body, tmp_path, change, message):
    with pytest.raises((ValueError, KeyError), match=message):
        load_motion(_bad(tmp_path, change), body, stage())


def test_frame_rate_from_the_command_line(body, tmp_path):
    path = _bad(tmp_path, lambda f: f.pop("mocap_framerate"))
    assert len(load_motion(path, body, stage(10.0), fps=120.0)) == 11
    assert len(load_motion(path, body, stage(10.0), fps=60.0)) == 21  # the same rows read as a 2 s motion
    with pytest.raises(ValueError, match=r"bad\.npz: fps= must be one frame rate > 0"):
        load_motion(path, body, stage(), fps=float("nan"))


def test_synthetic_data_configs_record_their_scenes_frame_rate():
    """data.fps is the time base of animations: each embedded scene's config must say its preset's rate."""
    from realityavatar.config import compose
    from realityavatar.data.synthetic import PRESETS
    from tests.helpers import CONF

    names = sorted(p.stem for p in (CONF / "data").glob("synthetic_*.yaml"))
    for name in names:
        data = compose([f"data={name}"]).data
        assert data.fps == PRESETS[data.build_preset]["fps"], name
    assert len(names) >= 3
