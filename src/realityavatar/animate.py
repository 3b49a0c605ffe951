"""Animate a trained avatar: a pose sequence (a dataset split or a motion file) rendered to a video that plays in real
time, from dataset cameras and/or a camera orbiting the moving avatar.

Command: `realityavatar-animate run_dir=<run> [poses=<file.npz> [fps=<the file's frame rate>] [up=auto|z|y]
[place=subject|keep] | split=novel_pose] [cameras=dataset|orbit|orbit,dataset] [views=0,2] [orbit.turns=1]
[orbit.height=<m>] [orbit.radius=<m>] [out=<file.mp4|.gif>] [device=cuda|cpu] [threads=N] [data.<key>=<value>]`
Pose files (AMASS/SMPL-H, SMPL-X, SMPL) are read by data/motion.py: resampled to the frame rate the run was trained
at (data.fps), turned upright and placed in the dataset's world; the video plays at that rate. See docs/animate.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from realityavatar.data.motion import Stage, load_motion, posed_joints
from realityavatar.data.poses import PoseTable
from realityavatar.geometry import camera_centres


def dataset_cameras(dm, views: list[int] | None = None, split: str | None = None) -> list[dict]:
    """Cameras (K, viewmat, width, height, view) of a DataModule's split, at the loader's image scale."""
    split = split or ("novel_pose" if "novel_pose" in dm.datasets else "train")
    ds = dm.datasets[split]
    first = {}
    for i, rec in enumerate(ds.records):
        first.setdefault(rec.view, i)
    wanted = sorted(first) if views is None else views
    missing = [v for v in wanted if v not in first]
    if missing:
        raise ValueError(f"views {missing} are not cameras of split {split!r} (available {sorted(first)})")
    cams = []
    for v in wanted:
        item = ds[first[v]]
        cams.append({k: item[k] for k in ("K", "viewmat", "width", "height", "view")})
    return cams


def orbit_camera(stage: Stage, pelvis: np.ndarray, cameras: list[dict], turns: float = 1.0,
                 height: float | None = None, radius: float | None = None) -> dict:
    """A turntable camera around the moving avatar, one viewmat per frame [N,4,4]: `turns` turns over the N frames
    of pelvis [N,3], from the first camera's side, at `radius` m from the pelvis and `height` m above the ground,
    looking at the pelvis (at the training subject's mean pelvis height). Radius and height default to the mean of
    the dataset `cameras` (about the training subject); K and image size are the first camera's."""
    from realityavatar.data.synthetic.cameras import look_at

    up = stage.up
    rel = camera_centres(torch.stack([c["viewmat"] for c in cameras]).double()).numpy() - stage.centre  # [C,3]
    flat = rel - (rel @ up)[:, None] * up
    height = float(np.mean(rel @ up) + stage.centre @ up - stage.ground) if height is None else height
    radius = float(np.linalg.norm(flat, axis=1).mean()) if radius is None else radius
    if not (np.isfinite([turns, height, radius]).all() and radius > 0):
        raise ValueError(f"orbit: expected finite turns and height and radius > 0, got turns={turns}, "
                         f"height={height}, radius={radius}")
    a = flat[0] / np.linalg.norm(flat[0])
    b = np.cross(up, a)
    look = stage.centre @ up - stage.ground  # the training subject's mean pelvis height above the ground
    viewmats = []
    for k, p in enumerate(pelvis):
        ground = p - (p @ up - stage.ground) * up
        angle = 2 * np.pi * turns * k / len(pelvis)
        eye = ground + radius * (np.cos(angle) * a + np.sin(angle) * b) + height * up
        viewmats.append(look_at(eye, ground + look * up, up))
    cam = cameras[0]
    return {"K": cam["K"], "viewmat": torch.as_tensor(np.stack(viewmats), dtype=torch.float32),
            "width": cam["width"], "height": cam["height"], "view": "orbit"}


@torch.no_grad()
def render_sequence(avatar, table: PoseTable, cameras: list[dict], window_len: int, window_step: int,
                    frames_to_render=None) -> list[np.ndarray]:
    """Render frames of `table` (all, or `frames_to_render`; windows look back into the whole table) from each
    camera (a fixed viewmat [4,4], or one per rendered frame [N,4,4]); returns uint8 frames [H, W*len(cameras), 3].
    A garment with state (sheet=physics) is simulated on the table's motion first."""
    frames = []
    avatar.drive(table)
    for i, f in enumerate(table.frames if frames_to_render is None else frames_to_render):
        posed = avatar.posed(*table.window(int(f), window_len, window_step), frame=int(f))
        tiles = []
        for cam in cameras:
            vm = cam["viewmat"] if cam["viewmat"].ndim == 2 else cam["viewmat"][i]
            img = avatar.render_view(posed, vm, cam["K"], cam["width"], cam["height"])
            tiles.append((img.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8))
        frames.append(np.concatenate(tiles, 1))
    return frames


def check_video_writer(path: str | Path) -> None:
    """Fail before rendering when writing `path` needs ffmpeg (every format but .gif) and imageio has none: without
    it imageio picks another plugin by the suffix and fails after the render with an unrelated TypeError."""
    if Path(path).suffix.lower() == ".gif":
        return
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except Exception as exc:  # noqa: BLE001 - ImportError, or RuntimeError when the package finds no binary
        raise RuntimeError(f"{path}: writing a video needs ffmpeg through the imageio-ffmpeg package "
                           f"({type(exc).__name__}: {exc}); pip install imageio-ffmpeg, set IMAGEIO_FFMPEG_EXE "
                           "to an ffmpeg binary, or write a .gif (out=...gif)") from None


ARGS = {"run_dir", "poses", "fps", "up", "place", "split", "cameras", "views", "orbit.turns", "orbit.height",
        "orbit.radius", "out", "device", "threads"}


def parse_args(argv: list[str], keys: set[str]) -> dict[str, str]:
    """`key=value` arguments: the command's own `keys`, and overrides of the run's config (`data.fps=...`). Anything
    else (a bare word, `pose=` for `poses=`, `orbit.radus=`) is a ValueError naming it: dropped, it would render or
    export something the user did not ask for without a word."""
    args = {}
    own = {k.split(".")[0] for k in keys if "." in k}  # dotted keys of the command's own (orbit.*)
    for a in argv:
        key, eq, value = a.partition("=")
        if not eq or not key:
            raise ValueError(f"{a!r}: expected key=value")
        if key not in keys and ("." not in key or key.split(".")[0] in own):
            raise ValueError(f"{key}=: unknown argument; expected one of {', '.join(sorted(keys))}, or an override of "
                             "the run's config (data.<key>=...)")
        args[key] = value
    return args


def number(args: dict, key: str, default: float | None = None) -> float | None:
    """args[key] as a float (default when absent); a non-number names the key."""
    if key not in args:
        return default
    try:
        return float(args[key])
    except ValueError:
        raise ValueError(f"{key}={args[key]!r}: expected a number") from None


def main(argv: list[str] | None = None) -> int:
    import imageio.v2 as imageio

    from realityavatar.build import build_data, load_avatar, run_device
    from realityavatar.runtime import set_threads

    try:
        args = parse_args(sys.argv[1:] if argv is None else argv, ARGS)
        set_threads(args.get("threads"))
    except ValueError as e:
        print(f"realityavatar-animate: {e}\n{__doc__}", file=sys.stderr)
        return 2
    if "run_dir" not in args:
        print(__doc__, file=sys.stderr)
        return 2
    if "fps" in args and "poses" not in args:
        raise ValueError(f"fps={args['fps']}: the frame rate of a pose file (poses=...); videos play at the rate the "
                         "run was trained at")
    kinds = args.get("cameras", "dataset").split(",")
    if not kinds or set(kinds) - {"dataset", "orbit"}:
        raise ValueError(f"cameras={args['cameras']}: expected dataset, orbit, or both (cameras=orbit,dataset)")
    split = args.get("split", "novel_pose")
    name = Path(args["poses"]).stem if "poses" in args else split
    out = Path(args.get("out", Path(args["run_dir"]) / "animations" / f"{name}.mp4"))
    check_video_writer(out)
    overrides = [f"{k}={v}" for k, v in args.items() if "." in k and not k.startswith("orbit.")]
    cfg, avatar, _info = load_avatar(args["run_dir"], overrides)
    dm = build_data(cfg, avatar.body)
    stage = Stage.of(dm, avatar.body)
    if "poses" in args:
        table = load_motion(args["poses"], avatar.body, stage, number(args, "fps"), args.get("up", "auto"),
                            args.get("place", "subject"))
        frame_ids = [int(f) for f in table.frames]
    else:
        table, frame_ids = dm.scene.poses, dm.pose_sequence(split)[0].tolist()
    views = [int(v) for v in args["views"].split(",")] if "views" in args else None
    dataset = dataset_cameras(dm, views, split if split in dm.datasets else None)
    cameras = []
    for kind in kinds:
        if kind == "dataset":
            cameras += dataset
            continue
        rows = torch.as_tensor(np.searchsorted(table.frames, frame_ids))
        pelvis = posed_joints(avatar.body, table.poses[rows], table.transl[rows])[:, 0]
        cameras.append(orbit_camera(stage, pelvis, dataset, number(args, "orbit.turns", 1.0),
                                    number(args, "orbit.height"), number(args, "orbit.radius")))
    avatar.to(run_device(cfg, args.get("device")))
    frames = render_sequence(avatar, table, cameras, dm.window_len, dm.window_step, frame_ids)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".gif":
        imageio.mimwrite(out, frames, duration=1000.0 / stage.fps, loop=0)
    else:
        imageio.mimwrite(out, frames, fps=stage.fps, macro_block_size=1)
    print(f"wrote {out} ({len(frames)} frames at {stage.fps:g} fps = {len(frames) / stage.fps:.2f} s, "
          f"{len(cameras)} cameras)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
