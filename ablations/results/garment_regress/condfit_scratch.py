# ruff: noqa: B023
"""Pose window -> canonical sheet offsets (pelvis-skinned targets): how well can the conditioning fit them?"""
# Scratch script of session 33 (needs the true-cloth patch, ablations/results/true_cloth/, on a worktree of ee8a46f, and
# RA_TRUECLOTH, RA_TRUECLOTH_SUP=1, RA_TRUECLOTH_UV set): modes lstm, skip, mlp, root, *_deltas, *_direct; env LR, BS, STEPS,
# DECAY, BLR, NTRAIN. ablations/garment_regress.py is the kept, patch-free version of its question.
import os
import sys
import time
from pathlib import Path

import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run
from realityavatar.model.encoders import LatentBoneEncoder, pose_features
from realityavatar.model.temporal import RecurrentTemporal

torch.set_num_threads(2)
run = Path(sys.argv[1])
cfg, module, _ = load_run(run)
dm = build_data(cfg, module.body)
ds = dm.datasets['train']
items = [default_collate([ds[i]]) for i, r in enumerate(ds.records) if r.view == 0]
sh = module.sheet; V = sh.vertices; P = V.shape[0]
with torch.no_grad():
    T = []
    for b in items:
        module._oracle_frames = b['frame']
        tru = module._true_cloth(V[None])[0]
        A0 = module.body.canonical_transforms(b['poses'][:, -1], b['transl'][:, -1])[0, 0]
        xc = (torch.linalg.inv(A0) @ torch.cat([tru, torch.ones(P, 1)], -1)[..., None])[:, :3, 0]
        T.append(xc - V)
    T = torch.stack(T)  # [F,P,3]
poses = torch.cat([b['poses'] for b in items]); transl = torch.cat([b['transl'] for b in items])
frames = [int(b['frame'][0]) for b in items]
Y = T.reshape(len(T), -1)
def rms(pred): return 100 * float(((pred.reshape(len(T), P, 3) - T) ** 2).sum(-1).mean().sqrt())
def rms_f(pred): return (100 * ((pred.reshape(len(T), P, 3) - T) ** 2).sum(-1).mean(-1).sqrt())
print('frames', len(T), 'zero-offset', rms(torch.zeros_like(Y)), 'mean', rms(Y.mean(0, keepdim=True).expand_as(Y)))
for dyn in ('none', 'deltas'):
    f = pose_features(poses, transl, dyn)
    X = torch.cat([v.reshape(len(T), -1) for v in f.values()], -1).double()
    Xc = torch.cat([X, torch.ones(len(X), 1, dtype=X.dtype)], -1)
    for lam in (1e-3, 1e-1):
        W = torch.linalg.solve(Xc.T @ Xc + lam * torch.eye(Xc.shape[1], dtype=X.dtype), Xc.T @ Y.double())
        print(f'ridge {dyn} lam {lam}: fit {rms((Xc @ W).float()):.2f} cm')
torch.manual_seed(0)
def phases(e): return f"frames 0-14 {float(e[:15].pow(2).mean().sqrt()):.2f} spin 15-42 {float(e[15:43].pow(2).mean().sqrt()):.2f} after 43-67 {float(e[43:68].pow(2).mean().sqrt()):.2f} later {float(e[68:].pow(2).mean().sqrt()):.2f}"
Xr = torch.cat([v.reshape(len(T), -1) for v in pose_features(poses, transl, 'deltas').values()], -1).double()
Xc = torch.cat([Xr, torch.ones(len(Xr), 1, dtype=Xr.dtype)], -1)
W = torch.linalg.solve(Xc.T @ Xc + 1e-3 * torch.eye(Xc.shape[1], dtype=Xr.dtype), Xc.T @ Y.double())
print('ridge deltas', phases(rms_f((Xc @ W).float())))
class Flat(torch.nn.Module):
    def __init__(self, dyn, hidden, layers):
        super().__init__(); self.dyn = dyn
        d = sum(v.shape[-1] for v in pose_features(poses[:1], transl[:1], dyn).values()) * poses.shape[1]
        mods = []; 
        for _ in range(layers): mods += [torch.nn.Linear(d, hidden), torch.nn.SiLU()]; d = hidden
        self.net = torch.nn.Sequential(*mods) if mods else torch.nn.Identity(); self.out_dim = d
    def forward(self, p, t):
        f = pose_features(p, t, self.dyn); return self.net(torch.cat([v.reshape(len(p), -1) for v in f.values()], -1))
for mode in sys.argv[2].split(','):
    dyn = 'deltas' if 'deltas' in mode else 'none'
    K = 64
    enc = LatentBoneEncoder(dynamics=dyn); tem = RecurrentTemporal(kind='lstm', in_dim=128, hidden_dim=128)
    flat = Flat(dyn, 256, 2 if 'mlp' in mode else 0)
    extra = []
    if mode.startswith('root'):
        from realityavatar.geometry import axis_angle_to_matrix
        def rootfeat(p, t):
            R0 = axis_angle_to_matrix(p[:, :, 0])  # [B,T,3,3]
            rel = R0[:, :-1].transpose(-1, -2) @ R0[:, 1:]
            # axis-angle of rel via the skew part (small-angle-safe enough for features)
            w = torch.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1) / 2
            c = (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
            ang = torch.atan2(w.norm(dim=-1), c)[..., None]
            w = torch.nn.functional.normalize(w, dim=-1) * ang
            Rt = R0[:, -1:]
            v = (Rt.transpose(-1, -2) @ (t[:, 1:] - t[:, :-1])[..., None])[..., 0]
            return torch.cat([w, v], -1).reshape(len(p), -1)
        hid = 64
        net = torch.nn.Sequential(torch.nn.Linear(6 * (poses.shape[1] - 1), hid), torch.nn.SiLU(), torch.nn.Linear(hid, hid), torch.nn.SiLU())
        extra = list(net.parameters()); cdim = hid
        cond = lambda p, t: net(rootfeat(p, t))
    elif mode.startswith('mlp'):
        cond = lambda p, t: flat(p, t); cdim = flat.out_dim; extra = list(flat.parameters())
    elif mode.startswith('skip'):
        lin = torch.nn.Linear(flat.out_dim, K); extra = list(lin.parameters())
        cond = lambda p, t: torch.cat([tem(enc(p, t)), flat(p, t)], -1); cdim = 128 + flat.out_dim
    else:
        cond = lambda p, t: tem(enc(p, t)); cdim = 128
    if 'direct' in mode: K = cdim
    basis = torch.nn.Parameter(torch.zeros(K, P * 3)); coeff = torch.nn.Linear(cdim, K)
    if 'direct' in mode:
        coeff = lambda x: x
    nets = list(enc.parameters()) + list(tem.parameters()) + extra + (list(coeff.parameters()) if isinstance(coeff, torch.nn.Module) else [])
    lr = float(os.environ.get('LR', '1e-3'))
    opt = torch.optim.Adam([{'params': nets, 'lr': lr}, {'params': [basis], 'lr': lr * float(os.environ.get('BLR', '1'))}])
    t0 = time.time()
    bs = int(os.environ.get('BS', '1'))
    g = torch.Generator().manual_seed(0)
    NS = int(os.environ.get('STEPS', '1000')); DEC = float(os.environ.get('DECAY', '1'))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: DEC ** (s / NS))
    for s in range(NS):
        idx = torch.randint(int(os.environ.get('NTRAIN', len(T))), (bs,), generator=g)
        pred = coeff(cond(poses[idx], transl[idx])) @ basis
        loss = ((pred - Y[idx]) ** 2).reshape(bs, P, 3).sum(-1).mean()
        opt.zero_grad(); loss.backward(); opt.step(); sched.step()
    with torch.no_grad():
        pred = coeff(cond(poses, transl)) @ basis
    print(f'{mode} lr {lr} bs {bs}: fit {rms(pred):.2f} cm; {phases(rms_f(pred))} ({time.time()-t0:.0f} s)', flush=True)
f = pose_features(poses, transl, 'none'); X = torch.cat([v.reshape(len(T), -1) for v in f.values()], -1)
for a, b in ((0, 99), (0, 14), (0, 80), (80, 99)):
    print(f'frames {frames[a]} vs {frames[b]}: feature diff {float((X[a]-X[b]).norm()):.3f}, target diff RMS {100*float((T[a]-T[b]).pow(2).sum(-1).mean().sqrt()):.2f} cm, pose diff {float((poses[a]-poses[b]).abs().max()):.3f} transl diff {float((transl[a]-transl[b]).abs().max()):.3f}')
