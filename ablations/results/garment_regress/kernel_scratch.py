# ruff: noqa
# Scratch script of session 33: the sheet basis coefficients as a kernel (Nadaraya-Watson) interpolation of per-training-window codes over standardised window features (or the current frame only), no networks; run as: REALITYAVATAR_SCENES=scenes python kernel.py
import sys, os, time
sys.path.insert(0, '/work/main/ablations')
import torch, numpy as np
from garment_regress import *
from realityavatar.config import compose
from hydra.utils import instantiate
torch.set_num_threads(1)
cfg = compose(['data=synthetic_sweep']); body = instantiate(cfg.body); dm = build_data(cfg, body)
g = np.load(Path(dm.root) / f"{dm.sequence}-garment.npz"); index = {int(f): i for i, f in enumerate(g['frames'])}
cloth = torch.as_tensor(g['vertices'], dtype=torch.float32)
p, t, fr = windows(dm.datasets['train']); pn, tn, frn = windows(dm.datasets['novel_pose'])
P = pelvis_frame_cloth(body, cloth[[index[f] for f in fr]], p, t); ref = P[0:1]; Y = P - ref
Yn = pelvis_frame_cloth(body, cloth[[index[f] for f in frn]], pn, tn) - ref
ev = dm.scene.meta['motion']['events']; phases = [phase_of(f, ev, 25.0) for f in fr]
for feat in ('window', 'current'):
    X = window_features(p, t) if feat == 'window' else window_features(p[:, -1:], t[:, -1:], 'none')
    Xn = window_features(pn, tn) if feat == 'window' else window_features(pn[:, -1:], tn[:, -1:], 'none')
    mu, sd = X.mean(0), X.std(0).clamp_min(1e-3)
    Z, Zn = (X - mu) / sd, (Xn - mu) / sd
    D = torch.cdist(Z, Z); nn_d = (D + torch.eye(len(D)) * 1e9).min(1).values
    for scale in (0.5, 1.0, 2.0):
        for lr in (1e-2, 3e-2):
            sig = scale * float(nn_d[nn_d > 0].median())
            def W(Zq): return torch.softmax(-torch.cdist(Zq, Z) ** 2 / (2 * sig ** 2), -1)
            Wt, Wn = W(Z), W(Zn)
            A = torch.zeros(len(Z), 64, requires_grad=True); B = torch.nn.Parameter(torch.randn(64, Y.shape[1] * 3) * 1e-3)
            opt = torch.optim.Adam([A, B], lr=lr); sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** (s / 1000))
            gen = torch.Generator().manual_seed(0)
            for s in range(1000):
                i = torch.randint(len(Y), (1,), generator=gen)
                pred = (Wt[i] @ A @ B).reshape(1, -1, 3)
                loss = (pred - Y[i]).pow(2).sum(-1).mean(); opt.zero_grad(); loss.backward(); opt.step(); sched.step()
            with torch.no_grad():
                e = ((Wt @ A @ B).reshape(Y.shape) - Y).pow(2).sum(-1).mean(-1).sqrt()
                en = 100 * float(((Wn @ A @ B).reshape(Yn.shape) - Yn).pow(2).sum(-1).mean().sqrt())
            print(feat, 'scale', scale, 'lr', lr, per_phase(e, phases), 'novel pose %.2f' % en, flush=True)
