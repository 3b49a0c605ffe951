"""Exact image flow of a synthetic scene's training images (the oracle for `flow=files`), and a check of a flow
source against it.

For every training image (frame t, camera c) at the training resolution, each pixel-centre ray is cast against frame
t's posed body + simulated garment; the hit's triangle and barycentrics give the same material point at frame
t - gap, whose projection into camera c minus the pixel is the flow (the projected 3D motion of the visible surface,
whether or not the point is visible at t - gap). Written as <out>/<view:02d>/<frame:06d>.npz (flow [H,W,2] float16,
valid [H,W] bool: the ray hits and the mask holds the pixel), the layout `flow=files flow.dir=<out>` reads.

    python ablations/oracle_flow.py --data synthetic_sweep --out outputs/oracle_flow_sweep
    python ablations/oracle_flow.py --data synthetic_sweep --out <dir> --check dis   # DIS against the oracle

`--check dis` prints, per phase of the demo motion, the median end-point error of the DIS flow that `flow=dis`
computes and the median share of the true motion it recovers (its projection on the true flow over the true length).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _scene_meshes(root: Path, sequence: str, body):
    """Per frame: body vertices (world) [F,V,3], garment vertices [F,Vg,3], body faces, garment faces, frame ids."""
    from types import SimpleNamespace

    from realityavatar.data.records import load_pickle
    from realityavatar.data.synthetic.scene import body_sequence

    g = np.load(root / f"{sequence}-garment.npz")
    frames = [int(f) for f in g["frames"]]
    infos = {}
    for split in ("train", "novelpose"):
        path = root / f"{sequence}-{split}" / "mesh_infos.pkl"
        if path.exists():
            from realityavatar.data.i3d import parse_frame_name

            for name, info in load_pickle(path).items():
                infos.setdefault(parse_frame_name(str(name))[0], info)
    missing = [f for f in frames if f not in infos]
    if missing:
        raise ValueError(f"{root}/{sequence}: no mesh_infos entry for frames {missing[:5]}")
    motion = SimpleNamespace(
        pose=np.stack([np.asarray(infos[f]["poses"], np.float64).reshape(24, 3) for f in frames]),
        Rh=np.stack([np.asarray(infos[f]["Rh"], np.float64).reshape(3) for f in frames]),
        Th=np.stack([np.asarray(infos[f]["Th"], np.float64).reshape(3) for f in frames]),
    )
    verts_w = body_sequence(body, motion)[0]
    return verts_w, g["vertices"].astype(np.float64), body.faces.numpy(), g["faces"], frames


def oracle_flow(mesh_t: tuple[np.ndarray, np.ndarray], verts_p: np.ndarray, K: np.ndarray, E: np.ndarray,
                W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """mesh_t (vertices [V,3], faces [F,3]) at frame t; verts_p the same vertices at the earlier frame.
    Returns flow [H,W,2] (pixels, to the earlier frame) and hit [H,W] bool."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    from realityavatar.data.synthetic.render import camera_rays, first_hits

    V, Fc = mesh_t
    caster = RayMeshIntersector(trimesh.Trimesh(V, Fc, process=False, validate=False))
    tri, ray, bary = first_hits(caster, V, Fc, *camera_rays(K, E, W, H))
    prev = np.einsum("pk,pkc->pc", bary, verts_p[Fc[tri]])
    cam = prev @ E[:3, :3].T + E[:3, 3]
    uv = np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], -1)
    v, u = np.divmod(ray, W)
    flow = np.zeros((H, W, 2), np.float32)
    flow[v, u] = uv - np.stack([u + 0.5, v + 0.5], -1)
    hit = np.zeros((H, W), bool)
    hit[v, u] = True
    return flow, hit


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="synthetic_sweep", help="data config (a synthetic scene)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--gap", type=int, default=1, help="frames between the two images (flow.frame_gap)")
    ap.add_argument("--check", choices=["dis"], default=None, help="compare a flow source with the oracle")
    ap.add_argument("overrides", nargs="*", help="more config overrides (data.image_scale=0.5, ...)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from hydra.utils import instantiate

    from realityavatar.build import build_data
    from realityavatar.config import compose
    from realityavatar.data.flow import FlowSpec, flow_pair

    cfg = compose([f"data={a.data}", *a.overrides])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    ds = dm.datasets["train"]
    root = Path(dm.root)
    verts_b, verts_g, faces_b, faces_g, frames = _scene_meshes(root, dm.sequence, body)
    row = {f: i for i, f in enumerate(frames)}
    faces = np.concatenate([faces_b, faces_g + verts_b.shape[1]])
    events = json.loads((root / f"{dm.sequence}-meta.json").read_text())["motion"]["events"]
    out = Path(a.out)
    stats: dict[str, list] = {}
    for i, rec in enumerate(ds.records):
        p = rec.frame - a.gap
        if p not in row:
            continue
        img, mask, K = ds._decoded(i)
        H, W = mask.shape
        V_t = np.concatenate([verts_b[row[rec.frame]], verts_g[row[rec.frame]]])
        V_p = np.concatenate([verts_b[row[p]], verts_g[row[p]]])
        flow, hit = oracle_flow((V_t, faces), V_p, K, rec.viewmat, W, H)
        valid = hit & mask
        dst = out / f"{rec.view:02d}" / f"{rec.frame:06d}.npz"
        dst.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(dst, flow=flow.astype(np.float16), valid=valid)
        if a.check == "dis":
            j = ds._by_frame_view.get((p, rec.view))
            img_p, mask_p, _ = ds._decoded(j)
            f_dis, v_dis = flow_pair(img * mask[..., None], mask, img_p * mask_p[..., None], mask_p, FlowSpec())
            both = v_dis & valid
            gt, est = flow[both], f_dis[both]
            big = np.linalg.norm(gt, axis=1) > 1.0
            phase = _phase(rec.frame, events)
            stats.setdefault(phase, []).append((np.linalg.norm(est - gt, axis=1), np.linalg.norm(gt, axis=1),
                                                ((est * gt).sum(1) / (gt * gt).sum(1).clip(1e-9))[big]))
    print(f"oracle flow for {len(ds.records)} training images -> {out}")
    if stats:
        print("phase    pixels  |true| px  DIS end-point error px (median / p90)  share of the true motion (median)")
        for phase, rows in stats.items():
            err, mag, share = (np.concatenate(z) for z in zip(*rows))
            print(f"{phase:8s} {len(err):7d}  {np.median(mag):8.2f}  {np.median(err):6.2f} / {np.quantile(err, 0.9):5.2f}"
                  f"                    {np.median(share) if share.size else float('nan'):6.2f}")


def _phase(frame: int, events: dict) -> str:
    """rest / spin / after (the second after the stop) from the scene's motion events (frames), else 'all'."""
    try:
        s0, s1 = int(events["spin_start_frame"]), int(events["spin_stop_frame"])
    except (KeyError, TypeError, ValueError):
        return "all"
    if frame < s0:
        return "rest"
    if frame <= s1:
        return "spin"
    return "after" if frame <= s1 + 25 else "settled"


if __name__ == "__main__":
    main()
