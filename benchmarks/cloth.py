"""Cloth convergence: the demo's skirt simulated at doubling resolutions until the drape stops changing.

For each resolution (vertices around x rings) the whole demo motion is simulated; each cloth is resampled to one
(u, v) grid (the coarsest's) and compared with the next coarser one: the rest drape (frame 0, every grid point), the
spin's hem (the hem ring over the spin's frames) and the spin's flare (the hem's mean distance from the body's axis).
A last row simulates one resolution again from another seed's initial ripple: the floor below which no resolution
can agree. Prints a table (cm; simulation seconds and GEMM units, 8 float32 1024^3 matmuls, so CPUs compare) and
writes benchmarks/results/cloth.json.
Usage: python benchmarks/cloth.py [--res 20x10 40x20 80x40] [--floor 40x20] [--sequence skirt_spin] [--save DIR]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch
from garment import gemm_unit  # benchmarks/garment.py: 8 float32 1024^3 matmuls, one thread
from scipy.interpolate import RegularGridInterpolator

from realityavatar.body import build_body
from realityavatar.data.synthetic.cloth import simulate_garment
from realityavatar.data.synthetic.motions import make_motion
from realityavatar.data.synthetic.scene import body_sequence, resolve_params


def demo_motion(sequence: str):
    """Skeleton [F,24,3], rotations [F,24,3,3], fps, garment, spin frames (start, stop), cloth parameters and the
    posed body (vertices [F,V,3], faces) of the demo preset."""
    p = resolve_params("demo", sequence=sequence)
    body = build_body(p["body"])
    rest_v = body.rest_vertices.numpy().astype(np.float64)
    pelvis = body.rest_joints[0].numpy().astype(np.float64)
    motion = make_motion(p["motion"], p["fps"], p["train_frames"], p["novel_frames"], pelvis,
                         float(pelvis[1] - rest_v[:, 1].min()), seed=0, params=p["motion_params"])
    verts, _, joints, rots = body_sequence(body, motion)
    ev = motion.events
    spin = (ev.get("spin_start_frame", 0), ev.get("spin_stop_frame", motion.num_train - 1))
    return joints, rots, p["fps"], p["garment"], spin, p["cloth_params"], (verts, body.faces.numpy())


def picture(path: Path, cloths: list[tuple[np.ndarray, np.ndarray]], body, frames: list[int], size: int = 256):
    """Rows: each cloth (vertices [F,V,3], faces) untextured on the body, at `frames`, from the demo's cameras 0 and
    2 (front, and 120 degrees round), framed on the skirt. Saved as a PNG."""
    from PIL import Image

    from realityavatar.data.synthetic.cameras import ring_cameras
    from realityavatar.data.synthetic.render import render_views

    Ks, views = ring_cameras(6, 2.8, 1.2, 0.7, size, size, 1.75, 1.6)  # closer in on the hips than the scene's
    grey, blue = (lambda f, b: np.full((len(b), 3), 0.8)), (lambda f, b: np.full((len(b), 3), [0.35, 0.3, 0.6]))
    rows = []
    for vertices, faces in cloths:
        tiles = [render_views([(body[0][f], body[1], blue), (vertices[f], faces, grey)], Ks[[0, 2]], views[[0, 2]],
                              size, size, supersample=2)[0] for f in frames]
        rows.append(np.concatenate([np.concatenate(list(t), 1) for t in tiles], 1))
    Image.fromarray(np.concatenate(rows, 0)).save(path, optimize=True)


def resample(vertices: np.ndarray, n_around: int, n_rings: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cloth vertices [F, n_rings*(n_around+1), 3] (rows by ring, seam column duplicated) at (u, v) [K] -> [F,K,3]."""
    grid = vertices.reshape(len(vertices), n_rings, n_around + 1, 3).transpose(1, 2, 0, 3)  # [R,A+1,F,3]
    f = RegularGridInterpolator((np.linspace(0, 1, n_rings), np.arange(n_around + 1) / n_around), grid)
    return f(np.stack([v, u], 1)).transpose(1, 0, 2)


def hem_radius(x: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Distance of cloth points x [F,K,3] from the body's axis (pelvis -> neck) per frame: [F,K] (metres)."""
    pelvis, axis = joints[:, 0], joints[:, 12] - joints[:, 0]
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    d = x - pelvis[:, None]
    return np.linalg.norm(d - (d * axis[:, None]).sum(-1, keepdims=True) * axis[:, None], axis=-1)


def changes(a: np.ndarray, b: np.ndarray, hem: np.ndarray, spin: slice, joints: np.ndarray) -> dict:
    """Distances (cm) between two resampled cloths [F,K,3]: every point at rest (frame 0), the hem over the spin, and
    the spin's flare (the hem's mean distance from the body's axis per frame)."""
    rest = np.linalg.norm(a[0] - b[0], axis=-1) * 100
    sp = np.linalg.norm(a[spin, hem] - b[spin, hem], axis=-1).ravel() * 100
    flare = np.abs(hem_radius(a[spin, hem], joints[spin]).mean(1) - hem_radius(b[spin, hem], joints[spin]).mean(1)) * 100
    r = lambda x: round(float(x), 2)
    return {"rest_median_cm": r(np.median(rest)), "rest_p90_cm": r(np.percentile(rest, 90)),
            "spin_hem_median_cm": r(np.median(sp)), "spin_hem_p90_cm": r(np.percentile(sp, 90)),
            "spin_flare_median_cm": r(np.median(flare))}


COLUMNS = ("rest_median_cm", "rest_p90_cm", "spin_hem_median_cm", "spin_hem_p90_cm", "spin_flare_median_cm")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--res", nargs="+", default=["20x10", "40x20", "80x40"], help="around x rings, coarse to fine")
    ap.add_argument("--floor", default="40x20", help="resolution simulated again from another seed's 1 mm ripple: "
                    "how far the cloth moves from its initial state alone (the floor of any convergence)")
    ap.add_argument("--sequence", default="skirt_spin")
    ap.add_argument("--save", default=None, help="folder for each resolution's simulated cloth (npz)")
    ap.add_argument("--picture", default=None, help="PNG of each cloth untextured at rest and mid-spin, two cameras")
    ap.add_argument("--before", nargs="*", default=[], help="-garment.npz files of earlier scenes: rows above the "
                    "picture's (the same motion simulated by another generator)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "cloth.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    joints, rots, fps, garment, (s0, s1), cloth_params, body = demo_motion(args.sequence)
    sizes = [tuple(int(x) for x in r.split("x")) for r in args.res]
    na0, nr0 = sizes[0]
    uu, vv = np.meshgrid(np.arange(na0) / na0, np.linspace(0, 1, nr0))  # the coarsest grid's points (no seam copy)
    u, v = uu.ravel(), vv.ravel()
    hem, spin = v == 1.0, slice(s0, s1 + 1)
    unit = gemm_unit()

    def simulate(na: int, nr: int, seed: int = 0):
        t0 = time.perf_counter()
        g = simulate_garment(joints, rots, fps, garment, {**cloth_params, "n_around": na, "n_rings": nr}, seed=seed)
        sec = time.perf_counter() - t0
        if args.save:
            Path(args.save).mkdir(parents=True, exist_ok=True)
            np.savez(Path(args.save) / f"cloth_{na}x{nr}_seed{seed}.npz", v=g.vertices, faces=g.faces, uv=g.uv)
        if seed == 0:
            meshes.append((g.vertices, g.faces))
        return resample(g.vertices, na, nr, u, v), sec

    rows, prev, cloths, meshes = [], None, {}, []
    for na, nr in sizes:
        x, sec = simulate(na, nr)
        cloths[f"{na}x{nr}"] = x
        row = {"resolution": f"{na}x{nr}", "vertices": na * nr, "sim_s": round(sec, 1),
               "sim_gemm_units": round(sec / unit), "frames": len(joints)}
        if prev is not None:
            row |= changes(x, prev, hem, spin, joints)
        rows.append(row)
        prev = x
        print(json.dumps(row), flush=True)
    if args.floor:
        na, nr = (int(x) for x in args.floor.split("x"))
        x, sec = simulate(na, nr, seed=1)
        rows.append({"resolution": f"{na}x{nr} seed 1 vs 0", "vertices": na * nr, "sim_s": round(sec, 1),
                     "sim_gemm_units": round(sec / unit), "frames": len(joints),
                     **changes(x, cloths[args.floor] if args.floor in cloths else simulate(na, nr)[0], hem, spin, joints)})
        print(json.dumps(rows[-1]), flush=True)
    print("\nchange from the previous row (cm): every point at rest (median, p90), the hem over the spin (median, p90), "
          "the spin's flare (median)")
    print(f"{'resolution':>20}" + "".join(f"{c.replace('_cm', ''):>21}" for c in COLUMNS) + f"{'sim s':>8}{'GEMM u':>8}")
    for r in rows:
        print(f"{r['resolution']:>20}" + "".join(f"{r.get(c, float('nan')):>21.2f}" for c in COLUMNS)
              + f"{r['sim_s']:>8.1f}{r['sim_gemm_units']:>8}")
    if args.picture:
        before = [(np.load(f)["vertices"], np.load(f)["faces"]) for f in args.before]
        picture(Path(args.picture), before + meshes, body, [0, (s0 + s1) // 2])
        print(f"wrote {args.picture}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "sequence": args.sequence, "spin_frames": [int(s0), int(s1)],
                               "gemm_unit_s": unit, "cpu": platform.processor() or platform.machine(),
                               "cloth_params": cloth_params}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
