"""Viewer benchmark: the two ways `realityavatar-view` could draw an avatar, at 10k and 35k Gaussians, and its start-up.

- browser path (what the viewer does): per frame the server poses the Gaussians (deform + baked colour), builds the
  covariances and hands them to viser, which sends ~32 bytes per Gaussian; the browser sorts and draws them, so orbiting
  costs the server nothing.
- server path (the alternative): per frame, and again for every camera move, the server poses, shades for the camera,
  rasterizes WxH with our renderer (numba on the CPU) and encodes a JPEG for the browser.

Prints a table and writes JSON (wall and CPU seconds: the CPU is shared, CPU seconds are steadier). Optionally the
browser's own drawing rate in headless chromium (software WebGL: no GPU here, far below a desktop browser).
Usage: `python benchmarks/viewer.py --run /tmp/viewer_run [--counts 10000 35000] [--frames 8] [--size 512]`
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


def timed(fn, repeats: int) -> dict:
    """Mean wall and CPU seconds of fn() over `repeats` calls (after one warm-up call)."""
    fn()
    w0, c0 = time.perf_counter(), time.process_time()
    for i in range(repeats):
        fn(i)
    return {"wall_s": (time.perf_counter() - w0) / repeats, "cpu_s": (time.process_time() - c0) / repeats}


def build_viewer(run_dir: Path, num_points: int):
    """The viewer on the run's data and architecture with `num_points` canonical Gaussians (untrained: the cost of a
    frame does not depend on the weights). Returns (viewer, module, dm)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from realityavatar.build import build_data, build_module
    from realityavatar.view import AvatarViewer

    cfg = OmegaConf.load(run_dir / "config.yaml")
    cfg.gaussians.num_points = int(num_points)
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent)
    module.on_fit_start()  # skinning=grid: the weight grid from the body, as at the start of training
    module.eval()
    return AvatarViewer(module.avatar, dm, run_dir, port=0), module, dm


def browser_fps(url: str, seconds: float, playing) -> dict | None:
    """requestAnimationFrame rate of headless chromium on the viewer page, with the timeline playing or not."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if exe is None:
        return None
    args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync"]
    js = """(ms) => new Promise(done => { let n = 0; const t0 = performance.now();
        const tick = () => { n++; if (performance.now() - t0 < ms) requestAnimationFrame(tick);
                             else done(n * 1000 / (performance.now() - t0)); };
        requestAnimationFrame(tick); })"""
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=args)
        page = browser.new_page(viewport={"width": 1000, "height": 640})
        page.goto(url)
        time.sleep(6)  # connect, receive the scene, first sort
        still = page.evaluate(js, seconds * 1000)
        playing(True)
        time.sleep(1)
        moving = page.evaluate(js, seconds * 1000)
        playing(False)
        browser.close()
    return {"browser_fps_still": still, "browser_fps_playing": moving}


def measure_count(run_dir: Path, n: int, frames: int, size: int, browser: bool) -> dict:
    from PIL import Image

    viewer, module, dm = build_viewer(run_dir, n)
    try:
        seq = viewer.current
        idx = lambda i=0: i % len(seq.frames)
        row = {"num_gaussians": int(module.avatar.gaussians.num_points)}
        # browser path: viewer.show = pose + colour + covariances + viser's buffer (the send runs on viser's thread)
        t = timed(lambda i=0: viewer.show(idx(i)), frames)
        row.update({f"browser_path_update_{k}": v for k, v in t.items()})
        parts = viewer.timings[-frames:]
        row["browser_path_pose_colour_wall_s"] = float(np.mean([p["deform_s"] for p in parts]))
        row["browser_path_bytes_per_frame"] = int(viewer.splats.buffer.nbytes)
        # server path: pose, shade for the camera, rasterize size x size with numba, encode a JPEG
        cam = viewer.cameras[0]
        s = size / max(int(cam["width"]), int(cam["height"]))
        K = cam["K"].clone()
        K[:2] *= s
        W, H = round(int(cam["width"]) * s), round(int(cam["height"]) * s)
        vm = cam["viewmat"][None]
        module.avatar.render_cfg["backend"] = "numba"

        @torch.no_grad()
        def server_frame(i=0):
            poses, transl = seq.table.window(seq.frames[idx(i)], dm.window_len, dm.window_step)
            posed = module.avatar.deform(module.avatar.pose_inputs(poses[None], transl[None]))
            rgb = module.avatar.shade(posed, vm, torch.full((1,), -1, dtype=torch.long))[0]
            img, _, meta = module.avatar.splat(posed, 0, rgb, vm, K[None], W, H)
            buf = io.BytesIO()
            Image.fromarray((img[0].clamp(0, 1).numpy() * 255).astype(np.uint8)).save(buf, "JPEG", quality=85)
            server_frame.backend = meta["backend"]

        server_frame()  # numba compile / cache load
        t = timed(server_frame, frames)
        row.update({f"server_path_frame_{k}": v for k, v in t.items()})
        row["server_path_backend"], row["server_path_size"] = server_frame.backend, [W, H]
        if browser:
            fps = browser_fps(viewer.url, 3.0, viewer.set_playing)
            if fps:
                row.update(fps)
    finally:
        viewer.close()
    return row


def startup(run_dir: Path) -> dict:
    """`realityavatar-view run_dir=... port=0 threads=1` from launch to the printed URL (imports, load_run, data,
    first posed frame, server up): wall and the child's CPU seconds at that moment (from /proc)."""
    cmd = [sys.executable, "-m", "realityavatar.view", f"run_dir={run_dir}", "port=0", "threads=1"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        for line in proc.stdout:
            if line.startswith("realityavatar-view: http"):
                wall = time.perf_counter() - t0
                fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
                cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
                n = int(re.search(r"\((\d+) Gaussians", line).group(1))
                return {"startup_wall_s": wall, "startup_cpu_s": cpu, "num_gaussians": n}
        raise RuntimeError(f"{' '.join(cmd)} exited without printing its URL (rc {proc.wait()})")
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def screenshot(run_dir: Path, path: Path, index: int) -> None:
    """The viewer on the trained run itself (realityavatar-view's own loading) in headless chromium, timeline at
    `index` of the training frames, written to `path` (docs/images/viewer.png, shown in docs/viewer.md)."""
    from io import BytesIO

    from PIL import Image
    from playwright.sync_api import sync_playwright

    from realityavatar.view import compose_view, load_viewer

    viewer = load_viewer(*compose_view([f"run_dir={run_dir}", "port=0"]))
    try:
        viewer.frame_slider.value = index
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=shutil.which("chromium") or shutil.which("chromium-browser"),
                                        args=["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(viewer.url)
            time.sleep(8)
            page.get_by_text("Software WebGL rendering detected").locator("xpath=../..").get_by_role("button").click()
            time.sleep(2)
            Image.open(BytesIO(page.screenshot())).convert("RGB").save(path)
            browser.close()
    finally:
        viewer.close()
    print(f"wrote {path}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a trained run folder (its data and architecture)")
    ap.add_argument("--counts", type=int, nargs="+", default=[10000, 35000])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=512, help="server path: the rendered image's longer side")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-browser", action="store_true", help="skip the headless chromium drawing rate")
    ap.add_argument("--screenshot", type=Path, help="only write a screenshot of the viewer on --run to this PNG")
    ap.add_argument("--screenshot-frame", type=int, default=10, help="timeline index of the screenshot")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "viewer_cpu.json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.screenshot:
        screenshot(a.run, a.screenshot, a.screenshot_frame)
        return 0
    load_before = list(os.getloadavg())
    rows = [measure_count(a.run, n, a.frames, a.size, not a.no_browser) for n in a.counts]
    start = startup(a.run)
    print(f"{'Gaussians':>9} | {'browser path update':>26} | {'server path frame':>26} | {'chromium rAF fps':>17}")
    print(f"{'':>9} | {'ms wall':>8} {'ms CPU':>8} {'fps':>8} | {'ms wall':>8} {'ms CPU':>8} {'fps':>8} | "
          f"{'still':>8} {'playing':>8}")
    for r in rows:
        bw, bc = 1000 * r["browser_path_update_wall_s"], 1000 * r["browser_path_update_cpu_s"]
        sw, sc = 1000 * r["server_path_frame_wall_s"], 1000 * r["server_path_frame_cpu_s"]
        fs = f"{r.get('browser_fps_still', float('nan')):8.1f} {r.get('browser_fps_playing', float('nan')):8.1f}"
        print(f"{r['num_gaussians']:>9} | {bw:8.1f} {bc:8.1f} {1000 / bw:8.1f} | {sw:8.1f} {sc:8.1f} {1000 / sw:8.1f} | {fs}")
    print(f"start-up ({start['num_gaussians']} Gaussians, command to URL): {start['startup_wall_s']:.1f} s wall, "
          f"{start['startup_cpu_s']:.1f} s CPU")
    out = {
        "rows": rows, "startup": start, "run": str(a.run), "threads": a.threads, "frames": a.frames,
        "server_path_size": a.size, "machine": platform.platform(), "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "loadavg_before": load_before, "loadavg_after": list(os.getloadavg()),
        "note": "shared CPU (other jobs running): CPU seconds are steadier than wall; browser fps is software WebGL",
        "torch": torch.__version__,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
