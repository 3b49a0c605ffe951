"""How learnable is a scene's garment motion from the pose window? The simulated cloth regressed on the model's conditioning.

Usage: python ablations/garment_regress.py [--data synthetic_sweep] [--temporal lstm,none] [--dynamics none,deltas]
       [--steps 1000] [--batch 1] [--lr 1e-3] [--basis 64] [--seeds 0] [--out <dir>] [config overrides ...]

Issue 9's spin target needs the garment's shape (README, "What the spin's gap is made of"). Before asking whether four
views teach it, this asks whether the model's deformation path can learn it at all when told the answer in 3D. No
images and no trained model: for every training frame of a synthetic scene (one window per frame, as the data config
builds it) the target is the simulated cloth in the current frame's pelvis frame (every garment vertex through the
inverse of the pelvis's bone transform), minus the first training frame's. It is what a garment skinned to the
pelvis would need as canonical offsets; the regressor is the model's own encoder and temporal module (as composed
from the config, `temporal=` and `encoder.dynamics=` set per run) followed by a motion basis as `sheet.basis`: a
linear map of h_t to `--basis` coefficients of per-vertex shapes (zero at the start). Trained with Adam on the 3D
error alone, frames drawn uniformly, `--batch` frames per step, the rate decaying to 0.1x as the project's optimizer
does.

Printed per phase (RMS over vertices and frames, cm):
- `floor`: what no function of the pose window can beat. Training frames whose windows are identical (a body
  standing still before the spin and again after the garment settled) but whose cloth differs are fitted at best by
  their mean; the floor is each frame's distance to the mean of its identical-window group.
- `ridge`: a closed-form linear map of the flattened window features (with the deltas), the best linear fit.
- one row per (temporal, dynamics, seed): the learnt conditioning after `--steps` steps.
- `novel pose`: the same networks on the novel-pose split's frames (generalisation; the held-out cameras of the
  novel-view metric see the training frames).
Writes garment_regress.json (every row) to `--out`. README, "Can the pose window learn the garment?".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hydra.utils import instantiate
from probe import PHASES, phase_of

from realityavatar.build import build_data
from realityavatar.config import compose
from realityavatar.model.encoders import pose_features


def windows(dm, split: str) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """One window per frame of a split, in its first camera's record order (the DataModule's pose table, no images):
    poses [F,T,24,3], transl [F,T,3], frame ids."""
    ds = dm.datasets.get(split)
    if ds is None or not ds.records:
        return torch.zeros(0), torch.zeros(0), []
    first = min(r.view for r in ds.records)
    frames = [int(r.frame) for r in ds.records if r.view == first]
    pairs = [dm.window_for(dm.scene.poses, f) for f in frames]
    return (torch.stack([torch.as_tensor(w[0]) for w in pairs]).float(),
            torch.stack([torch.as_tensor(w[1]) for w in pairs]).float(), frames)


def pelvis_frame_cloth(body, cloth: torch.Tensor, poses: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """World cloth vertices [F,V,3] -> the same in each frame's pelvis frame: the inverse of the pelvis's bone
    transform (canonical -> posed) at the window's current pose, applied to every vertex."""
    A0 = body.canonical_transforms(poses[:, -1].double(), transl[:, -1].double())[:, 0]  # [F,4,4]
    X = torch.cat([cloth.double(), torch.ones_like(cloth[..., :1]).double()], -1)
    return (torch.linalg.inv(A0)[:, None] @ X[..., None])[..., :3, 0].float()


def window_features(poses: torch.Tensor, transl: torch.Tensor, dynamics: str = "deltas") -> torch.Tensor:
    """Every part's features of every window frame, flattened: [F, T * D]."""
    f = pose_features(poses, transl, dynamics)
    return torch.cat([v.reshape(len(poses), -1) for v in f.values()], -1)


def window_floor(X: torch.Tensor, Y: torch.Tensor, tol: float = 1e-6) -> torch.Tensor:
    """Per sample [F]: the RMS over vertices of its target Y [F,V,3] from the mean target of every sample whose
    features X [F,D] equal its own (within tol, max-abs): the error no function of X can go below on average."""
    out = torch.zeros(len(X))
    done = torch.zeros(len(X), dtype=torch.bool)
    for i in range(len(X)):
        if done[i]:
            continue
        group = (X - X[i]).abs().amax(-1) <= tol
        done |= group
        mean = Y[group].mean(0, keepdim=True)
        out[group] = (Y[group] - mean).pow(2).sum(-1).mean(-1).sqrt()
    return out


def ridge(X: torch.Tensor, Y: torch.Tensor, lam: float = 1e-3) -> torch.Tensor:
    """Per sample RMS [F] of the least-squares linear map (with bias, ridge lam) from X [F,D] to Y [F,V,3]."""
    Xc = torch.cat([X, torch.ones(len(X), 1)], -1).double()
    Yf = Y.reshape(len(Y), -1).double()
    W = torch.linalg.solve(Xc.T @ Xc + lam * torch.eye(Xc.shape[1], dtype=Xc.dtype), Xc.T @ Yf)
    return ((Xc @ W).float().reshape(Y.shape) - Y).pow(2).sum(-1).mean(-1).sqrt()


class Conditioned(torch.nn.Module):
    """The model's encoder and temporal module, then a motion basis: y = sum_k c_k(h_t) B_k (as sheet.basis)."""

    def __init__(self, encoder: torch.nn.Module, temporal: torch.nn.Module, hidden: int, verts: int, basis: int):
        super().__init__()
        self.encoder, self.temporal = encoder, temporal
        self.coeff = torch.nn.Linear(hidden, basis)
        self.basis = torch.nn.Parameter(torch.zeros(basis, verts * 3))

    def forward(self, poses: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        h = self.temporal(self.encoder(poses, transl))
        return (self.coeff(h) @ self.basis).reshape(len(poses), -1, 3)


def fit(model: Conditioned, poses, transl, Y, steps: int, batch: int, lr: float, seed: int,
        final_factor: float = 0.1) -> float:
    """Adam on the mean squared 3D error, `batch` frames drawn uniformly per step, the rate decaying exponentially
    to lr * final_factor. Returns the seconds it took."""
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: final_factor ** (s / max(steps, 1)))
    t0 = time.perf_counter()
    for _ in range(steps):
        idx = torch.randint(len(Y), (batch,), generator=gen)
        loss = (model(poses[idx], transl[idx]) - Y[idx]).pow(2).sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    return time.perf_counter() - t0


def per_phase(err: torch.Tensor, phases: list[str]) -> dict[str, float]:
    """Per-sample RMS [F] -> {phase: RMS over that phase's samples, in cm} (and "all")."""
    out = {}
    for ph in (*PHASES, "all"):
        sel = [i for i, p in enumerate(phases) if ph == "all" or p == ph]
        if sel:
            out[ph] = round(100 * float(err[sel].pow(2).mean().sqrt()), 2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="synthetic_sweep", help="data config (a synthetic scene with a garment)")
    ap.add_argument("--temporal", default="lstm,none", help="temporal configs to compare (comma-separated)")
    ap.add_argument("--dynamics", default="none,deltas", help="encoder.dynamics values (comma-separated)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--batch", type=int, default=1, help="frames per step (a training step renders one frame)")
    ap.add_argument("--lr", type=float, default=1e-3, help="the encoder's, temporal module's and decoder's rate")
    ap.add_argument("--basis", type=int, default=64)
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    ap.add_argument("overrides", nargs="*", help="more config overrides (data.window_len=8, ...)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = compose([f"data={args.data}", *args.overrides])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    npz = Path(dm.root) / f"{dm.sequence}-garment.npz"
    if not npz.is_file():
        raise SystemExit(f"{npz}: not found (the regression needs a synthetic scene's simulated garment)")
    g = np.load(npz)
    index = {int(f): i for i, f in enumerate(g["frames"])}
    cloth = torch.as_tensor(g["vertices"], dtype=torch.float32)
    meta = dm.scene.meta or {}
    events = meta.get("motion", {}).get("events", {})
    fps = float(meta.get("fps", 25.0))

    def targets(poses, transl, frames):
        missing = [f for f in frames if f not in index]
        if missing:
            raise ValueError(f"{npz}: no simulated garment for frames {missing[:5]}")
        return pelvis_frame_cloth(body, cloth[[index[f] for f in frames]], poses, transl)

    poses, transl, frames = windows(dm, "train")
    P = targets(poses, transl, frames)
    ref = P[0:1]
    Y = P - ref
    phases = [phase_of(f, events, fps) for f in frames]
    np_poses, np_transl, np_frames = windows(dm, "novel_pose")
    Y_np = targets(np_poses, np_transl, np_frames) - ref if np_frames else None
    with torch.no_grad():
        X = window_features(poses, transl)
        rows = [{"row": "no motion (the first frame's cloth)", **per_phase(Y.pow(2).sum(-1).mean(-1).sqrt(), phases)},
                {"row": "floor (identical windows, different cloth)", **per_phase(window_floor(X, Y), phases)},
                {"row": "ridge (linear in the window's features with deltas)", **per_phase(ridge(X, Y), phases)}]
    if Y_np is not None:
        rows[0]["novel pose"] = round(100 * float(Y_np.pow(2).sum(-1).mean().sqrt()), 2)
    for temporal in args.temporal.split(","):
        for dynamics in args.dynamics.split(","):
            c = compose([f"data={args.data}", f"temporal={temporal}", f"encoder.dynamics={dynamics}", *args.overrides])
            for seed in (int(s) for s in args.seeds.split(",")):
                torch.manual_seed(seed)
                model = Conditioned(instantiate(c.encoder), instantiate(c.temporal), int(c.temporal.hidden_dim),
                                    Y.shape[1], args.basis)
                secs = fit(model, poses, transl, Y, args.steps, args.batch, args.lr, seed)
                with torch.no_grad():
                    err = (model(poses, transl) - Y).pow(2).sum(-1).mean(-1).sqrt()
                    row = {"row": f"temporal={temporal} dynamics={dynamics} seed={seed}", **per_phase(err, phases),
                           "seconds": round(secs, 1)}
                    if Y_np is not None:
                        row["novel pose"] = round(100 * float((model(np_poses, np_transl) - Y_np).pow(2).sum(-1)
                                                              .mean().sqrt()), 2)
                rows.append(row)
                print(row, flush=True)
    cols = [*PHASES, "all", "novel pose"]
    print(f"\n{args.data}: {len(frames)} training frames, window {poses.shape[1]} frames {cfg.data.window_step} apart, "
          f"{args.steps} steps x {args.batch} frame(s), lr {args.lr:g}; RMS cm over the garment's vertices")
    print(f"| | {' | '.join(cols)} |\n|---|{'---:|' * len(cols)}")
    for r in rows:
        print(f"| {r['row']} | " + " | ".join(f"{r[k]:.2f}" if k in r else "" for k in cols) + " |")
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "garment_regress.json").write_text(json.dumps(
            {"data": args.data, "overrides": args.overrides, "steps": args.steps, "batch": args.batch, "lr": args.lr,
             "basis": args.basis, "frames": frames, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
