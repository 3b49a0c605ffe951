"""realityavatar-animate: a video from a pose file, clear errors, no ffmpeg."""

from __future__ import annotations

import numpy as np
import pytest


def test_animate_writes_video_from_pose_file(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main

    out, _ = trained_run
    poses = np.zeros((5, 24, 3), np.float32)
    poses[:, 16, 2] = np.linspace(0, 1.2, 5)  # raise the left arm
    np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((5, 3), np.float32))
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
    assert anim.main([f"run_dir={out}", "views=0", f"out={tmp_path / 'a.gif'}", "fps=10"]) == 0
    frames = imageio.mimread(tmp_path / "a.gif")
    assert rendered and len(frames) > 1 and frames[0].shape[0] > 0
