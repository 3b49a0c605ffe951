import torch, numpy as np, sys
from pathlib import Path
from torch.utils.data import default_collate
from realityavatar.build import build_data, load_run
torch.set_num_threads(2)
cfg, module, _ = load_run(Path(sys.argv[1]))
dm = build_data(cfg, module.body)
ds = dm.datasets["train"]
seen=set()
g=module.gaussians
s_c = torch.exp(g.log_scales).max(-1).values
op = g.opacities()
with torch.no_grad():
  for i, rec in enumerate(ds.records):
    if rec.frame in seen or rec.frame not in (6,10,20,26,30,32,34,36,44,60,90): continue
    seen.add(rec.frame)
    batch = default_collate([ds[i]])
    posed = module.deform(batch["poses"], batch["transl"])
    dx=(posed["x_e"][0]-g.means).norm(dim=-1)
    smax=posed["scales"][0].max(-1).values
    hem = dx > 0.12
    print(rec.frame, "n_hem", int(hem.sum()), "hem smax med %.4f p90 %.4f canon med %.4f | all smax med %.4f | hem opac %.2f" % (
        smax[hem].median() if hem.any() else 0, smax[hem].quantile(0.9) if hem.any() else 0, s_c[hem].median() if hem.any() else 0, smax.median(), op[hem].mean() if hem.any() else 0))
