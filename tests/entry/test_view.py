"""realityavatar-view: the viewer in a headless browser (avatar drawn where the camera sees it, the timeline moves it),
its controls, its bad-input messages, and `realityavatar-export frames=a:b` writing what the viewer streams."""

from __future__ import annotations

import os
import shutil
import socket
import time

import numpy as np
import pytest

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def view_run(trained_run):
    """The suite's trained run (conftest.py): evaluated on every test frame, so per_frame.csv exists."""
    return trained_run[0]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(run_dir, *extra):
    from realityavatar.view import compose_view, load_viewer

    vcfg, overrides = compose_view([f"run_dir={run_dir}", f"port={free_port()}", *extra])
    return load_viewer(vcfg, overrides)


def chromium_path() -> str | None:
    for p in (os.environ.get("REALITYAVATAR_CHROMIUM"), shutil.which("chromium"), shutil.which("chromium-browser"),
              shutil.which("google-chrome")):
        if p and os.path.exists(p):
            return p
    return None


@pytest.fixture(scope="module")  # module scope like view_run, so it is set up (or skips) first
def browser_exe() -> str:
    """Chromium for playwright, or a skip saying what is missing (requested before view_run: no training to skip)."""
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[dev]')")
    exe = chromium_path()
    if exe is None:
        pytest.skip("no chromium browser found (Debian: apt-get install chromium, as .ci/run does; or set "
                    "REALITYAVATAR_CHROMIUM=<path>)")
    return exe


def wait_for(cond, timeout: float, what: str):
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def settled_screenshot(page, timeout: float = 15.0) -> np.ndarray:
    """A screenshot once two in a row agree (the splats are sorted and drawn a few frames after an update)."""
    from io import BytesIO

    from PIL import Image

    prev, t0 = None, time.perf_counter()
    while True:
        time.sleep(0.4)
        img = np.asarray(Image.open(BytesIO(page.screenshot())).convert("RGB")).astype(np.int16)
        if prev is not None and np.abs(img - prev).max() <= 2 or time.perf_counter() - t0 > timeout:
            return img
        prev = img


def save_png(path, img: np.ndarray) -> None:
    """Keep the screenshots beside the test's tmp_path, for a look when an assertion fails."""
    from PIL import Image

    Image.fromarray(img.astype(np.uint8)).save(path)


def projected_box(camera, means: np.ndarray, W: int, H: int, margin: int = 6) -> tuple[int, int, int, int]:
    """Pixel box (x0, y0, x1, y1) of the Gaussians' centres seen by the browser's camera in a W x H page (viser: OpenCV
    camera, vertical fov, square pixels; its image_width/height is the render buffer, which it scales down when slow)."""
    import viser.transforms as tf

    R = tf.SO3(np.asarray(camera.wxyz)).as_matrix()  # camera-to-world
    p = (means - camera.position) @ R  # [N,3] in camera coordinates
    f = (H / 2) / np.tan(camera.fov / 2)
    u, v = f * p[:, 0] / p[:, 2] + W / 2, f * p[:, 1] / p[:, 2] + H / 2
    u0, u1 = np.percentile(u, [1, 99])
    v0, v1 = np.percentile(v, [1, 99])
    return int(u0) - margin, int(v0) - margin, int(u1) + margin, int(v1) + margin


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_browser_draws_the_avatar_and_the_timeline_moves_it(browser_exe, view_run, tmp_path):
    """Headless chromium on the viewer: the avatar is drawn inside the box its Gaussians project to for the browser's
    camera (and hardly anywhere else), the frusta checkbox and the timeline slider work from the page, and the image
    changes between the first and the last frame."""
    from playwright import sync_api as pw

    exe = browser_exe
    viewer = start(view_run)
    try:
        with pw.sync_playwright() as p:
            # playwright gives every launch a fresh temporary profile (its own --user-data-dir)
            browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 640})
            page.goto(viewer.url)
            client = wait_for(lambda: next(iter(viewer.server.get_clients().values()), None), 30, "the page to connect")
            page.get_by_text("show frusta").click()  # frusta off, from the page
            wait_for(lambda: viewer.show_frusta.value is False, 10, "the frusta checkbox")
            panel_left = 1000 - 360  # the control panel's column on the right
            viewer.splats.visible = False
            empty = settled_screenshot(page)
            viewer.splats.visible = True
            first = settled_screenshot(page)
            save_png(tmp_path / "first.png", first)
            seq = viewer.current
            x0, y0, x1, y1 = projected_box(client.camera, viewer.posed(seq, 0)["means"], 1000, 640)
            assert 0 <= x0 < x1 <= panel_left and 0 <= y0 < y1 <= 640, f"avatar box {x0, y0, x1, y1} off the canvas"

            drawn = np.abs(first - empty).sum(-1) > 40  # [H,W] pixels the avatar changed
            inside = drawn[y0:y1, x0:x1]
            assert inside.mean() > 0.15, f"only {inside.mean():.1%} of the avatar's box is drawn"
            outside = drawn[:, :panel_left].sum() - inside.sum()
            assert outside < 0.1 * inside.sum(), f"{outside} drawn pixels outside the avatar's box ({inside.sum()} in)"

            # the ci sequence spins and comes back: move to the frame posed furthest from the first
            m0 = viewer.posed(seq, 0)["means"]
            far = int(np.argmax([np.linalg.norm(viewer.posed(seq, i)["means"] - m0, axis=1).mean()
                                 for i in range(len(seq.frames))]))
            # drag the timeline's thumb along its track (arrow keys would also orbit viser's camera)
            thumb = page.get_by_role("slider").first
            thumb.scroll_into_view_if_needed()  # the panel scrolls when a control further down is clicked
            track = thumb.locator("xpath=..").bounding_box()
            at = thumb.bounding_box()
            page.mouse.move(at["x"] + at["width"] / 2, at["y"] + at["height"] / 2)
            page.mouse.down()
            page.mouse.move(track["x"] + track["width"] * far / (len(seq.frames) - 1), at["y"] + at["height"] / 2,
                            steps=8)
            page.mouse.up()
            index = lambda: int(viewer.frame_slider.value)
            wait_for(lambda: abs(index() - far) <= 1 and viewer.timings[-1]["frame"] == seq.frames[index()], 20,
                     f"the timeline at frame index {far} (±1) and that frame posed")
            last = index()
            moved = settled_screenshot(page)
            save_png(tmp_path / "moved.png", moved)
            x0b, y0b, x1b, y1b = projected_box(client.camera, viewer.posed(seq, last)["means"], 1000, 640)
            X0, Y0, X1, Y1 = max(min(x0, x0b), 0), max(min(y0, y0b), 0), min(max(x1, x1b), panel_left), max(y1, y1b)
            change = np.abs(moved - first).sum(-1)[Y0:Y1, X0:X1] > 40
            assert change.mean() > 0.05, f"frame {seq.frames[last]} looks like frame {seq.frames[0]} ({change.mean():.1%} changed)"
            assert (np.abs(moved - empty).sum(-1)[y0b:y1b, max(x0b, 0):x1b] > 40).mean() > 0.15

            # Jump to camera (the first in the list) puts the browser's camera at that dataset camera
            page.get_by_role("button", name="Jump to camera").click()
            centre = np.linalg.inv(viewer.cameras[0]["viewmat"].numpy())[:3, 3]
            wait_for(lambda: np.allclose(client.camera.position, centre, atol=1e-3), 10, "the camera jump")
            # a pose file uploaded from the page becomes the timeline
            poses = np.zeros((4, 24, 3), np.float32)
            poses[:, 16, 2] = np.linspace(0, 1.2, 4)
            np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((4, 3), np.float32), fps=10.0)
            page.locator("input[type=file]").first.set_input_files(str(tmp_path / "wave.npz"))
            wait_for(lambda: viewer.current.name == "file: wave.npz" and viewer.timings[-1]["frame"] == 0, 20,
                     "the uploaded pose file to become the timeline")
            browser.close()
    finally:
        viewer.close()


def test_controls_pose_file_cameras_canonical_and_metrics(view_run, tmp_path):
    from realityavatar.export import gaussians_for_export

    viewer = start(view_run, "split=novel_view")
    try:
        assert set(viewer.sequences) >= {"train", "novel_view", "novel_pose"} and viewer.current.name == "novel_view"
        # held-out PSNR and IoU of a frame that per_frame.csv scored
        (split, frame), rows = next(iter(sorted(viewer.per_frame.items())))
        viewer.seq_dropdown.value = "novel_pose" if split == "novel_pose" else "novel_view"
        viewer.frame_slider.value = viewer.current.frames.index(frame)
        text = viewer.frame_metrics.content
        assert f"frame {frame}" in text and f"{rows[0][1]:.2f}" in text and f"{rows[0][2]:.3f}" in text, text
        # a pose file becomes a timeline; a wrong one is reported in the panel and changes nothing
        poses = np.zeros((6, 24, 3), np.float32)
        poses[:, 16, 2] = np.linspace(0, 1.2, 6)
        np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((6, 3), np.float32), fps=10.0)
        assert viewer.load_pose_file(tmp_path / "wave.npz")
        assert viewer.current.name == "file: wave.npz" and viewer.frame_slider.max == 5
        viewer.frame_slider.value = 5
        assert viewer.timings[-1]["frame"] == 5
        np.savez(tmp_path / "bad.npz", poses=np.zeros((6, 23, 3), np.float32))
        assert not viewer.load_pose_file(tmp_path / "bad.npz")
        assert "bad.npz" in viewer.pose_status.content and "'poses'" in viewer.pose_status.content
        assert viewer.current.name == "file: wave.npz"
        # play advances the timeline by itself, pause stops it
        viewer.fps.value = 20.0
        viewer.set_playing(True)
        wait_for(lambda: viewer.frame_slider.value != 5, 10, "playback to advance")
        viewer.set_playing(False)
        assert viewer.play_button.label == "Play"
        # canonical Gaussians: what export writes for canonical space
        viewer.canonical.value = True
        canon = gaussians_for_export(viewer.avatar)
        np.testing.assert_allclose(viewer.splats.centers, canon["means"], atol=1e-6)
        with pytest.raises(Exception, match="not a dataset camera"):
            viewer.jump_to_camera(99)
    finally:
        viewer.close()


def test_playback_runs_at_the_runs_frame_rate_unless_told(view_run):
    """fps=null (conf/view.yaml): the timeline plays in real time, at the run's data.fps; fps=<n> sets it."""
    for extra, want in (("data.fps=12.5", 12.5), ("fps=7", 7.0)):
        viewer = start(view_run, extra)
        try:
            assert viewer.fps.value == want
        finally:
            viewer.close()


def test_bad_input_gives_clear_messages(view_run, tmp_path, capsys):
    from realityavatar.view import main

    no_ckpt = tmp_path / "no_ckpt"
    no_ckpt.mkdir()
    shutil.copy(view_run / "config.yaml", no_ckpt / "config.yaml")
    assert main([f"run_dir={no_ckpt}", "port=0"], block=False) == 2
    err = capsys.readouterr().err
    assert "checkpoint" in err and "last.ckpt" in err and str(no_ckpt) in err, err

    assert main([f"run_dir={tmp_path / 'nowhere'}", "port=0"], block=False) == 2
    assert "no such folder" in capsys.readouterr().err

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        assert main([f"run_dir={view_run}", f"port={port}"], block=False) == 2
    err = capsys.readouterr().err
    assert f"port={port}" in err and "in use" in err, err
    assert main([f"run_dir={view_run}", "port=-5"], block=False) == 2  # was the OS's OverflowError, no key named
    assert "port=-5: expected a TCP port 1-65535, or 0 for any free one" in capsys.readouterr().err

    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((5, 23, 3), np.float32))
    assert main([f"run_dir={view_run}", "port=0", f"poses={bad}"], block=False) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "'poses'" in err and "[F,24,3]" in err, err

    assert main([f"run_dir={view_run}", "port=0"], block=False) == 0  # and a good start prints the URL
    assert "http://127.0.0.1:" in capsys.readouterr().out


def test_export_frames_writes_what_the_viewer_streams(view_run, tmp_path):
    from realityavatar.export import main as export_main
    from realityavatar.export import parse_frames, read_ply

    assert export_main([f"run_dir={view_run}", "frames=2:5", f"out={tmp_path / 'seq'}"]) == 0
    files = sorted((tmp_path / "seq").glob("*.ply"))
    assert [f.name for f in files] == ["posed_000002.ply", "posed_000003.ply", "posed_000004.ply"]
    viewer = start(view_run, "split=train")
    try:
        seq = viewer.sequences["train"]
        g = viewer.posed(seq, seq.frames.index(3))
        ply = read_ply(tmp_path / "seq" / "posed_000003.ply")
        np.testing.assert_allclose(ply["means"], g["means"], atol=1e-6)
        np.testing.assert_allclose(ply["scales"], g["scales"], rtol=1e-4)
        np.testing.assert_allclose(ply["sh"][:, 0] * 0.28209479177387814 + 0.5, g["rgb"], atol=1e-5)
    finally:
        viewer.close()
    with pytest.raises(ValueError, match="frames='2-5'"):
        parse_frames("2-5")
    with pytest.raises(ValueError, match=r"frames=5000:5010 selects no frame of run"):
        export_main([f"run_dir={view_run}", "frames=5000:5010", f"out={tmp_path / 'none'}"])


def test_export_and_viewer_read_a_motion_file_alike(view_run, tmp_path):
    """An AMASS file (120 fps, Z-up) through export's and the viewer's pose loader (the one reader, data/motion.py,
    with the same up= and place=): the same resampled frames, the same posed Gaussians."""
    from realityavatar.export import main as export_main
    from realityavatar.export import read_ply
    from tests.fixtures_data import write_motion

    write_motion(tmp_path / "walk.npz", "amass_smplh", fps=120.0, seconds=1.0)
    assert export_main([f"run_dir={view_run}", "frames=8:12", f"poses={tmp_path / 'walk.npz'}", "up=z",
                        f"out={tmp_path / 'seq'}"]) == 0
    assert [f.name for f in sorted((tmp_path / "seq").glob("*.ply"))] == [f"posed_{f:06d}.ply" for f in (8, 9, 10)]
    viewer = start(view_run, "up=z")
    try:
        assert viewer.load_pose_file(tmp_path / "walk.npz")
        assert viewer.current.frames == list(range(11))  # 1 s at the run's 10 fps
        np.testing.assert_allclose(read_ply(tmp_path / "seq" / "posed_000009.ply")["means"],
                                   viewer.posed(viewer.current, 9)["means"], atol=1e-6)
    finally:
        viewer.close()
