"""Scratch: how well a trained run's pose path meets its training silhouettes, per phase (posefit's own terms, all
mask pixels, every Gaussian centre). Usage: python silhouette_fit_scratch.py <run> [...]"""
import sys

import numpy as np
import torch

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2]))
import torch.nn.functional as F
from probe import phase_of

from realityavatar.build import build_data, load_run
from realityavatar.losses import nearest_index, project_points
from realityavatar.model.posefit import SilhouettePoseFit

torch.set_num_threads(2)
ev = {"spin_start_frame": 15, "spin_stop_frame": 42}
for run in sys.argv[1:]:
    cfg, module, _ = load_run(run)
    dm = build_data(cfg, module.body)
    pf = SilhouettePoseFit()
    pf.build(dm)
    module.set_progress(None)
    ph = {}
    with torch.no_grad():
        for b in pf.bank:
            pts = module.deform_points(b["poses"][None], b["transl"][None], torch.arange(module.gaussians.num_points))[0]
            S = module.gaussians.num_points
            for v in b["views"]:
                uv, z = project_points(pts, v["viewmat"], v["K"])
                dist = v["dist"].float(); H, W = dist.shape
                inside = uv.clamp(min=0); inside = torch.minimum(inside, uv.new_tensor([W - 1., H - 1.]))
                g = (inside / uv.new_tensor([W - 1., H - 1.]) * 2 - 1)[None, None]
                d = F.grid_sample(dist[None, None], g, align_corners=True)[0, 0, 0] + (uv - inside).norm(dim=-1)
                pix = v["pix"].float()
                gap = (uv[nearest_index(pix, uv)] - pix).norm(dim=-1)
                # sheet only: the garment's own points outside the masks
                rec = (float(np.percentile(gap, 99)), float(gap.max()), float((gap > 2).float().mean()),
                       float(np.percentile(d[S:], 99)) if len(d) > S else 0.0, float(np.percentile(d[:S], 99)))
                ph.setdefault(phase_of(b["frame"], ev, 25.0), []).append(rec)
    print(run)
    print("  phase   cover_p99px cover_max_px frac_px>2px  sheet_out_p99px free_out_p99px")
    for k, v in ph.items():
        a = np.mean(v, 0)
        print(f"  {k:8s} {a[0]:10.2f} {a[1]:11.2f} {a[2]:11.4f} {a[3]:14.2f} {a[4]:14.2f}")
