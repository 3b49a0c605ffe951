"""Cost of the garment-motion mechanisms per training step: silhouette chamfer, the per-Gaussian decoder, skinning
grid vs skinning MLP, world-lit shading (irradiance map on the posed body normal).

Usage: python benchmarks/garment.py [--threads 1] [--out benchmarks/results/garment_cpu.json]
Prints seconds and GEMM units (8 float32 matmuls of 1024³ timed in the same process) for forward+backward.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def gemm_unit(repeats: int = 3) -> float:
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(8):
            a @ b
        best = min(best, time.perf_counter() - t0)
    return best


def timeit(fn, repeats: int = 5) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    from hydra.utils import instantiate

    from realityavatar.config import compose
    from realityavatar.data.records import mask_distance

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="benchmarks/results/garment_cpu.json")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    unit = gemm_unit()
    cfg = compose([])  # the default components, as a run builds them
    rows = []
    for res in (128, 256):
        K = torch.tensor([[res * 1.2, 0, res / 2], [0, res * 1.2, res / 2], [0, 0, 1.0]])
        E = torch.eye(4)
        E[2, 3] = 2.8
        yy, xx = torch.meshgrid(torch.arange(res), torch.arange(res), indexing="ij")
        mask = (((xx - res / 2) / (res * 0.25)) ** 2 + ((yy - res / 2) / (res * 0.4)) ** 2 < 1).float()[..., None]
        alpha = mask * (xx < res / 2).float()[..., None]  # half of the silhouette uncovered
        for n in (5000, 10000):
            means = (torch.randn(n, 3) * 0.3).requires_grad_(True)
            loss = instantiate(compose(["silhouette=chamfer"]).silhouette)

            dist = mask_distance(mask[..., 0])  # the dataset's, once per image

            def step(loss=loss, means=means, mask=mask, dist=dist, alpha=alpha, E=E, K=K):
                loss.total(loss.image_terms(means, E, K, mask, dist, alpha)).backward()

            rows.append({"part": "silhouette chamfer", "resolution": res, "gaussians": n, "seconds": timeit(step)})
    for n in (5000, 10000):
        x = torch.randn(n, 3) * 0.3
        h = torch.randn(1, 128)
        dec = instantiate(cfg.deformer)  # the configured decoder (conf/deformer)
        dec(x, h)  # fit the box once, as training does

        def step(dec=dec, x=x, h=h):
            out = dec(x, h)
            (out["dx"].sum() + out["ds"].sum() + out["dq"].sum() + out["f_mt"].sum()).backward()

        rows.append({"part": "decoder per Gaussian", "resolution": None, "gaussians": n, "seconds": timeit(step)})
    from realityavatar.body import build_body

    body = build_body("mannequin")
    verts = body.canonical_vertices().detach()
    grid = instantiate(compose(["skinning=grid"]).skinning)
    grid.init_from_body(verts, body.faces, body.skin_weights)
    mlp = instantiate(compose(["skinning=mlp"]).skinning)
    for n in (5000, 10000):
        x = (verts[torch.randint(0, verts.shape[0], (n,))] + 0.05 * torch.randn(n, 3)).requires_grad_(True)
        for name, field in (("skinning MLP", mlp), ("skinning grid", grid)):
            def step(field=field, x=x):
                w = field(x)
                (w * torch.arange(24.0)).sum().backward()

            rows.append({"part": name, "resolution": None, "gaussians": n, "seconds": timeit(step)})

    shading = instantiate(cfg.shading)
    shading.init_from_body(verts, body.faces)
    for n in (5000, 10000):
        x = verts[torch.randint(0, verts.shape[0], (n,))][None] + 0.05 * torch.randn(1, n, 3)
        rot = torch.linalg.qr(torch.randn(1, n, 3, 3))[0]
        rgb = torch.rand(1, n, 3, requires_grad=True)

        def step(rgb=rgb, x=x, rot=rot):
            (rgb * shading(x, rot)).sum().backward()

        rows.append({"part": "shading irradiance", "resolution": None, "gaussians": n, "seconds": timeit(step)})
    for r in rows:
        r["gemm_units"] = r["seconds"] / unit
    print(f"GEMM unit (8 x 1024³ float32 matmuls): {unit * 1000:.1f} ms, {a.threads} thread(s)")
    print(f"{'part':<28}{'res':>6}{'N':>8}{'ms':>10}{'units':>8}")
    for r in rows:
        print(f"{r['part']:<28}{r['resolution'] or '-'!s:>6}{r['gaussians']:>8}{r['seconds'] * 1000:10.1f}"
              f"{r['gemm_units']:8.3f}")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"gemm_unit_s": unit, "threads": a.threads, "rows": rows}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
