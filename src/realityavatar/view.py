"""Interactive browser viewer of a trained run: viser draws the Gaussians in the browser; the server poses them per frame
(`Avatar.baked`: posed Gaussians with their colour baked, as export writes them) and streams means, covariances, colours, opacities.

Command: `realityavatar-view run_dir=<run> [port=8080] [host=127.0.0.1] [split=train] [poses=<file.npz>]
[fps=<the run's data.fps>] [poses_fps=<the file's frame rate>] [up=auto|z|y] [place=subject|keep]`
(viewer settings: conf/view.yaml; any other key=value overrides the run's config, as for realityavatar-evaluate).
"""

from __future__ import annotations

import csv
import json
import logging
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

SPLITS = ("train", "novel_view", "novel_pose")
# per_frame.csv holds held-out images only: a training frame is scored from the novel-view camera.
METRIC_SPLIT = {"train": "novel_view", "novel_view": "novel_view", "novel_pose": "novel_pose"}


class ViewerError(Exception):
    """Bad input to the viewer (run folder, port, pose file): the message says what and what was expected."""


@dataclass
class Timeline:
    """A timeline: frame ids in order, looked up (with their pose windows) in `table` (a PoseTable)."""

    name: str
    table: object
    frames: list[int]
    split: str | None = None  # dataset split, for the held-out metrics of a frame


def covariances(quats: np.ndarray, scales: np.ndarray, blur: float = 0.0) -> np.ndarray:
    """quats [N,4] wxyz, scales [N,3] (linear) -> world covariances R S S^T R^T + blur I [N,3,3] (blur: a variance in
    scene units squared)."""
    from realityavatar.geometry import quat_to_matrix

    R = quat_to_matrix(torch.from_numpy(quats)).numpy()  # [N,3,3]
    M = R * scales[:, None, :]
    cov = M @ M.transpose(0, 2, 1)
    if blur > 0:
        cov += np.float32(blur) * np.eye(3, dtype=cov.dtype)
    return cov


def camera_pose(viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera [4,4] (OpenCV) -> camera-to-world rotation as wxyz [4] and camera centre [3] (viser's
    cameras and frusta also follow OpenCV: +z forward, -y up)."""
    import viser.transforms as tf

    c2w = np.linalg.inv(np.asarray(viewmat, np.float64))
    return tf.SO3.from_matrix(c2w[:3, :3]).wxyz, c2w[:3, 3]


def check_port_free(host: str, port: int) -> None:
    """viser moves to the next port when the asked one is taken; the viewer says so instead."""
    if not 0 <= port <= 65535:
        raise ViewerError(f"port={port}: expected a TCP port 1-65535, or 0 for any free one")
    if port == 0:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            raise ViewerError(f"port={port}: {host}:{port} is in use or not available ({e.strerror}); give another "
                              f"port (e.g. port={port + 1}) or port=0 for any free one") from None


def read_run_metrics(run_dir: Path) -> tuple[dict, dict]:
    """metrics.json of the run ({} when absent) and per_frame.csv rows grouped by (split, frame): [(view, psnr, iou)]."""
    metrics = {}
    if (run_dir / "metrics.json").is_file():
        metrics = json.loads((run_dir / "metrics.json").read_text())
    per_frame: dict[tuple[str, int], list[tuple[int, float | None, float | None]]] = {}
    path = run_dir / "per_frame.csv"
    if path.is_file():
        with open(path, newline="") as fh:
            for row in csv.DictReader(fh):
                psnr, iou = (float(row[k]) if row.get(k) not in (None, "") else None for k in ("psnr", "iou"))
                per_frame.setdefault((row["split"], int(row["frame"])), []).append((int(row["view"]), psnr, iou))
    return metrics, per_frame


def run_metrics_markdown(metrics: dict) -> str:
    if not metrics:
        return "*no metrics.json in the run folder*"
    lines = ["| | PSNR | SSIM | IoU |", "|---|---|---|---|"]
    for split in ("novel_view", "novel_pose"):
        g = [metrics.get(f"test/{split}/{k}") for k in ("psnr", "ssim", "iou")]
        if g[0] is not None:
            lines.append(f"| {split} | " + " | ".join("–" if v is None else f"{v:.3f}" for v in g) + " |")
    facts = [f"{metrics.get('iterations', '?')} it", f"{metrics.get('num_gaussians', '?')} Gaussians"]
    if metrics.get("train_seconds") is not None:
        facts.append(f"trained {metrics['train_seconds']:.0f} s")
    return "\n".join(lines) + "\n\n" + ", ".join(facts)


class AvatarViewer:
    """The viser server, its controls and the playback thread for one loaded run.

    avatar: a trained Avatar (model/avatar.py) in eval mode; dm: the run's set-up DataModule; run_dir: for metrics.json/per_frame.csv.
    """

    def __init__(self, avatar, dm, run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080, split: str = "train",
                 poses: str | None = None, fps: float | None = None, frustum_scale: float = 0.1,
                 poses_fps: float | None = None, up: str = "auto", place: str = "subject"):
        import viser

        from realityavatar.animate import dataset_cameras
        from realityavatar.export import gaussians_for_export

        self._gaussians_for = gaussians_for_export
        self._driven = None  # the pose table the avatar's garment was last simulated on
        self.avatar, self.dm, self.run_dir = avatar, dm, Path(run_dir)
        self.motion = {"fps": poses_fps, "up": up, "place": place}  # how pose files are read (data/motion.py)
        fps = float(fps if fps is not None else dm.fps or 10.0)  # the run's frame rate: real time (10: configs before data.fps)
        if fps <= 0:
            raise ViewerError(f"fps={fps}: expected a playback rate > 0 frames per second")
        self.sequences: dict[str, Timeline] = {}
        for s in SPLITS:
            if s in dm.datasets:
                ids = dm.pose_sequence(s)[0].tolist()
                if ids:
                    self.sequences[s] = Timeline(s, dm.scene.poses, ids, s)
        if split not in self.sequences:
            raise ViewerError(f"split={split!r}: this run has the splits {list(self.sequences)}")
        self.current = self.sequences[split]
        if poses:  # before the server starts: a bad file stops the command with its message
            self.current = self._read_pose_file(poses)
        self.metrics, self.per_frame = read_run_metrics(self.run_dir)
        self.cameras = self._cameras(dataset_cameras)
        # The rasterizer adds eps2d px^2 to every projected covariance: at training resolution (64 px for the ci
        # scene) millimetre Gaussians are drawn a pixel wide. The same blur in scene units at the cameras' distance
        # keeps the avatar looking as trained when the browser draws it at many more pixels.
        self.eps2d = float(avatar.render_cfg.get("eps2d", 0.3))
        self.pixel_size = float(np.median([self._pixel_size(c) for c in self.cameras]))
        self.timings: list[dict] = []  # per update: deform_s, pack_s, total_s (wall) and cpu_s
        self.playing = False
        self._lock = threading.RLock()
        self._stop = threading.Event()

        check_port_free(host, port)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(dark_mode=True, control_width="medium", show_share_button=False)
        if port and self.server.get_port() != port:  # taken between the check and the bind
            self.server.stop()
            raise ViewerError(f"port={port}: {host}:{port} is in use; give another port or port=0")
        self.host, self.port = host, self.server.get_port()
        self.url = f"http://{host}:{self.port}"
        try:
            self._build_scene(frustum_scale)
            self._build_gui(fps)
            self.show(0)
        except BaseException:
            self.server.stop()
            raise
        self._thread = threading.Thread(target=self._play_loop, name="realityavatar-view-play", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ data
    def _read_pose_file(self, path: str | Path) -> Timeline:
        from realityavatar.data.motion import Stage, load_motion

        try:
            table = load_motion(path, self.avatar.body, Stage.of(self.dm, self.avatar.body), **self.motion)
        except (OSError, KeyError, ValueError) as e:
            raise ViewerError(str(e).strip("'\"")) from None
        name = f"file: {Path(path).name}"
        self.sequences[name] = Timeline(name, table, [int(f) for f in table.frames])
        return self.sequences[name]

    def _cameras(self, dataset_cameras) -> list[dict]:
        cams = {}
        for s in SPLITS:
            if s in self.dm.datasets:
                for c in dataset_cameras(self.dm, None, s):
                    cams.setdefault(int(c["view"]), {**c, "split": s})
        return [cams[v] for v in sorted(cams)]

    def _pixel_size(self, cam: dict) -> float:
        """Scene units per training pixel at the avatar, for one camera: distance / focal length."""
        c2w = np.linalg.inv(cam["viewmat"].numpy().astype(np.float64))
        centre = self.dm.scene.poses.transl.mean(0).numpy()  # near the avatar, before anything is posed
        return float(np.linalg.norm(centre - c2w[:3, 3]) / cam["K"][1, 1].item())

    def blur(self) -> float:
        """The isotropic variance added to every Gaussian (scene units^2), from the panel's training-pixel blur."""
        return float(self.blur_px.value) * self.pixel_size**2

    @torch.no_grad()
    def posed(self, seq: Timeline, index: int) -> dict:
        """The Gaussians of frame `seq.frames[index]` as export writes them: means, quats, scales, opacities, rgb."""
        poses, transl = seq.table.window(seq.frames[index], self.dm.window_len, self.dm.window_step)
        if self._driven is not seq.table:  # a garment with state (sheet=physics) runs on this timeline's motion
            self.avatar.drive(seq.table)
            self._driven = seq.table
        return self._gaussians_for(self.avatar, poses, transl, int(seq.frames[index]))

    # ------------------------------------------------------------------ scene
    def _build_scene(self, frustum_scale: float) -> None:
        scene = self.server.scene
        ups = [-np.linalg.inv(c["viewmat"].numpy().astype(np.float64))[:3, 1] for c in self.cameras]
        up = np.mean(ups, 0)
        self.up = up / max(np.linalg.norm(up), 1e-9)
        scene.set_up_direction(tuple(self.up))
        g0 = self.posed(self.current, 0)
        self.centre = g0["means"].mean(0).astype(np.float64)
        self.splats = scene.add_gaussian_splats(
            "/avatar", centers=g0["means"], covariances=covariances(g0["quats"], g0["scales"], self.eps2d * self.pixel_size**2), rgbs=g0["rgb"],
            opacities=g0["opacities"][:, None])
        self.frusta = []
        for cam in self.cameras:
            wxyz, pos = camera_pose(cam["viewmat"].numpy())
            K, W, H = cam["K"].numpy(), int(cam["width"]), int(cam["height"])
            h = scene.add_camera_frustum(
                f"/cameras/view_{cam['view']}", fov=float(2 * np.arctan2(H / 2, K[1, 1])), aspect=W / H,
                scale=frustum_scale, thickness=0.15 * frustum_scale, wxyz=wxyz, position=pos,
                color=(30, 90, 200) if cam["split"] == "train" else (220, 120, 20))
            h.on_click(lambda event, v=int(cam["view"]): self.jump_to_camera(v, [event.client]))
            self.frusta.append(h)
        cam0 = self.cameras[0]
        _, pos0 = camera_pose(cam0["viewmat"].numpy())
        # Behind camera 0 and 30 degrees round the avatar, so camera 0's frustum does not cover it.
        a, u = np.deg2rad(30.0), self.up
        off = 1.3 * (pos0 - self.centre)
        off = off * np.cos(a) + np.cross(u, off) * np.sin(a) + u * np.dot(u, off) * (1 - np.cos(a))  # Rodrigues
        self.server.initial_camera.position = tuple(self.centre + off)
        self.server.initial_camera.look_at = tuple(self.centre)
        self.server.initial_camera.up = tuple(self.up)
        self.server.initial_camera.fov = float(2 * np.arctan2(int(cam0["height"]) / 2, cam0["K"][1, 1].item()))

    def jump_to_camera(self, view: int, clients=None) -> None:
        """Put the browsers' camera (all, or `clients`) at dataset camera `view`, looking where it looks."""
        cam = next((c for c in self.cameras if c["view"] == view), None)
        if cam is None:
            raise ViewerError(f"camera {view} is not a dataset camera (have {[c['view'] for c in self.cameras]})")
        c2w = np.linalg.inv(cam["viewmat"].numpy().astype(np.float64))
        pos, fwd, up = c2w[:3, 3], c2w[:3, 2], -c2w[:3, 1]
        dist = max(float(np.dot(self.centre - pos, fwd)), 0.1)
        for client in clients if clients is not None else self.server.get_clients().values():
            with client.atomic():
                client.camera.fov = float(2 * np.arctan2(int(cam["height"]) / 2, cam["K"][1, 1].item()))
                client.camera.up_direction = up
                client.camera.position = pos
                client.camera.look_at = pos + dist * fwd

    # ------------------------------------------------------------------ controls
    def _build_gui(self, fps: float) -> None:
        gui = self.server.gui
        with gui.add_folder("Timeline"):
            self.seq_dropdown = gui.add_dropdown("sequence", tuple(self.sequences), initial_value=self.current.name)
            self.frame_slider = gui.add_slider("frame", min=0, max=max(len(self.current.frames) - 1, 1), step=1,
                                               initial_value=0)
            self.frame_label = gui.add_markdown("")
            self.play_button = gui.add_button("Play")
            self.speed = gui.add_slider("speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
            self.fps = gui.add_number("fps at speed 1", initial_value=float(fps), min=0.1, step=1.0)
            self.rate_label = gui.add_markdown("")
        with gui.add_folder("Metrics"):
            gui.add_markdown(run_metrics_markdown(self.metrics))
            self.frame_metrics = gui.add_markdown("")
        with gui.add_folder("Pose file"):
            self.pose_path = gui.add_text("path (.npz)", initial_value="")
            self.pose_load = gui.add_button("Load pose file")
            self.pose_upload = gui.add_upload_button("Upload .npz", mime_type="*/*")
            self.pose_status = gui.add_markdown("AMASS/SMPL-H, SMPL-X or SMPL .npz with a frame rate")
        with gui.add_folder("Cameras"):
            self.show_frusta = gui.add_checkbox("show frusta", initial_value=True)
            self.camera_choice = gui.add_dropdown("camera", tuple(f"view {c['view']} ({c['split']})" for c in self.cameras))
            self.camera_jump = gui.add_button("Jump to camera")
        with gui.add_folder("Gaussians"):
            self.canonical = gui.add_checkbox("canonical Gaussians", initial_value=False)
            self.blur_px = gui.add_slider("training-pixel blur (px²)", min=0.0, max=2.0, step=0.05,
                                          initial_value=self.eps2d)

        self.frame_slider.on_update(lambda _: self.show(int(self.frame_slider.value)))
        self.seq_dropdown.on_update(lambda _: self.select_sequence(self.seq_dropdown.value))
        self.play_button.on_click(lambda _: self.set_playing(not self.playing))
        self.pose_load.on_click(lambda _: self.load_pose_file(self.pose_path.value))
        self.pose_upload.on_upload(lambda _: self._on_upload())
        self.show_frusta.on_update(lambda _: self._set_frusta_visible(self.show_frusta.value))
        self.camera_jump.on_click(lambda event: self.jump_to_camera(
            self.cameras[list(self.camera_choice.options).index(self.camera_choice.value)]["view"], [event.client]))
        self.canonical.on_update(lambda _: self.show(int(self.frame_slider.value)))
        self.blur_px.on_update(lambda _: self.show(int(self.frame_slider.value)))

    def _set_frusta_visible(self, on: bool) -> None:
        for h in self.frusta:
            h.visible = bool(on)

    def set_playing(self, on: bool) -> None:
        self.playing = bool(on)
        self.play_button.label = "Pause" if self.playing else "Play"

    def select_sequence(self, name: str) -> None:
        with self._lock:
            self.current = self.sequences[name]
            self.frame_slider.max = max(len(self.current.frames) - 1, 1)
            if self.frame_slider.value > len(self.current.frames) - 1:
                self.frame_slider.value = 0  # shows frame 0 through the slider's callback
            else:
                self.show(int(self.frame_slider.value))

    def load_pose_file(self, path: str | Path) -> bool:
        """Add a pose file as a timeline and switch to it; a bad file is reported in the panel, not raised."""
        try:
            seq = self._read_pose_file(path)
        except ViewerError as e:
            self.pose_status.content = f"**could not load**: {e}"
            log.warning("%s", e)
            return False
        self.seq_dropdown.options = tuple(self.sequences)
        self.pose_status.content = f"loaded {seq.name}: {len(seq.frames)} frames"
        self.seq_dropdown.value = seq.name  # switches through the dropdown's callback
        return True

    def _on_upload(self) -> None:
        up = self.pose_upload.value
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / Path(up.name or "upload.npz").name
            path.write_bytes(up.content)
            self.load_pose_file(path)  # named after the uploaded file

    # ------------------------------------------------------------------ updates
    def show(self, index: int) -> dict:
        """Pose frame `index` of the current timeline (or the canonical Gaussians) and send it to the browsers."""
        with self._lock:
            index = int(np.clip(index, 0, len(self.current.frames) - 1))
            t0, c0 = time.perf_counter(), time.process_time()
            if self.canonical.value:
                g = self._gaussians_for(self.avatar)
                if "rgb" not in g:  # SH colour model: its degree-0 term
                    g["rgb"] = np.clip(g["sh"][:, 0] * 0.28209479177387814 + 0.5, 0, 1)
            else:
                g = self.posed(self.current, index)
            t1 = time.perf_counter()
            self.splats.set_gaussians(g["means"], covariances(g["quats"], g["scales"], self.blur()), g["rgb"],
                                      g["opacities"][:, None])
            t2 = time.perf_counter()
            timing = {"frame": self.current.frames[index], "deform_s": t1 - t0, "pack_s": t2 - t1, "total_s": t2 - t0,
                      "cpu_s": time.process_time() - c0, "num_gaussians": int(g["means"].shape[0])}
            self.timings.append(timing)
            del self.timings[:-200]
            self._update_labels(index, timing)
            return timing

    def _update_labels(self, index: int, timing: dict) -> None:
        seq, frame = self.current, self.current.frames[index]
        self.frame_label.content = f"{seq.name}: frame **{frame}** ({index + 1}/{len(seq.frames)})"
        self.rate_label.content = (f"update {1000 * timing['total_s']:.0f} ms (pose+colour "
                                   f"{1000 * timing['deform_s']:.0f} ms), {timing['num_gaussians']} Gaussians")
        rows = self.per_frame.get((METRIC_SPLIT.get(seq.split or "", ""), frame), []) if seq.split else []
        if not rows:
            self.frame_metrics.content = f"frame {frame}: no held-out image (per_frame.csv)"
            return
        lines = [f"frame {frame} ({METRIC_SPLIT[seq.split]})", "", "| view | PSNR | IoU |", "|---|---|---|"]
        for view, p, iou in sorted(rows):
            lines.append(f"| {view} | {'–' if p is None else f'{p:.2f}'} | {'–' if iou is None else f'{iou:.3f}'} |")
        self.frame_metrics.content = "\n".join(lines)

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if not self.playing:
                self._stop.wait(0.05)
                continue
            t0 = time.perf_counter()
            with self._lock:
                nxt = (int(self.frame_slider.value) + 1) % len(self.current.frames)
                self.frame_slider.value = nxt  # the slider's callback poses and sends the frame
            period = 1.0 / (float(self.fps.value) * float(self.speed.value))
            self._stop.wait(max(period - (time.perf_counter() - t0), 0.001))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.server.stop()


def load_viewer(vcfg, overrides: list[str] | None = None) -> AvatarViewer:
    """Rebuild the run of `vcfg.run_dir` (overrides apply to its config) and start its viewer."""
    from realityavatar.build import build_data, load_avatar, run_device

    run_dir = Path(str(vcfg.run_dir))
    check_port_free(str(vcfg.host), int(vcfg.port))  # before the run loads: seconds saved on a busy port
    if not run_dir.is_dir():
        raise ViewerError(f"run_dir={run_dir}: no such folder; expected a run folder written by realityavatar-train")
    try:
        cfg, avatar, _ = load_avatar(run_dir, overrides)
    except FileNotFoundError as e:
        raise ViewerError(f"run_dir={run_dir}: {e}") from None
    avatar.to(run_device(cfg, vcfg.get("device")))
    dm = build_data(cfg, avatar.body)
    return AvatarViewer(avatar, dm, run_dir, host=str(vcfg.host), port=int(vcfg.port), split=str(vcfg.split),
                        poses=vcfg.get("poses"), fps=vcfg.get("fps"), frustum_scale=float(vcfg.frustum_scale),
                        poses_fps=vcfg.get("poses_fps"), up=str(vcfg.up), place=str(vcfg.place))


def compose_view(args: list[str]) -> tuple[object, list[str]]:
    """Split the command line into the viewer's settings (keys of conf/view.yaml, composed by hydra) and overrides of
    the run's config."""
    from omegaconf import OmegaConf

    from realityavatar.config import CONFIG_DIR, compose

    keys = set(OmegaConf.load(CONFIG_DIR / "view.yaml").keys())
    mine = [a for a in args if a.split("=", 1)[0] in keys]
    cfg = compose(mine, config_name="view")
    OmegaConf.set_struct(cfg, False)
    cfg.pop("hydra", None)
    return cfg, [a for a in args if a not in mine]


def main(argv: list[str] | None = None, block: bool = True) -> int:
    from omegaconf import OmegaConf

    from realityavatar.runtime import set_threads

    args = list(sys.argv[1:] if argv is None else argv)
    vcfg, overrides = compose_view(args)
    if OmegaConf.is_missing(vcfg, "run_dir"):
        print(__doc__, file=sys.stderr)
        return 2
    try:
        set_threads(vcfg.get("threads"))
    except ValueError as e:
        print(f"realityavatar-view: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        viewer = load_viewer(vcfg, overrides)
    except ViewerError as e:
        print(f"realityavatar-view: {e}", file=sys.stderr)
        return 2
    print(f"realityavatar-view: {viewer.url}  ({len(viewer.avatar.canonical_gaussians()['means'])} Gaussians, ready in "
          f"{time.perf_counter() - t0:.1f} s; Ctrl-C stops)", flush=True)
    if not block:
        viewer.close()
        return 0
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
