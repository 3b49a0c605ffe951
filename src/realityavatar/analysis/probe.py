"""Geometry probe of trained runs: per-frame silhouette IoU, PSNR and motion-trend offset sizes around a spin and its stop.

Usage: python -m realityavatar.analysis.probe <run_dir> [...] --out <folder> [--labels a,b,...]
For every training frame it renders the training cameras and the held-out (novel-view) cameras, and measures the
decoder's offsets |Δx| (median, 99th percentile, max over Gaussians). Frames are grouped into phases from the scene's
motion events: rest (before the spin), spin, after (the second after the stop), settled (later); "stop" is the first
0.3 s of "after" again, on its own. Writes probe.csv (per frame and camera kind), probe.json (phase means per run) and
probe.png (per-frame curves; its last panel is the ground-truth garment's hem radius and height from the scene's
<scene>-garment.npz, so the model's offsets can be read against how far and how long the simulated skirt moves).

Held-out sequence: the novel-pose split's own spin and abrupt stop, its phases (np_rest / np_spin / np_after) read from
the root's turning in its mesh_infos.pkl, its PSNR / IoU from the run's per_frame.csv (all cameras), in probe.json.

Cloth tracking (synthetic scenes, from <scene>-garment.npz): the Gaussians within 2 cm of the simulated cloth in every
rest frame are the garment's. Per frame, `cloth_p50` is their median distance to that frame's cloth and `drift_p50` /
`drift_p90` how far their material position (the closest cloth point, carried back to the first frame's cloth by its
triangle and barycentrics) has moved from its mean over the rest frames, in metres. A Gaussian that follows the cloth
keeps its material position; one that slides over the cloth mixes the colours of the texture it crosses.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run, run_device
from realityavatar.data.i3d import read_mesh_infos, split_folder
from realityavatar.data.poses import PHASES
from realityavatar.evaluate import undersampled
from realityavatar.metrics import psnr, silhouette_iou
from realityavatar.runtime import add_threads_option, set_threads

CLOTH_NEAR = 0.02  # a garment Gaussian: within 2 cm of the cloth in every rest frame
CLOTH_SAMPLES = 40000  # material points sampled on the cloth (about 5 mm apart on the demo skirt)
STOP_SECONDS = 0.3  # the "stop" summary: the first 0.3 s after the abrupt stop


def phase_of(frame: int, events: dict, fps: float) -> str:
    start, stop = events.get("spin_start_frame"), events.get("spin_stop_frame")
    if start is None or stop is None:
        return "all"
    if frame < start:
        return "rest"
    if frame < stop:
        return "spin"
    return "after" if frame < stop + round(fps) else "settled"


def garment_curves(npz: Path, settled_frame: int | None = None) -> dict[int, tuple[float, float, float]] | None:
    """Per frame of a synthetic scene's garment: (hem radius, hem depth below the waist, shape change) in metres. The
    waist ring is the 10% highest vertices of the first frame, the hem the 10% lowest; the radius is the hem's mean
    horizontal distance (world y up) from the waist ring's centre, which a spin does not change but a flare does.
    The shape change is the median distance of the cloth's vertices from where they are in `settled_frame` (default:
    the last frame), with both frames rigidly aligned on the waist ring, which the pelvis carries: in a sequence
    whose body pose does not change (a spin and its stop) it is the part of the garment's shape that only the
    motion's history explains."""
    if not npz.is_file():
        return None
    g = np.load(npz)
    V, frames = g["vertices"].astype(np.float64), [int(f) for f in g["frames"]]  # [F,Vg,3], [F]
    order = np.argsort(V[0, :, 1])
    k = max(1, len(order) // 10)
    hem, waist = order[:k], order[-k:]
    ref = V[frames.index(settled_frame) if settled_frame in frames else -1]
    ref_c = ref - ref[waist].mean(0)
    out = {}
    for f, v in zip(frames, V):
        c = v[waist].mean(0)
        # Kabsch: the rotation taking this frame's waist ring onto the settled frame's
        u, _, wt = np.linalg.svd((v[waist] - c).T @ ref_c[waist])
        d = np.sign(np.linalg.det(u @ wt))
        rot = u @ np.diag([1.0, 1.0, d]) @ wt  # row vectors: x_aligned = (x - c) @ rot
        change = float(np.median(np.linalg.norm((v - c) @ rot - ref_c, axis=1)))
        out[f] = (float(np.linalg.norm((v[hem] - c)[:, [0, 2]], axis=1).mean()), float(c[1] - v[hem, 1].mean()), change)
    return out


def settled_frame(meta: dict) -> int | None:
    """The reference of the garment's shape change: a synthetic scene's last training frame (from its meta)."""
    n_train = meta.get("params", {}).get("train_frames")
    return int(n_train) - 1 if n_train else None


class ClothTracker:
    """Material positions of posed Gaussians on a simulated garment (vertices [F,V,3] per frame, faces [Fc,3])."""

    def __init__(self, npz: Path, seed: int = 0):
        g = np.load(npz)
        self.V, self.F, self.frames = g["vertices"], g["faces"], [int(f) for f in g["frames"]]
        rng = np.random.default_rng(seed)
        self.tri = rng.integers(0, len(self.F), CLOTH_SAMPLES)
        r = rng.random((CLOTH_SAMPLES, 2))
        r = np.where(r.sum(1, keepdims=True) > 1, 1 - r, r)  # uniform on each triangle
        self.bary = np.stack([1 - r.sum(1), r[:, 0], r[:, 1]], 1)
        self.material = self._points(0)  # the sample's position on the first frame's cloth

    def _points(self, k: int) -> np.ndarray:
        return np.einsum("pk,pkc->pc", self.bary, self.V[k][self.F[self.tri]])

    def locate(self, frame: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x [N,3] posed means -> (distance to the frame's cloth [N], material position [N,3])."""
        from scipy.spatial import cKDTree

        d, j = cKDTree(self._points(self.frames.index(frame))).query(x.astype(np.float64))
        return d, self.material[j]


def cloth_tracking(per_frame: dict[int, tuple[np.ndarray, np.ndarray]], phase: dict[int, str]) -> dict[int, tuple]:
    """{frame: (distance [N], material [N,3])} -> {frame: (cloth_p50, drift_p50, drift_p90)} over the garment's
    Gaussians (reference: the rest frames, or the first frame where a sequence has none)."""
    frames = sorted(per_frame)
    ref = [f for f in frames if phase[f] == "rest"] or frames[:1]
    on = np.all([per_frame[f][0] < CLOTH_NEAR for f in ref], 0)
    if not on.any():
        return {}
    home = np.mean([per_frame[f][1][on] for f in ref], 0)
    out = {}
    for f in frames:
        d, m = per_frame[f]
        drift = np.linalg.norm(m[on] - home, axis=1)
        out[f] = (float(np.median(d[on])), float(np.median(drift)), float(np.percentile(drift, 90)))
    return out


@torch.no_grad()
def probe_run(run_dir: Path, threads: int = 1, kinds: tuple[str, ...] = ("train", "heldout"),
              overrides: list[str] | None = None) -> tuple[list[dict], dict]:
    """overrides: key=value settings for the run (as realityavatar-evaluate takes them), e.g. another scene of the same
    sequence at another resolution with eval.supersample; its novel-pose phases then come from the per_frame.csv of
    `realityavatar-evaluate run_dir=<run> <the same overrides>` (<run>/eval/)."""
    set_threads(threads, "--threads")
    cfg, module, info = load_run(run_dir, overrides)
    dm = build_data(cfg, module.avatar.body)
    module.to(run_device(cfg))  # a GPU run renders with its own backend (gsplat needs CUDA tensors)
    meta = dm.scene.meta or {}
    events = meta.get("motion", {}).get("events", {})
    fps = float(meta.get("fps", meta.get("preset", {}).get("fps", 25.0)))
    rows: list[dict] = []
    offsets: dict[int, tuple[float, float, float]] = {}
    npz = Path(str(cfg.data.root)) / f"{cfg.data.sequence}-garment.npz"
    tracker = ClothTracker(npz) if npz.is_file() else None
    located: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for kind, split in (("train", "train"), ("heldout", "novel_view")):
        ds = dm.datasets.get(split)
        if ds is None or kind not in kinds:
            continue
        for i, rec in enumerate(ds.records):
            batch = module.device_batch(default_collate([ds[i]]))
            if not rows and (note := undersampled(info, module.eval_supersample, int(batch["width"][0]))):
                print(f"probe: {run_dir}: {note}", file=sys.stderr)
            rgb, alpha, _, posed = module.avatar.render_batch(batch, supersample=module.eval_supersample)
            if rec.frame not in offsets:
                n = module.avatar.gaussians.num_points  # the free Gaussians (a garment sheet's follow after them)
                dx = (posed["x_e"][0][:n] - module.avatar.gaussians.means).norm(dim=-1)
                q = torch.quantile(dx, torch.tensor([0.5, 0.99], dtype=dx.dtype, device=dx.device))
                offsets[rec.frame] = (float(q[0]), float(q[1]), float(dx.max()))
                if tracker is not None and int(rec.frame) in tracker.frames:
                    located[int(rec.frame)] = tracker.locate(int(rec.frame), posed["means"][0].cpu().numpy())
            rows.append({
                "frame": int(rec.frame), "view": int(rec.view), "kind": kind,
                "phase": phase_of(int(rec.frame), events, fps),
                "iou": float(silhouette_iou(alpha[0], batch["mask"][0])),
                "psnr": float(psnr(rgb[0].clamp(0, 1), batch["image"][0])),
            })
    for r in rows:
        r["dx_p50"], r["dx_p99"], r["dx_max"] = offsets[r["frame"]]
    tracking = cloth_tracking(located, {f: phase_of(f, events, fps) for f in located}) if located else {}
    for r in rows:
        if r["frame"] in tracking:
            r["cloth_p50"], r["drift_p50"], r["drift_p90"] = tracking[r["frame"]]
    garment = garment_curves(npz, settled_frame(meta))
    if garment:
        for r in rows:
            r["hem_radius"], r["hem_depth"], r["shape_change"] = garment.get(r["frame"], (float("nan"),) * 3)
    stop = events.get("spin_stop_frame")
    summary: dict = {"events": events, "fps": fps}
    for kind in ("train", "heldout"):
        for ph in PHASES + ("all", "stop"):
            if ph == "stop":
                sel = [r for r in rows if r["kind"] == kind and stop is not None
                       and stop <= r["frame"] < stop + round(STOP_SECONDS * fps)]
            else:
                sel = [r for r in rows if r["kind"] == kind and (ph == "all" or r["phase"] == ph)]
            if sel:
                summary[f"{kind}/{ph}/iou"] = float(np.mean([r["iou"] for r in sel]))
                summary[f"{kind}/{ph}/psnr"] = float(np.mean([r["psnr"] for r in sel]))
                summary[f"{kind}/{ph}/dx_p99"] = float(np.mean([r["dx_p99"] for r in sel]))
                for m in ("cloth_p50", "drift_p50", "drift_p90", "shape_change"):
                    if all(m in r for r in sel):
                        summary[f"{kind}/{ph}/{m}"] = float(np.mean([r[m] for r in sel]))
    novel_pose = split_folder(Path(str(cfg.data.root)), cfg.data.sequence, "novel_pose")
    summary.update(novel_pose_phases(run_dir / "eval" if overrides else run_dir, novel_pose, fps))
    return rows, summary


def heading_stops(split_dir: Path, fps: float, still_deg: float = 0.5) -> dict[int, str]:
    """Phases of a held-out (novel-pose) sequence from its global orientations (the split's mesh_infos.pkl, read by
    the I3D reader), PoseTable.motion_phases at `still_deg` degrees a frame: "np_rest" before the body first turns
    (every frame when it never does), "np_spin" while it turns faster, "np_after" from the first still frame after
    the turning on (motion_phases' after and settled)."""
    table = read_mesh_infos(split_dir, torch.zeros(3))  # the pelvis only moves the translation: the turning is the same
    phases = table.motion_phases(table.frames, fps, still_deg_s=still_deg * fps)
    return {f: "np_" + {"settled": "after", "all": "rest"}.get(p, p) for f, p in phases.items()}


def novel_pose_phases(folder: Path, mesh_dir: Path, fps: float) -> dict:
    """Novel-pose PSNR / IoU per phase of the held-out sequence (its own spin and abrupt stop; `fps` its frame rate),
    from the per_frame.csv in `folder` (a run's or its eval/: every camera of the novel-pose split); {} when either
    file is missing."""
    table, infos = folder / "per_frame.csv", mesh_dir / "mesh_infos.pkl"
    if not table.is_file() or not infos.is_file():
        return {}
    phases = heading_stops(mesh_dir, fps)
    with open(table) as f:
        rows = [r for r in csv.DictReader(f) if r["split"] == "novel_pose" and int(r["frame"]) in phases]
    out = {}
    for ph in ("np_rest", "np_spin", "np_after"):
        sel = [r for r in rows if phases[int(r["frame"])] == ph]
        if sel:
            out[f"novel_pose/{ph}/psnr"] = float(np.mean([float(r["psnr"]) for r in sel]))
            out[f"novel_pose/{ph}/iou"] = float(np.mean([float(r["iou"]) for r in sel]))
            out[f"novel_pose/{ph}/images"] = len(sel)
    return out


def plot(results: dict[str, list[dict]], events: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with_garment = any("hem_radius" in r for rows in results.values() for r in rows)
    fig, axes = plt.subplots(4 if with_garment else 3, 1, figsize=(9, 10.5 if with_garment else 8), sharex=True)
    if with_garment:
        rows = next(iter(results.values()))
        gt = sorted({(r["frame"], r["hem_radius"], r["hem_depth"], r["shape_change"]) for r in rows
                     if "hem_radius" in r})
        axes[3].plot([g[0] for g in gt], [100 * g[1] for g in gt], "k-", label="hem radius")
        axes[3].plot([g[0] for g in gt], [100 * g[2] for g in gt], "k--", label="hem depth below waist")
        axes[3].plot([g[0] for g in gt], [100 * g[3] for g in gt], "k:", label="shape change from the settled cloth")
        axes[3].legend(fontsize=8)
    for label, rows in results.items():
        held = [r for r in rows if r["kind"] == "heldout"]
        frames = sorted({r["frame"] for r in held})
        by = {f: [r for r in held if r["frame"] == f] for f in frames}
        axes[0].plot(frames, [np.mean([r["iou"] for r in by[f]]) for f in frames], label=label)
        axes[1].plot(frames, [np.mean([r["psnr"] for r in by[f]]) for f in frames], label=label)
        axes[2].plot(frames, [100 * by[f][0]["dx_p99"] for f in frames], label=label)
    for ax, name in zip(axes, ("held-out IoU", "held-out PSNR (dB)", "p99 |Δx| (cm)", "ground-truth garment (cm)")):
        ax.set_ylabel(name)
        for k in ("spin_start_frame", "spin_stop_frame"):
            if k in events:
                ax.axvline(events[k], color="grey", ls="--", lw=0.8)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("frame (dashed: spin start, abrupt stop)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def scene_report(prefix: Path) -> int:
    """Print a synthetic scene's garment shape change (cm) from its settled cloth, per 0.1 s around the stop."""
    meta_path, npz = Path(f"{prefix}-meta.json"), Path(f"{prefix}-garment.npz")
    for path in (meta_path, npz):
        if not path.is_file():
            print(f"probe --scene: {path} not found (build the scene with realityavatar-make-scene)", file=sys.stderr)
            return 2
    meta = json.loads(meta_path.read_text())
    events, fps = meta.get("motion", {}).get("events", {}), float(meta["fps"])
    n_train = int(meta["params"]["train_frames"])
    curves = garment_curves(npz, settled_frame(meta))
    print(f"{prefix.name}: shape change = median cloth-vertex distance from frame {n_train - 1} (settled), waist-aligned")
    phases: dict[str, list[float]] = {}
    for f in range(n_train):
        phases.setdefault(phase_of(f, events, fps), []).append(curves[f][2])
    stop = events.get("spin_stop_frame")
    if stop is not None:
        phases["stop"] = [curves[f][2] for f in range(stop, min(n_train, stop + round(STOP_SECONDS * fps)))]
    print("  per phase (cm): " + ", ".join(f"{k} {100 * np.mean(v):.1f}" for k, v in phases.items()))
    if stop is not None:
        step = max(1, round(0.1 * fps))
        print(f"  {'s after stop':>12} {'shape change cm':>16} {'hem radius cm':>14}")
        for f in range(stop - 3 * step, min(n_train, stop + round(1.6 * fps)), step):
            print(f"  {(f - stop) / fps:>+12.2f} {100 * curves[f][2]:>16.1f} {100 * curves[f][0]:>14.1f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m realityavatar.analysis.probe",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*")
    ap.add_argument("--out", default=None)
    ap.add_argument("--scene", default=None, metavar="ROOT/NAME",
                    help="no runs: print how long a synthetic scene's garment keeps the spin's history (its shape "
                         "change from the settled cloth around the abrupt stop)")
    ap.add_argument("--labels", default=None, help="comma-separated labels, one per run (default: folder names)")
    add_threads_option(ap)
    ap.add_argument("--heldout-only", action="store_true", help="skip the training cameras (3x faster)")
    ap.add_argument("--override", nargs="+", default=[], metavar="KEY=VALUE",
                    help="settings for every run, as realityavatar-evaluate takes them: e.g. a 512 px run probed on "
                         "the 128 px scene (docs/gpu.md); novel-pose phases then from <run>/eval/per_frame.csv")
    a = ap.parse_args(argv)
    if a.scene:
        return scene_report(Path(a.scene))
    if not a.runs or not a.out:
        print("probe: give run folders and --out, or --scene ROOT/NAME", file=sys.stderr)
        return 2
    runs = [Path(r) for r in a.runs]
    labels = a.labels.split(",") if a.labels else [r.name for r in runs]
    if len(labels) != len(runs):
        print(f"--labels: {len(labels)} labels for {len(runs)} runs", file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results, summaries, events = {}, {}, {}
    for label, run in zip(labels, runs):
        rows, summary = probe_run(run, a.threads, ("heldout",) if a.heldout_only else ("train", "heldout"), a.override)
        results[label], summaries[label] = rows, summary
        events = summary["events"]
    with open(out / "probe.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["run", *results[labels[0]][0].keys()])
        w.writeheader()
        for label, rows in results.items():
            for r in rows:
                w.writerow({"run": label, **r})
    (out / "probe.json").write_text(json.dumps({"runs": {lb: str(r) for lb, r in zip(labels, runs)}, **summaries},
                                               indent=2))
    plot(results, events, out / "probe.png")
    hdr = f"{'run':<22}" + "".join(f"{k:>14}" for k in ("IoU rest", "IoU spin", "IoU after", "PSNR rest",
                                                           "PSNR spin", "PSNR after", "PSNR stop", "p99dx rest",
                                                           "p99dx spin", "drift spin", "drift settl"))
    print("held-out cameras, training frames")
    print(hdr)
    for label, s in summaries.items():
        vals = [s.get(f"heldout/{p}/iou") for p in ("rest", "spin", "after")]
        vals += [s.get(f"heldout/{p}/psnr") for p in ("rest", "spin", "after", "stop")]
        vals += [100 * s[f"heldout/{p}/dx_p99"] if f"heldout/{p}/dx_p99" in s else None for p in ("rest", "spin")]
        vals += [100 * s[f"heldout/{p}/drift_p50"] if f"heldout/{p}/drift_p50" in s else None for p in ("spin", "settled")]
        print(f"{label:<22}" + "".join(f"{v:14.3f}" if v is not None else f"{'-':>14}" for v in vals))
    groups: dict[str, list[dict]] = {}
    for label, sm in summaries.items():  # labels "<name>@<seed>" are averaged per name
        groups.setdefault(label.split("@")[0], []).append(sm)
    if any(len(v) > 1 for v in groups.values()):
        keys = [f"heldout/{p}/{m}" for m in ("psnr", "iou") for p in ("rest", "spin", "after", "stop", "settled")]
        keys += [f"heldout/{p}/drift_p50" for p in ("spin", "after", "settled")]
        keys += [f"heldout/{p}/shape_change" for p in ("spin", "stop", "after")]
        keys += [f"novel_pose/{p}/psnr" for p in ("np_rest", "np_spin", "np_after")]
        lines = ["| run | n | " + " | ".join(k.replace("heldout/", "").replace("/", " ") for k in keys) + " |",
                 "|---|---:|" + "---:|" * len(keys)]
        for name, sms in groups.items():
            cells = []
            for k in keys:
                v = np.array([sm[k] for sm in sms if k in sm])
                cells.append(f"{v.mean():.3f} ± {v.std(ddof=1):.3f}" if len(v) > 1 else (f"{v.mean():.3f}" if len(v) else "-"))
            lines.append(f"| {name} | {len(sms)} | " + " | ".join(cells) + " |")
        (out / "probe_groups.md").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
    print(f"wrote {out}/probe.csv, probe.json, probe.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
