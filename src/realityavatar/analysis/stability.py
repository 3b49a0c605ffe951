"""Stability report: abrupt stops, extreme unseen poses, pose-fit noise and seed spread.

Usage: python -m realityavatar.analysis.stability <run_dir or sweep_dir> [...] --out ablations/results/stability
       [--view V]
Every number comes from rendering the trained runs; the report is Markdown + PNG + JSON.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.metrics import psnr, temporal_flicker
from realityavatar.runtime import add_threads_option, set_threads

NOISE_SIGMAS = (0.0, 0.02, 0.05, 0.1)  # radians added to every joint rotation (pose-fit noise)


def find_runs(paths: list[str]) -> list[Path]:
    runs: list[Path] = []
    for p in map(Path, paths):
        runs += sorted({m.parent for m in p.rglob("metrics.json") if (m.parent / "last.ckpt").is_file()})
    if not runs:
        raise FileNotFoundError(f"no run folders (metrics.json + last.ckpt) under {paths}")
    return runs


def label_of(metrics: dict) -> str:
    cfg = metrics.get("config", {})
    return cfg.get("variant") or f"{cfg.get('encoder', '?')}/{cfg.get('temporal', '?')}"


def stop_frames(dm) -> list[int]:
    """Frames where a fast global rotation ends: from the synthetic scene's metadata, else the first frame of each
    "after" phase that the poses give (PoseTable.motion_phases, the evaluation's own phases)."""
    ev = (dm.scene.meta or {}).get("motion", {}).get("events", {})
    stops = [int(v) for k, v in ev.items() if k.endswith("stop_frame")]
    if stops or not dm.fps:
        return sorted(stops)
    frames = [int(f) for f in dm.scene.poses.frames]
    phases = dm.scene.poses.motion_phases(frames, dm.fps)
    return [f for prev, f in itertools.pairwise(frames) if phases[prev] == "spin" and phases[f] == "after"]


@torch.no_grad()
def render_items(module, ds, indices) -> tuple[torch.Tensor, torch.Tensor]:
    preds, gts = [], []
    for i in indices:
        batch = module.device_batch(default_collate([ds[i]]))
        rgb, _, _, _ = module.avatar.render_batch(batch)
        preds.append(rgb[0].clamp(0, 1))
        gts.append(batch["image"][0])
    return torch.stack(preds), torch.stack(gts)


def per_frame_sequence(module, dm, split: str, view: int | None):
    """Per-frame PSNR of one camera over a split's frames, plus the rendered and true frames."""
    ds = dm.datasets[split]
    views = sorted({r.view for r in ds.records})
    view = views[0] if view is None or view not in views else view
    idx = sorted((r.frame, i) for i, r in enumerate(ds.records) if r.view == view)
    pred, gt = render_items(module, ds, [i for _, i in idx])
    vals = [float(psnr(p, g)) for p, g in zip(pred, gt)]
    return [f for f, _ in idx], vals, pred, gt, view


@torch.no_grad()
def extreme_poses(module, dm, n: int = 48, seed: int = 0, show: int = 6) -> dict:
    """Joint-limit poses and very fast spins: finite output, Gaussian scale/opacity/offset statistics, and renders
    of the first `show` joint-limit poses (`_renders`, uint8 [show,H,W,3]; not written to the JSON)."""
    g = torch.Generator().manual_seed(seed)
    T = dm.window_len
    _, poses, transl = dm.pose_sequence("train")
    base, base_t = poses[0], transl[0]
    windows, trans, renders = [], [], []
    for k in range(n):
        if k % 2 == 0:  # joint limits: every body joint rotated up to 1.6 rad, held over the window
            p = base.clone()
            p[1:] = (torch.rand(23, 3, generator=g) * 2 - 1) * 1.6
            w = p.expand(T, 24, 3).clone()
        else:  # a spin far faster than in training: 1-3 turns per window
            from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

            speed = (1 + 2 * torch.rand(1, generator=g).item()) * 2 * math.pi / max(T - 1, 1)
            yaws = torch.arange(T, dtype=torch.float32) * speed
            Ry = axis_angle_to_matrix(torch.stack([torch.zeros(T), yaws, torch.zeros(T)], -1))
            w = base.expand(T, 24, 3).clone()
            w[:, 0] = matrix_to_axis_angle(Ry @ axis_angle_to_matrix(base[0]))
        windows.append(w)
        trans.append(base_t.expand(T, 3))
    poses_w, transl_w = torch.stack(windows), torch.stack(trans)
    # A garment with state (sheet=physics) is simulated into each pose: RAMP frames from the first training pose,
    # then the window; a blow-up or cloth inside the body is counted, never rendered silently.
    motions = [ramp_into(base, base_t, w, t) for w, t in zip(poses_w, transl_w)]
    blowups, inside, parts = [], [], []
    for k, (w, t, table) in enumerate(zip(poses_w, transl_w, motions)):
        try:
            record = module.avatar.drive(table)
        except RuntimeError as e:
            blowups.append({"pose": k, "error": str(e).splitlines()[0][:200]})
            continue
        inside += [k] if record["inside"] else []
        parts.append(module.avatar.posed(w, t, frame=int(table.frames[-1])))
        if k < 2 * show and k % 2 == 0:
            renders.append(render_poses(module, dm, w[None], t[None], frame=int(table.frames[-1]))[0])
    module.avatar.drive(dm.scene.poses)  # the dataset's motion again, for what follows
    posed = {key: torch.cat([p[key] for p in parts]) for key in ("means", "scales")}
    posed["opacities"] = parts[0]["opacities"]
    keep = [k for k in range(n) if k not in {b["pose"] for b in blowups}]
    joints = module.avatar.body.joints(poses_w[keep, -1], transl_w[keep, -1])  # [n,24,3]
    dist = torch.cdist(posed["means"], joints).min(-1).values  # [n,N] distance to the nearest joint
    finite = bool(torch.isfinite(posed["means"]).all() and torch.isfinite(posed["scales"]).all())
    canonical_scale = float(module.avatar.canonical_gaussians()["scales"].max())  # free Gaussians and a sheet's
    trained_scale = training_scale_max(module, dm)
    renders = np.stack(renders)
    return {
        "poses": n,
        "finite": finite,
        "max_scale_m": float(posed["scales"].max()),
        "max_canonical_scale_m": canonical_scale,
        "scale_growth": float(posed["scales"].max() / max(canonical_scale, 1e-12)),
        "max_training_scale_m": trained_scale,
        "scale_growth_vs_training": float(posed["scales"].max() / max(trained_scale, 1e-12)),
        "opacity_mean": float(posed["opacities"].mean()),
        "opacity_p99": float(posed["opacities"].quantile(0.99)),
        "max_dist_to_joint_m": float(dist.max()),
        "frac_gaussians_over_0.6m_from_joints": float((dist > 0.6).float().mean()),
        "garment_blowups": blowups,
        "garment_inside_body": inside,
        "_renders": renders,
    }


RAMP = 10  # frames from the first training pose into an extreme pose's window (a garment with state)


def ramp_into(base: torch.Tensor, base_t: torch.Tensor, window: torch.Tensor, transl: torch.Tensor):
    """A motion into a pose window [T,24,3] / [T,3]: RAMP frames from the pose `base` [24,3] / `base_t` [3]
    (axis-angles blended linearly), then the window's entries; a PoseTable of frames 0..RAMP+T-1."""
    from realityavatar.data.poses import PoseTable

    a = torch.linspace(0, 1, RAMP + 1)[:-1, None, None]
    poses = torch.cat([(1 - a) * base + a * window[0], window])
    trans = torch.cat([(1 - a[:, 0]) * base_t + a[:, 0] * transl[0], transl])
    return PoseTable.from_sequence(poses, trans)


@torch.no_grad()
def render_poses(module, dm, poses_w: torch.Tensor, transl_w: torch.Tensor, frame: int = -1) -> np.ndarray:
    """Pose windows [K,T,24,3] / [K,T,3] rendered from the first held-out camera (else a training one), with the
    mean appearance latent (frame_idx -1, as a novel pose): uint8 [K,H,W,3]. frame: the windows' last frame in the
    motion a garment with state was driven on."""
    ds = dm.datasets["novel_view" if "novel_view" in dm.datasets else "train"]
    batch = default_collate([ds[0]])
    out = []
    for w, t in zip(poses_w, transl_w):
        b = {**batch, **module.avatar.pose_inputs(w[None], t[None]), "frame_idx": torch.full_like(batch["frame_idx"], -1),
             "frame": torch.full_like(batch["frame"], frame)}
        rgb = module.avatar.render_batch(b)[0][0].clamp(0, 1)
        out.append((rgb.numpy() * 255).round().astype(np.uint8))
    return np.stack(out)


@torch.no_grad()
def training_scales(module, dm, batch: int = 16) -> dict[int, float]:
    """The largest posed Gaussian scale of every training frame (its own pose window): what the model itself does
    with the poses it was trained on (a garment sheet stretches its cells at peak flare), the reference for the
    extreme poses."""
    ds = dm.datasets["train"]
    first: dict[int, int] = {}
    for i, rec in enumerate(ds.records):
        first.setdefault(int(rec.frame), i)
    frames, out = list(first), {}
    for k in range(0, len(frames), batch):
        b = default_collate([ds[first[f]] for f in frames[k:k + batch]])
        s = module.avatar.deform(b)["scales"].flatten(1).max(1).values
        out.update({f: float(v) for f, v in zip(frames[k:k + batch], s)})
    return out


def training_scale_max(module, dm) -> float:
    return max(training_scales(module, dm).values())


@torch.no_grad()
def pose_noise(module, dm, view: int | None, sigmas=NOISE_SIGMAS, seed: int = 0) -> dict:
    """Novel-pose PSNR of one camera when Gaussian noise (rad) is added to every joint of the pose windows."""
    split = "novel_pose" if "novel_pose" in dm.datasets else "novel_view"
    ds = dm.datasets[split]
    views = sorted({r.view for r in ds.records})
    view = views[0] if view is None or view not in views else view
    idx = [i for i, r in enumerate(ds.records) if r.view == view]
    out = {}
    for sigma in sigmas:
        g = torch.Generator().manual_seed(seed)
        vals = []
        for i in idx:
            batch = module.device_batch(default_collate([ds[i]]))
            noisy = batch["poses"] + sigma * torch.randn(batch["poses"].shape, generator=g).to(batch["poses"])
            batch.update(module.avatar.pose_inputs(noisy, batch["transl"]))  # what the model reads of the poses
            rgb, _, _, _ = module.avatar.render_batch(batch)
            vals.append(float(psnr(rgb[0].clamp(0, 1), batch["image"][0])))
        out[f"{sigma:g}"] = float(np.mean(vals))
    return {"split": split, "view": view, "psnr_by_sigma": out}


def analyse_run(run: Path, view: int | None, window: int) -> dict:
    from realityavatar.build import build_data, load_run

    cfg, module, _ = load_run(run)
    torch.manual_seed(0)
    dm = build_data(cfg, module.avatar.body)
    metrics = json.loads((run / "metrics.json").read_text())
    frames, vals, pred, gt, used_view = per_frame_sequence(module, dm, "novel_view" if "novel_view" in dm.datasets else "train", view)
    stops = [s for s in stop_frames(dm) if frames[0] <= s <= frames[-1]]
    around = {}
    for s in stops:
        sel = [i for i, f in enumerate(frames) if s - window <= f <= s + window]
        if len(sel) >= 2:
            around[str(s)] = {
                "psnr": float(np.mean([vals[i] for i in sel])),
                "flicker": float(temporal_flicker(pred[sel], gt[sel])),
            }
    return {
        "run": str(run),
        "label": label_of(metrics),
        "seed": metrics.get("seed"),
        "novel_view_psnr": metrics.get("test/novel_view/psnr"),
        "novel_pose_psnr": metrics.get("test/novel_pose/psnr"),
        "view": used_view,
        "frames": frames,
        "psnr_per_frame": vals,
        "flicker_all": float(temporal_flicker(pred, gt)),
        "stops": stops,
        "around_stops": around,
        "extreme": extreme_poses(module, dm),
        "noise": pose_noise(module, dm, view),
    }


def _mean_std(xs):
    """Mean and sample std (ddof=1, as collect.py) of the values that exist."""
    xs = [x for x in xs if x is not None]
    if not xs:
        return float("nan"), float("nan")
    return float(np.mean(xs)), float(np.std(xs, ddof=1)) if len(xs) > 1 else 0.0


def write_report(results: list[dict], out: Path, command: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    renders = [r["extreme"].pop("_renders", None) for r in results]
    (out / "stability.json").write_text(json.dumps(results, indent=1))
    shown = [(r, im) for r, im in zip(results, renders) if im is not None and len(im)]
    if shown:  # the first joint-limit poses of every run: where a model breaks, it shows here
        k = max(len(im) for _, im in shown)
        fig, axes = plt.subplots(len(shown), k, figsize=(2 * k, 2.1 * len(shown)), squeeze=False)
        for row, (r, im) in enumerate(shown):
            for c in range(k):
                ax = axes[row, c]
                ax.axis("off")
                if c < len(im):
                    ax.imshow(im[c])
            axes[row, 0].set_title(f"{r['label']} seed {r['seed']}", fontsize=8, loc="left")
        fig.tight_layout()
        fig.savefig(out / "extreme_poses.png", dpi=90)
        plt.close(fig)
    by = defaultdict(list)
    for r in results:
        by[r["label"]].append(r)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for label, rs in by.items():
        L = min(len(r["psnr_per_frame"]) for r in rs)
        curve = np.mean([r["psnr_per_frame"][:L] for r in rs], 0)
        axes[0].plot(rs[0]["frames"][:L], curve, label=label)
        sig = list(rs[0]["noise"]["psnr_by_sigma"])
        axes[1].plot([float(s) for s in sig], [np.mean([r["noise"]["psnr_by_sigma"][s] for r in rs]) for s in sig], "o-", label=label)
    for s in results[0]["stops"]:
        axes[0].axvline(s, color="k", ls="--", lw=0.8)
    axes[0].set(xlabel="frame (held-out camera)", ylabel="PSNR (dB)", title="Per-frame PSNR; dashed = abrupt stop")
    axes[1].set(xlabel="pose noise sigma (rad)", ylabel="novel-pose PSNR (dB)", title="Robustness to pose-fit noise")
    for a in axes:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "stability.png", dpi=110)
    plt.close(fig)

    commits = ", ".join(sorted({json.loads(Path(r["run"], "metrics.json").read_text()).get("commit", "?") for r in results}))
    L = ["# Stability report", "", f"Generated by `{command}` from {len(results)} runs (commits: {commits}).", "",
         "![stability](stability.png)", "",
         "Renders of the first joint-limit poses: [extreme_poses.png](extreme_poses.png).", "",
         "## Abrupt stops (held-out camera, frames within the window around each stop)", "",
         "| variant | seeds | PSNR all frames | PSNR around stops | flicker around stops | flicker all frames |",
         "|---|---|---|---|---|---|"]
    for label, rs in by.items():
        a = _mean_std([np.mean(r["psnr_per_frame"]) for r in rs])
        b = _mean_std([np.mean([v["psnr"] for v in r["around_stops"].values()]) if r["around_stops"] else None for r in rs])
        c = _mean_std([np.mean([v["flicker"] for v in r["around_stops"].values()]) if r["around_stops"] else None for r in rs])
        d = _mean_std([r["flicker_all"] for r in rs])
        L.append(f"| {label} | {len(rs)} | {a[0]:.2f} ± {a[1]:.2f} | {b[0]:.2f} ± {b[1]:.2f} | {c[0]:.4f} ± {c[1]:.4f} | {d[0]:.4f} ± {d[1]:.4f} |")
    L += ["", "Flicker = mean |(pred_t − pred_{t−1}) − (gt_t − gt_{t−1})| over consecutive frames (lower is better).", "",
          "## Extreme unseen poses (joint limits ±1.6 rad, spins of 1–3 turns per window)", "",
          ("A garment with state (sheet=physics) is simulated into each pose: its blow-ups (the pose is left out of "
           "the other columns) and the poses with cloth inside the body are counted."), "",
          "| variant | all finite | max scale (m) | scale growth vs canonical | max scale over the training frames (m) | growth vs training | opacity mean / p99 | max dist to a joint (m) | share > 0.6 m from joints | garment: blow-ups / inside the body |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for label, rs in by.items():
        e = [r["extreme"] for r in rs]
        L.append(f"| {label} | {all(x['finite'] for x in e)} | {max(x['max_scale_m'] for x in e):.4f} | "
                 f"{max(x['scale_growth'] for x in e):.2f} | {max(x.get('max_training_scale_m', float('nan')) for x in e):.4f} | "
                 f"{max(x.get('scale_growth_vs_training', float('nan')) for x in e):.2f} | {np.mean([x['opacity_mean'] for x in e]):.3f} / "
                 f"{np.mean([x['opacity_p99'] for x in e]):.3f} | {max(x['max_dist_to_joint_m'] for x in e):.3f} | "
                 f"{np.mean([x['frac_gaussians_over_0.6m_from_joints'] for x in e]):.4f} | "
                 f"{sum(len(x['garment_blowups']) for x in e)} / {sum(len(x['garment_inside_body']) for x in e)}"
                 f" of {sum(x['poses'] for x in e)} |")
    # No long-rollout row: the temporal state is rebuilt from a fixed pose window every frame, so "cycle 1 vs cycle
    # 10" compares a pure function with itself and cannot fail; the extreme-pose table is the check that can.
    L += ["",
          "## Pose-fit noise (novel-pose PSNR, one camera)", "", "| variant | " + " | ".join(f"σ={s}" for s in results[0]["noise"]["psnr_by_sigma"]) + " |",
          "|---|" + "---|" * len(results[0]["noise"]["psnr_by_sigma"])]
    for label, rs in by.items():
        sig = list(rs[0]["noise"]["psnr_by_sigma"])
        L.append(f"| {label} | " + " | ".join(f"{np.mean([r['noise']['psnr_by_sigma'][s] for r in rs]):.2f}" for s in sig) + " |")
    L += ["", "## Seed spread (test metrics from metrics.json; ± = sample std over seeds)", "", "| variant | seeds | novel view PSNR | novel pose PSNR |", "|---|---|---|---|"]
    for label, rs in by.items():
        a, b = _mean_std([r["novel_view_psnr"] for r in rs]), _mean_std([r["novel_pose_psnr"] for r in rs])
        L.append(f"| {label} | {len(rs)} | {a[0]:.2f} ± {a[1]:.2f} | {b[0]:.2f} ± {b[1]:.2f} |")
    (out / "stability.md").write_text("\n".join(L) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m realityavatar.analysis.stability",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="run folders or sweep folders holding them")
    ap.add_argument("--out", default="ablations/results/stability")
    ap.add_argument("--view", type=int, default=None, help="held-out camera id (default: the first)")
    ap.add_argument("--window", type=int, default=5, help="frames either side of a stop")
    add_threads_option(ap)
    args = ap.parse_args(argv)
    set_threads(args.threads, "--threads")
    torch.set_grad_enabled(False)
    results = [analyse_run(r, args.view, args.window) for r in find_runs(args.paths)]
    cmd = "python -m realityavatar.analysis.stability " + " ".join(sys.argv[1:] if argv is None else argv)
    write_report(results, Path(args.out), cmd)
    print((Path(args.out) / "stability.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
