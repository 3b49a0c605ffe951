# ruff: noqa
# Scratch script of session 33: the LSTM path plus a kernel over training windows (rbf: unnormalised Gaussian weights; nw: normalised), as pose-space deformation; run as: REALITYAVATAR_SCENES=scenes python kernel2.py rbf,nw
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
X = window_features(p, t); Xn = window_features(pn, tn)
mu, sd = X.mean(0), X.std(0).clamp_min(1e-3)
Z, Zn = (X - mu) / sd, (Xn - mu) / sd
D = torch.cdist(Z, Z); nn_d = (D + torch.eye(len(D)) * 1e9).min(1).values
med = float(nn_d[nn_d > 0].median())
print('median nn dist', med, 'novel nn dist median', float(torch.cdist(Zn, Z).min(1).values.median()))
for mode in sys.argv[1].split(','):
    for scale in (1.0, 3.0):
        torch.manual_seed(0)
        c = compose(['data=synthetic_sweep'])
        enc, tem = instantiate(c.encoder), instantiate(c.temporal)
        coeff = torch.nn.Linear(128, 64)
        sig = scale * med
        def Wf(Zq):
            w = torch.exp(-torch.cdist(Zq, Z) ** 2 / (2 * sig ** 2))
            return w / w.sum(-1, keepdim=True) if mode == 'nw' else w
        Wt, Wn = Wf(Z), Wf(Zn)
        A = torch.zeros(len(Z), 64, requires_grad=True); B = torch.nn.Parameter(torch.zeros(64, Y.shape[1] * 3))
        def pred(pp, tt, Wq):
            out = coeff(tem(enc(pp, tt))) + Wq @ A
            return (out @ B).reshape(len(pp), -1, 3)
        opt = torch.optim.Adam([{'params': list(enc.parameters()) + list(tem.parameters()) + list(coeff.parameters()) + [B], 'lr': 1e-3}, {'params': [A], 'lr': 1e-2}])
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** (s / 1000))
        gen = torch.Generator().manual_seed(0)
        for s in range(1000):
            i = torch.randint(len(Y), (1,), generator=gen)
            loss = (pred(p[i], t[i], Wt[i]) - Y[i]).pow(2).sum(-1).mean(); opt.zero_grad(); loss.backward(); opt.step(); sched.step()
        with torch.no_grad():
            e = (pred(p, t, Wt) - Y).pow(2).sum(-1).mean(-1).sqrt()
            en = 100 * float((pred(pn, tn, Wn) - Yn).pow(2).sum(-1).mean().sqrt())
        print(mode, 'scale', scale, per_phase(e, phases), 'novel pose %.2f' % en, 'self-weight median %.2f' % float(Wt.diagonal().median()), flush=True)
