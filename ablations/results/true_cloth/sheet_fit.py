"""How far a trained sheet run's posed garment-sheet vertices are from the simulated cloth, per phase and per ring.
Needs true_cloth_experiment.patch applied and RA_TRUECLOTH, RA_TRUECLOTH_SUP=1 and the run's RA_TRUECLOTH_UV set:
    python ablations/results/true_cloth/sheet_fit.py <run>"""
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from probe import phase_of

torch.set_num_threads(1)
run = Path(sys.argv[1])
cfg, module, _ = load_run(run)
dm = build_data(cfg, module.body)
ev = dm.scene.meta['motion']['events']
ds = dm.datasets['train']
res = {}
with torch.no_grad():
    for i, rec in enumerate(ds.records):
        if rec.view != 0: continue
        b = default_collate([ds[i]])
        module._oracle_frames = b['frame']
        posed = module.deform_shared(b['poses'], b['transl'], deform=True, frame_idx=b['frame_idx'])
        d = (posed['sheet_verts'] - posed['sheet_true']).norm(dim=-1)[0]
        res.setdefault(phase_of(rec.frame, ev, 25.0), []).append((float(d.pow(2).mean().sqrt()), float(d.median()), rec.frame))
for ph, v in res.items():
    a = np.array([x[:2] for x in v]); rms, med = 100 * a.mean(0)
    print(ph, f'rms {rms:.1f} cm, median {med:.1f} cm', 'worst frame', max(v)[2], '%.1f' % (100 * max(v)[0]))
with torch.no_grad():
    for f in (0, 32):
        i = next(k for k, r in enumerate(ds.records) if r.view == 0 and r.frame == f)
        b = default_collate([ds[i]]); module._oracle_frames = b['frame']
        posed = module.deform_shared(b['poses'], b['transl'], deform=True, frame_idx=b['frame_idx'])
        sh = module.sheet
        d = (posed['sheet_verts'] - posed['sheet_true'])[0].reshape(sh.rows + 1, sh.cols, 3)
        print('frame', f, 'per-ring rms cm', ' '.join('%.1f' % (100 * float(x)) for x in d.norm(dim=-1).pow(2).mean(1).sqrt()))
        print('   radial (cm, + = learnt outside)', end=' ')
        V = posed['sheet_true'][0].reshape(sh.rows + 1, sh.cols, 3); L = posed['sheet_verts'][0].reshape(sh.rows + 1, sh.cols, 3)
        ax = V[0].mean(0)
        rl = (L - ax)[..., [0, 2]].norm(dim=-1); rt = (V - ax)[..., [0, 2]].norm(dim=-1)
        print(' '.join('%.1f' % (100 * float(x)) for x in (rl - rt).mean(1)))
        print('   height (cm, + = learnt higher)', ' '.join('%.1f' % (100 * float(x)) for x in (L[..., 1] - V[..., 1]).mean(1)))
