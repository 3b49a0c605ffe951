"""Export canonical or posed Gaussians to PLY in the standard 3DGS layout that common splat viewers read.

Commands: `realityavatar-export run_dir=<run> [frame=<global frame id>] [out=<file.ply>]` (no frame: canonical space);
`realityavatar-export run_dir=<run> frames=a:b[:step] [poses=<file.npz> [fps=] [up=] [place=]] [out=<folder>]`: one
PLY per frame a <= f < b (global frame ids of the run's sequence, or frames of the pose file resampled to the run's
frame rate, as realityavatar-animate reads it), the same posed Gaussians `realityavatar-view` shows.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

SH_C0 = 0.28209479177387814


def write_ply(path: str | Path, means, quats, scales, opacities, sh: np.ndarray | None = None, rgb: np.ndarray | None = None) -> Path:
    """Write a 3DGS PLY. means [N,3], quats [N,4] wxyz, scales [N,3] (linear), opacities [N] in (0,1),
    either sh [N,K,3] (K = (d+1)^2) or rgb [N,3] in [0,1] (stored as the degree-0 SH term)."""
    means, quats, scales, opacities = (np.asarray(x, dtype=np.float32) for x in (means, quats, scales, opacities))
    N = means.shape[0]
    for name, arr, shape in (("means", means, (N, 3)), ("quats", quats, (N, 4)), ("scales", scales, (N, 3)), ("opacities", opacities, (N,))):
        if arr.shape != shape:
            raise ValueError(f"write_ply: {name} must have shape {shape}, got {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"write_ply: {name} has non-finite values")
    if sh is None:
        if rgb is None:
            raise ValueError("write_ply: give either sh [N,K,3] or rgb [N,3]")
        sh = ((np.asarray(rgb, np.float32) - 0.5) / SH_C0)[:, None, :]
    sh = np.asarray(sh, np.float32)
    K = sh.shape[1]
    eps = 1e-7
    fields = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    fields += [(n, np.zeros(N, np.float32)) for n in ("nx", "ny", "nz")]
    fields += [(f"f_dc_{i}", sh[:, 0, i]) for i in range(3)]
    # 3DGS stores the rest coefficients channel-major: all R, then all G, then all B.
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(N, -1) if K > 1 else np.zeros((N, 0), np.float32)
    fields += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    op = np.clip(opacities, eps, 1 - eps)
    fields += [("opacity", np.log(op / (1 - op)))]
    fields += [(f"scale_{i}", np.log(np.maximum(scales[:, i], eps))) for i in range(3)]
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True).clip(eps)
    fields += [(f"rot_{i}", q[:, i]) for i in range(4)]
    arr = np.empty(N, dtype=[(n, "<f4") for n, _ in fields])
    for n, v in fields:
        arr[n] = v
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {N}\n"
    header += "".join(f"property float {n}\n" for n, _ in fields) + "end_header\n"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".ply.tmp")
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(arr.tobytes())
    tmp.replace(path)
    return path


def read_ply(path: str | Path) -> dict:
    """Read a 3DGS PLY back: means, quats, scales (linear), opacities (0..1), sh [N,K,3]."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    n = int(next(h.split()[2] for h in header if h.startswith("element vertex")))
    names = [h.split()[2] for h in header if h.startswith("property float")]
    arr = np.frombuffer(data[end + len(b"end_header\n") :], dtype=[(nm, "<f4") for nm in names], count=n)
    rest = sorted([nm for nm in names if nm.startswith("f_rest_")], key=lambda s: int(s.split("_")[-1]))
    K = 1 + len(rest) // 3
    sh = np.zeros((n, K, 3), np.float32)
    sh[:, 0] = np.stack([arr[f"f_dc_{i}"] for i in range(3)], 1)
    if rest:
        sh[:, 1:] = np.stack([arr[r] for r in rest], 1).reshape(n, 3, K - 1).transpose(0, 2, 1)
    return {
        "means": np.stack([arr["x"], arr["y"], arr["z"]], 1),
        "quats": np.stack([arr[f"rot_{i}"] for i in range(4)], 1),
        "scales": np.exp(np.stack([arr[f"scale_{i}"] for i in range(3)], 1)),
        "opacities": 1 / (1 + np.exp(-arr["opacity"])),
        "sh": sh,
    }


def gaussians_for_export(avatar, poses: torch.Tensor | None = None, transl: torch.Tensor | None = None,
                         frame: int | None = None) -> dict:
    """`avatar.baked(poses, transl, frame)` (model/avatar.py: canonical, or posed by one pose window, colour baked) as
    numpy arrays: what `export_gaussians` writes and what `realityavatar-view` streams. frame: the window's last
    frame in the motion a garment with state was driven on (sheet=physics)."""
    return {k: v.detach().cpu().float().numpy() for k, v in avatar.baked(poses, transl, frame).items()}


def export_gaussians(avatar, out: Path, poses: torch.Tensor | None = None, transl: torch.Tensor | None = None,
                     frame: int | None = None) -> Path:
    """Write `gaussians_for_export(avatar, poses, transl, frame)` to the PLY `out`."""
    return write_ply(out, **gaussians_for_export(avatar, poses, transl, frame))


ARGS = {"run_dir", "frame", "frames", "poses", "fps", "up", "place", "out", "threads"}
USAGE = ("usage: realityavatar-export run_dir=<run> [frame=<global frame id> | frames=a:b[:step] [poses=<file.npz> "
         "[fps=<its frame rate>] [up=auto|z|y] [place=subject|keep]]] [out=<file.ply or folder>] [threads=N]")


def parse_frames(text: str) -> slice:
    """`frames=a:b[:step]` -> slice(a, b, step): half-open like Python, a or b may be left out (`:40`, `10:`)."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        a, b, *st = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ValueError(f"frames={text!r}: expected a:b or a:b:step with whole numbers (frames a <= f < b)") from None
    step = st[0] if st and st[0] is not None else 1
    if step < 1:
        raise ValueError(f"frames={text!r}: step must be >= 1")
    return slice(a, b, step)


def select_frames(available, frames: slice, source: str) -> list[int]:
    """The frame ids of `available` (sorted ids) with frames.start <= f < frames.stop, every frames.step-th."""
    available = [int(f) for f in available]
    lo = available[0] if frames.start is None else frames.start
    hi = available[-1] + 1 if frames.stop is None else frames.stop
    chosen = [f for f in available if lo <= f < hi][:: frames.step]
    if not chosen:
        raise ValueError(f"frames={lo}:{hi} selects no frame of {source} (it has frames {available[0]}..{available[-1]})")
    return chosen


def export_frames(avatar, table, frame_ids: list[int], window_len: int, window_step: int, out_dir: Path) -> list[Path]:
    """One PLY of posed Gaussians per frame id of `table` (a PoseTable; windows look back into the whole table; a
    garment with state is simulated on the table's motion first)."""
    paths = []
    avatar.drive(table)
    for f in frame_ids:
        poses, transl = table.window(int(f), window_len, window_step)
        paths.append(export_gaussians(avatar, out_dir / f"posed_{int(f):06d}.ply", poses, transl, int(f)))
    return paths


def main(argv: list[str] | None = None) -> int:
    from realityavatar.animate import number, parse_args
    from realityavatar.build import build_data, load_avatar
    from realityavatar.data.motion import Stage, load_motion
    from realityavatar.runtime import set_threads

    try:
        args = parse_args(sys.argv[1:] if argv is None else argv, ARGS)
        set_threads(args.get("threads"))
    except ValueError as e:
        print(f"realityavatar-export: {e}\n{USAGE}", file=sys.stderr)
        return 2
    if "run_dir" not in args:
        print(USAGE, file=sys.stderr)
        return 2
    if "frame" in args and "frames" in args:
        print(f"realityavatar-export: give frame=<id> or frames=a:b, not both\n{USAGE}", file=sys.stderr)
        return 2
    pose_file = sorted({"poses", "fps", "up", "place"} & set(args))
    if pose_file and not {"poses", "frames"} <= set(args):  # else ignored: the canonical or a dataset frame written
        print(f"realityavatar-export: {', '.join(k + '=' for k in pose_file)} apply to frames=a:b of a pose file: "
              f"give both poses=<file.npz> and frames=a:b\n{USAGE}", file=sys.stderr)
        return 2
    frames = parse_frames(args["frames"]) if "frames" in args else None  # checked before the run is loaded
    cfg, avatar, _info = load_avatar(args["run_dir"], [f"{k}={v}" for k, v in args.items() if "." in k])
    frame = args.get("frame")
    if frames is not None:
        dm = build_data(cfg, avatar.body)
        if "poses" in args:
            table = load_motion(args["poses"], avatar.body, Stage.of(dm, avatar.body), number(args, "fps"),
                                args.get("up", "auto"), args.get("place", "subject"))
            source = f"pose file {args['poses']}"
            default = Path(args["run_dir"]) / "export" / Path(args["poses"]).stem
        else:
            table, source, default = dm.scene.poses, f"run {args['run_dir']}", Path(args["run_dir"]) / "export" / "frames"
        ids = select_frames(table.frames, frames, source)
        out_dir = Path(args.get("out", default))
        export_frames(avatar, table, ids, dm.window_len, dm.window_step, out_dir)
        print(f"wrote {len(ids)} PLY files (frames {ids[0]}..{ids[-1]}) to {out_dir}")
        return 0
    out = Path(args.get("out", Path(args["run_dir"]) / "export" / (f"posed_{frame}.ply" if frame else "canonical.ply")))
    if frame is None:
        export_gaussians(avatar, out)
    else:
        dm = build_data(cfg, avatar.body)
        poses, transl = dm.window_for(dm.scene.poses, int(frame))
        export_gaussians(avatar, out, poses, transl, int(frame))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
