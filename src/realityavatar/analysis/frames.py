"""Render chosen frames of a trained run from a dataset camera: prediction | ground truth | 4x error, one row each.

Usage: python -m realityavatar.analysis.frames <run_dir> --frames 10,34,46 [--split novel_view] [--view V]
       --out frames.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run, run_device
from realityavatar.runtime import add_threads_option, set_threads


@torch.no_grad()
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m realityavatar.analysis.frames",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--frames", required=True, help="comma-separated global frame ids")
    ap.add_argument("--split", default="novel_view", choices=("train", "novel_view", "novel_pose"))
    ap.add_argument("--view", type=int, default=None, help="camera id (default: the split's first)")
    ap.add_argument("--out", required=True)
    add_threads_option(ap)
    a = ap.parse_args(argv)
    set_threads(a.threads, "--threads")
    cfg, module, _ = load_run(Path(a.run))
    ds = build_data(cfg, module.avatar.body).datasets[a.split]
    module.to(run_device(cfg))  # a GPU run renders with its own backend (gsplat needs CUDA tensors)
    views = sorted({r.view for r in ds.records})
    view = views[0] if a.view is None else a.view
    if view not in views:
        print(f"--view {view}: split {a.split} has cameras {views}", file=sys.stderr)
        return 2
    rows = []
    for f in (int(x) for x in a.frames.split(",")):
        idx = [i for i, r in enumerate(ds.records) if r.frame == f and r.view == view]
        if not idx:
            print(f"--frames: frame {f} is not in split {a.split}", file=sys.stderr)
            return 2
        batch = module.device_batch(default_collate([ds[idx[0]]]))
        rgb = module.avatar.render_batch(batch)[0][0].clamp(0, 1).cpu().numpy()
        gt = batch["image"][0].cpu().numpy()
        rows.append(np.concatenate([rgb, gt, np.clip(4 * np.abs(rgb - gt), 0, 1)], 1))
    import matplotlib.pyplot as plt

    plt.imsave(a.out, np.concatenate(rows, 0))
    print(f"wrote {a.out} (frames {a.frames}, {a.split} camera {view}; prediction | ground truth | 4x error)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
