"""Animate a trained avatar: a pose sequence (a dataset split or an .npz file) rendered from chosen cameras to MP4.

Command: `realityavatar-animate run_dir=<run> [poses=<file.npz> | split=novel_pose] [views=0,2] [out=<file.mp4>] [fps=25]
[device=cuda|cpu]` (default: the GPU when the run trained on one and CUDA is present)
The .npz holds `poses` [F,24,3] or [F,72] (SMPL axis-angle, pose[0] = global orientation) and `transl` [F,3];
optionally `Rh`, `Th` [F,3] in the EasyMocap convention (converted with the body model's pelvis).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.poses import PoseTable


def load_pose_file(path: str | Path, body) -> PoseTable:
    """Read an animation .npz into a PoseTable; errors name the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file {path} not found")
    with np.load(path) as z:
        if "poses" not in z:
            raise KeyError(f"{path}: missing field 'poses' ([F,24,3] or [F,72] axis-angle); fields present: {list(z.keys())}")
        poses = np.asarray(z["poses"], np.float32)
        if poses.ndim == 0 or poses.shape[0] == 0:
            raise ValueError(f"{path}: field 'poses' has no frames (shape {poses.shape}); expected [F,24,3] or [F,72] "
                             "with F >= 1")
        F = poses.shape[0]
        if poses[0].size != 72:
            raise ValueError(f"{path}: field 'poses' must be [F,24,3] or [F,72], got {poses.shape}")
        poses = poses.reshape(F, 24, 3)
        if not np.isfinite(poses).all():
            raise ValueError(f"{path}: field 'poses' has non-finite values (NaN/inf)")

        def per_frame(key: str) -> np.ndarray:
            a = np.asarray(z[key], np.float32)
            if a.shape != (F, 3):
                raise ValueError(f"{path}: field {key!r} must be [{F},3] (one 3-vector per frame of 'poses'), got "
                                 f"{a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"{path}: field {key!r} has non-finite values (NaN/inf)")
            return a

        transl = per_frame("transl") if "transl" in z else np.zeros((F, 3), np.float32)
        p, t = torch.from_numpy(poses), torch.from_numpy(transl)
        if ("Rh" in z) != ("Th" in z):
            raise ValueError(f"{path}: fields 'Rh' and 'Th' come together (EasyMocap placement); only "
                             f"{'Rh' if 'Rh' in z else 'Th'} is present")
        if "Rh" in z:
            rh, th = per_frame("Rh"), per_frame("Th")
            p, t = rh_th_to_smpl(p, torch.from_numpy(rh), torch.from_numpy(th) + t, body.rest_joints[0])
    return PoseTable.from_sequence(p, t)


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


@torch.no_grad()
def render_sequence(module, table: PoseTable, cameras: list[dict], window_len: int, window_step: int,
                    frames_to_render=None) -> list[np.ndarray]:
    """Render frames of `table` (all, or `frames_to_render`; windows look back into the whole table) from each
    camera; returns uint8 frames [H, W*len(cameras), 3]."""
    dev, dt = module.device, module.dtype  # poses and cameras come as float32 CPU tensors
    frames = []
    for f in (table.frames if frames_to_render is None else frames_to_render):
        poses, transl = table.window(int(f), window_len, window_step)
        idx = torch.full((1,), -1, dtype=torch.long, device=dev)
        posed = module.deform(poses[None].to(dev, dt), transl[None].to(dev, dt))
        tiles = []
        for cam in cameras:
            vm = cam["viewmat"][None].to(dev, dt)
            rgb = module.shade(posed, vm, idx)[0]
            img, _, _ = module.splat(posed, 0, rgb, vm, cam["K"][None].to(dev, dt), cam["width"], cam["height"])
            tiles.append((img[0].clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8))
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


def main(argv: list[str] | None = None) -> int:
    import imageio.v2 as imageio

    from realityavatar.build import build_data, load_run, run_device

    args = dict(a.split("=", 1) for a in (sys.argv[1:] if argv is None else argv) if "=" in a)
    if "run_dir" not in args:
        print(__doc__, file=sys.stderr)
        return 2
    cfg, module, _info = load_run(args["run_dir"])
    module.to(run_device(cfg, args.get("device")))
    dm = build_data(cfg, module.body)
    split = args.get("split", "novel_pose")
    if "poses" in args:
        table, frame_ids = load_pose_file(args["poses"], module.body), None
        name = Path(args["poses"]).stem
    else:
        table, frame_ids = dm.scene.poses, dm.pose_sequence(split)[0].tolist()
        name = split
    views = [int(v) for v in args["views"].split(",")] if "views" in args else None
    cameras = dataset_cameras(dm, views, split if split in dm.datasets else None)
    out = Path(args.get("out", Path(args["run_dir"]) / "animations" / f"{name}.mp4"))
    check_video_writer(out)
    frames = render_sequence(module, table, cameras, dm.window_len, dm.window_step, frame_ids)
    out.parent.mkdir(parents=True, exist_ok=True)
    fps = float(args.get("fps", 25))
    if out.suffix.lower() == ".gif":
        imageio.mimwrite(out, frames, duration=1000.0 / fps, loop=0)
    else:
        imageio.mimwrite(out, frames, fps=fps, macro_block_size=1)
    print(f"wrote {out} ({len(frames)} frames, {len(cameras)} cameras)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
