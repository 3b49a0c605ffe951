"""Can the trained model's deformation path (encoder, LSTM, decoder, sheet basis) represent the true cloth?
Regress the posed sheet vertices onto the simulated cloth (3D term only, no images) from a trained checkpoint."""
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from probe import phase_of

torch.set_num_threads(1)
run = Path(sys.argv[1]); steps = int(sys.argv[2]); mode = sys.argv[3]
cfg, module, _ = load_run(run)
dm = build_data(cfg, module.body)
ev = dm.scene.meta['motion']['events']
ds = dm.datasets['train']
items = [default_collate([ds[i]]) for i, r in enumerate(ds.records) if r.view == 0 and (mode != 'perframeonly' or r.frame in ((32,) if os.environ.get('ONLY32') else (0, 32)))]
for p in module.parameters(): p.requires_grad_(False)
params = []
for name in (() if mode in ('staticonly', 'perframeonly') else ('encoder', 'temporal', 'deformer', 'skinning')):
    for p in getattr(module, name).parameters(): p.requires_grad_(True); params.append(p)
if module.sheet.num_basis and mode not in ('staticonly', 'perframeonly'):
    module.sheet.basis.requires_grad_(True); params.append(module.sheet.basis)
    for p in module.sheet.coeff.parameters(): p.requires_grad_(True); params.append(p)
P = module.sheet.vertices.shape[0]
static = torch.zeros(P, 3, requires_grad=True)
if mode in ('static', 'perframe', 'staticonly'):
    params.append(static)
perframe = torch.zeros(len(items), P, 3, requires_grad=True)
orig = module.sheet.basis_offsets
fi = {int(b['frame'][0]): k for k, b in enumerate(items)}
cur = {}
def basis_offsets(h_t):
    out = orig(h_t) + static[None]
    if mode in ('perframe', 'perframeonly'):
        out = out + perframe[cur['k']][None]
    return out
module.sheet.basis_offsets = basis_offsets
opt = torch.optim.Adam([{'params': params, 'lr': 1e-3}, {'params': [perframe], 'lr': float(os.environ.get('PF_LR', '1e-2'))}])
gen = torch.Generator().manual_seed(0)
def err(b):
    module._oracle_frames = b['frame']; cur['k'] = fi[int(b['frame'][0])]
    posed = module.deform_shared(b['poses'], b['transl'], deform=True, frame_idx=b['frame_idx'])
    return (posed['sheet_verts'] - posed['sheet_true'])[0]
t0 = time.time()
for s in range(steps):
    b = items[int(torch.randint(len(items), (1,), generator=gen))]
    loss = err(b).pow(2).sum(-1).mean()
    opt.zero_grad(); loss.backward(); opt.step()
    if s % 50 == 0: print(s, float(loss), flush=True)
res = {}
with torch.no_grad():
    for b in items:
        d = err(b).norm(dim=-1)
        res.setdefault(phase_of(int(b['frame'][0]), ev, 25.0), []).append(float(d.pow(2).mean().sqrt()))
    b = next(x for x in items if int(x['frame'][0]) == 32)
    e = err(b).reshape(module.sheet.rows + 1, module.sheet.cols, 3)
    hem = e[-1].norm(dim=-1).pow(2).mean().sqrt()
    print('frame 32 per-ring rms cm', ' '.join('%.1f' % (100 * float(x)) for x in e.norm(dim=-1).pow(2).mean(1).sqrt()))
    print('worst vertices (cm):', [round(100 * float(x), 1) for x in e.norm(dim=-1).flatten().topk(8).values])
print(f"{mode} {steps} steps ({time.time() - t0:.0f} s): " + ", ".join(f"{k} {100 * np.mean(v):.1f}" for k, v in res.items()) + f" cm RMS; hem at frame 32 {100 * float(hem):.1f} cm")
