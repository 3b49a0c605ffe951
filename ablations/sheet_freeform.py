"""How far a per-frame correction of a trained garment sheet gets: a bound on what the decoder could still learn.

Usage: python ablations/sheet_freeform.py <run_dir> --frames 32 [40 ...] [--steps 400] [--lr 2e-3] [--oracle] [--colour]
       [--out <dir>]

For each frame, every network and Gaussian of a trained `sheet=skirt` run is frozen and only a free offset per sheet
vertex (posed space, [P,3]) is fitted to that frame's training images with the run's own training loss (L1 +
D-SSIM/perceptual + mask, plus the silhouette chamfer). It prints and writes the training- and held-out-camera PSNR and IoU of that frame before and after, and the offsets'
size. If the held-out cameras gain little while the training cameras gain much, what is left of the frame's error
is what its training views leave open, not what the decoder failed to learn (README, "A garment sheet"). --oracle fits the held-out cameras' images
as well: how far the sheet's geometry alone could take the held-out cameras if they had been seen; --colour adds a
per-frame RGB offset of every Gaussian (the appearance's share). Written as freeform[_oracle][_colour].json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run
from realityavatar.metrics import psnr, silhouette_iou


@torch.no_grad()
def evaluate(module, batches) -> dict:
    vals = []
    for b in batches:
        rgb, alpha, _, _ = module.render_batch(b)
        vals.append((float(psnr(rgb[0].clamp(0, 1), b["image"][0])), float(silhouette_iou(alpha[0], b["mask"][0]))))
    v = np.mean(vals, 0)
    return {"psnr": float(v[0]), "iou": float(v[1]), "images": len(batches)}


def fit_frame(module, dm, frame: int, steps: int, lr: float, seed: int = 0, oracle: bool = False,
              colour: bool = False) -> dict:
    sheet = module.sheet
    train = [default_collate([dm.datasets["train"][i]]) for i, r in enumerate(dm.datasets["train"].records) if r.frame == frame]
    held = [default_collate([dm.datasets["novel_view"][i]]) for i, r in enumerate(dm.datasets["novel_view"].records)
            if r.frame == frame] if "novel_view" in dm.datasets else []
    if not train:
        raise ValueError(f"frame {frame} is not a training frame of this run")
    delta = torch.zeros(sheet.vertices.shape[0], 3, requires_grad=True)
    place, shade = sheet.place, module.shade
    sheet.place = lambda v: place(v + delta[None].to(v))  # the correction rides on the posed vertices
    # colour: a per-frame RGB offset of every rendered Gaussian (free and sheet) as well, after the colour MLP
    n_all = module.gaussians.num_points + sheet.num_points
    drgb = torch.zeros(n_all, 3, requires_grad=True)
    if colour:
        module.shade = lambda posed, *a: shade(posed, *a) + drgb[None].to(posed["means"])
    try:
        before = {"train": evaluate(module, train), "heldout": evaluate(module, held) if held else None}
        fit = train + held if oracle else train  # oracle: the held-out cameras' images too (a bound, not a result)
        opt = torch.optim.Adam([{"params": [delta], "lr": lr}, {"params": [drgb], "lr": 1e-2}])
        gen = torch.Generator().manual_seed(seed)
        skin_pts, skin_w = module._skin_targets()
        for _ in range(steps):
            b = fit[int(torch.randint(len(fit), (1,), generator=gen))]
            rgb, alpha, _, posed = module.render_batch(b)
            total, _ = module.loss_fn(rgb, alpha, b["image"], b["mask"], skinning=module.skinning, skin_points=skin_pts,
                                      skin_weights=skin_w, skin_decayed=True)
            if module.silhouette is not None:
                sil = module.silhouette(posed["means"][0], b["viewmat"][0], b["K"][0], b["mask"][0], alpha[0])
                if sil:  # silhouette=none returns no terms
                    total = total + module.silhouette.total(sil)
            opt.zero_grad(set_to_none=True)
            total.backward()
            opt.step()
        after = {"train": evaluate(module, train), "heldout": evaluate(module, held) if held else None}
    finally:
        sheet.place, module.shade = place, shade
    n = delta.detach().norm(dim=-1)
    return {"frame": frame, "steps": steps, "lr": lr, "oracle": oracle, "colour": colour, "before": before, "after": after,
            "offset_p50_m": float(n.median()), "offset_max_m": float(n.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--frames", type=int, nargs="+", required=True)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--lr", type=float, default=2e-3, help="Adam step on the offsets, metres")
    ap.add_argument("--oracle", action="store_true",
                    help="fit the held-out cameras' images too: how far the sheet's geometry alone could go with views")
    ap.add_argument("--colour", action="store_true",
                    help="fit a per-frame RGB offset of every Gaussian as well (appearance, not only the sheet's shape)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None, help="folder for freeform.json (default: print only)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg, module, _ = load_run(Path(args.run))
    if module.sheet is None:
        raise SystemExit(f"{args.run}: not a sheet=skirt run (no garment sheet to correct)")
    for p in module.parameters():
        p.requires_grad_(False)
    dm = build_data(cfg, module.body)
    rows = []
    print("| frame | train PSNR / IoU before → after | held-out PSNR / IoU before → after | offset p50 / max (cm) |")
    print("|---|---|---|---|")
    for f in args.frames:
        r = fit_frame(module, dm, f, args.steps, args.lr, oracle=args.oracle, colour=args.colour)
        rows.append(r)
        h0, h1 = r["before"]["heldout"], r["after"]["heldout"]
        held = f"{h0['psnr']:.2f} / {h0['iou']:.3f} → {h1['psnr']:.2f} / {h1['iou']:.3f}" if h0 else "—"
        print(f"| {f} | {r['before']['train']['psnr']:.2f} / {r['before']['train']['iou']:.3f} → "
              f"{r['after']['train']['psnr']:.2f} / {r['after']['train']['iou']:.3f} | {held} | "
              f"{100 * r['offset_p50_m']:.1f} / {100 * r['offset_max_m']:.1f} |", flush=True)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        name = "freeform" + ("_oracle" if args.oracle else "") + ("_colour" if args.colour else "") + ".json"
        (out / name).write_text(json.dumps({"run": str(args.run), "rows": rows}, indent=1))
        print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
