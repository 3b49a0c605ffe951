"""realityavatar-animate: a video from a pose file (an AMASS file at its own frame rate, upright, in view, an orbit
camera), clear errors, no ffmpeg."""

from __future__ import annotations

import numpy as np
import pytest


def test_animate_writes_video_from_pose_file(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main

    out, _ = trained_run
    poses = np.zeros((5, 24, 3), np.float32)
    poses[:, 16, 2] = np.linspace(0, 1.2, 5)  # raise the left arm
    np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((5, 3), np.float32), fps=10.0)
    assert animate_main([f"run_dir={out}", f"poses={tmp_path / 'wave.npz'}", "views=0", f"out={tmp_path / 'wave.mp4'}"]) == 0
    assert (tmp_path / "wave.mp4").stat().st_size > 0
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((5, 23, 3), np.float32))
    with pytest.raises(ValueError, match="poses"):
        animate_main([f"run_dir={out}", f"poses={bad}"])


def test_animate_without_ffmpeg_fails_before_rendering_and_gif_needs_none(trained_run, tmp_path, monkeypatch):
    """No imageio-ffmpeg (a GPU image without it): a clear error naming the file before any frame is rendered
    (imageio otherwise picked its TIFF plugin and failed with `unexpected keyword 'fps'`); a .gif still works."""
    import sys

    import imageio.v2 as imageio

    import realityavatar.animate as anim

    out, _ = trained_run
    rendered = []
    real = anim.render_sequence
    monkeypatch.setattr(anim, "render_sequence", lambda *a, **k: rendered.append(1) or real(*a, **k))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(RuntimeError, match=r"a\.mp4: writing a video needs ffmpeg.*imageio-ffmpeg"):
        anim.main([f"run_dir={out}", "views=0", f"out={tmp_path / 'a.mp4'}"])
    assert not rendered and not (tmp_path / "a.mp4").exists()
    assert anim.main([f"run_dir={out}", "views=0", f"out={tmp_path / 'a.gif'}"]) == 0
    frames = imageio.mimread(tmp_path / "a.gif")
    assert rendered and len(frames) > 1 and frames[0].shape[0] > 0


def test_amass_file_plays_in_real_time_upright_and_in_view(trained_run, tmp_path, monkeypatch):
    """An AMASS SMPL-H file (120 fps, Z-up, 5 m from the origin, the root turning at 3 rad/s) drives the ci run (10
    fps, y-up world): resampled to 10 fps the root still turns at 3 rad/s, the body stands upright, the pelvis is in
    the image of every dataset camera and of the orbit camera, which turns once around it, and the GIF plays the 2 s
    of motion in 2 s."""
    from PIL import Image

    import realityavatar.animate as anim
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
    from tests.fixtures_data import write_motion

    out, _ = trained_run
    known = write_motion(tmp_path / "walk.npz", "amass_smplh", fps=120.0, seconds=2.0, omega=3.0)
    seen, real = {}, anim.render_sequence

    def spy(avatar, table, cameras, *a):
        seen.update(table=table, cameras=cameras, body=avatar.body)
        return real(avatar, table, cameras, *a)

    monkeypatch.setattr(anim, "render_sequence", spy)
    gif = tmp_path / "walk.gif"
    assert anim.main([f"run_dir={out}", f"poses={tmp_path / 'walk.npz'}", "up=z", "cameras=orbit,dataset",
                      f"out={gif}"]) == 0
    table, cameras = seen["table"], seen["cameras"]
    assert len(table) == 21  # 2 s at the run's 10 fps
    R = axis_angle_to_matrix(table.poses[:, 0].double())
    turn = matrix_to_axis_angle(R[1:] @ R[:-1].transpose(-1, -2)).numpy()  # world-frame turn per frame [20,3]
    np.testing.assert_allclose(turn[:, 1] * 10.0, known["omega"], rtol=1e-3)  # rad/s about the world's y (up)
    joints = seen["body"].joints(table.poses, table.transl).cpu().numpy()  # [21,24,3], the dataset's world (y up)
    head = joints[:, 15] - joints[:, 0]
    assert (head[:, 1] > 0.9 * np.linalg.norm(head, axis=1)).all(), "the body is not upright"
    assert cameras[0]["viewmat"].shape == (21, 4, 4) and len(cameras) >= 2
    for cam in cameras:
        vm = cam["viewmat"].double().numpy()
        vm = vm if vm.ndim == 3 else np.broadcast_to(vm, (21, 4, 4))
        x = np.einsum("fij,fj->fi", vm[:, :3, :3], joints[:, 0]) + vm[:, :3, 3]  # pelvis in the camera [21,3]
        uv = (x @ cam["K"].double().numpy().T)[:, :2] / x[:, 2:]
        inside = (x[:, 2] > 0) & (uv >= 0).all(1) & (uv[:, 0] < cam["width"]) & (uv[:, 1] < cam["height"])
        assert inside.all(), f"camera {cam['view']}: the pelvis leaves the image at frames {np.flatnonzero(~inside)}"
    eye = np.linalg.inv(cameras[0]["viewmat"].double().numpy())[:, :3, 3] - joints[:, 0]
    azimuth = np.unwrap(np.arctan2(eye[:, 0], eye[:, 2]))
    assert abs(azimuth[-1] - azimuth[0]) == pytest.approx(2 * np.pi * 20 / 21, abs=0.05)  # one turn over the clip
    with Image.open(gif) as im:
        assert im.n_frames == 21 and im.info["duration"] == 100  # ms: 10 fps, real time


def test_the_runs_frame_rate_and_up_come_from_its_config_and_training_poses(trained_run):
    from realityavatar.build import build_data, load_avatar
    from realityavatar.data.motion import Stage

    cfg, avatar, _ = load_avatar(trained_run[0])
    dm = build_data(cfg, avatar.body)
    stage = Stage.of(dm, avatar.body)
    assert stage.fps == cfg.data.fps == 10 and stage.up.tolist() == [0.0, 1.0, 0.0]  # the ci scene: 10 fps, y up
    dm.fps = 25.0
    with pytest.raises(ValueError, match=r"data\.fps=25 but the scene .*skirt_spin_ci was built at 10 fps"):
        Stage.of(dm, avatar.body)
    dm.fps = None  # a config written before data.fps: a synthetic scene's own record
    assert Stage.of(dm, avatar.body).fps == 10
    dm.scene.meta.pop("fps")
    with pytest.raises(ValueError, match=r"skirt_spin_ci: the run's config has no data\.fps.*data\.fps=<frames"):
        Stage.of(dm, avatar.body)


@pytest.mark.parametrize("argv, named", [
    (["pose=walk.npz"], "pose="),                  # a typo of poses=: the dataset split was rendered instead
    (["poses=walk.npz", "orbit.radus=2"], "orbit.radus="),
    (["walk.npz"], "'walk.npz': expected key=value"),
])
def test_an_unknown_argument_stops_animate_before_the_run_is_read(argv, named, capsys):
    """Each is refused with exit 2 and named on stderr, before the run folder (here absent) is read."""
    from realityavatar.animate import main as animate_main

    assert animate_main(["run_dir=/nonexistent/run", *argv]) == 2
    assert named in capsys.readouterr().err
