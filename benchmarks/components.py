"""Forward+backward time of the per-Gaussian model path (encoder, temporal, decoder, skinning, colour).

python benchmarks/components.py [--points 10000 35000] [--repeats 3] [--out benchmarks/results/components_cpu.json]
Times are the best of `repeats` runs (the machine may be shared); batch of 1 frame, 6-frame window.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from realityavatar.model.color import MLPColor
from realityavatar.model.deform import MotionTrendDecoder, apply_deformation
from realityavatar.model.encoders import LatentBoneEncoder
from realityavatar.model.skinning import SkinningField, lbs_gaussians
from realityavatar.model.temporal import RecurrentTemporal


def best_of(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def path_step(n: int):
    torch.manual_seed(0)
    enc, tem = LatentBoneEncoder(), RecurrentTemporal("lstm", 128, 128)
    dec, skin = MotionTrendDecoder(cond_dim=128), SkinningField()
    col = MLPColor(num_frames=100)
    means = (torch.rand(n, 3) - 0.5).requires_grad_()
    log_s = torch.full((n, 3), -4.0, requires_grad=True)
    quats = torch.tensor([1.0, 0, 0, 0]).repeat(n, 1).requires_grad_()
    feats = (torch.randn(n, 32) * 0.01).requires_grad_()
    poses, transl = torch.randn(1, 6, 24, 3) * 0.2, torch.randn(1, 6, 3)
    A = torch.eye(4).expand(1, 24, 4, 4)

    def step():
        out = dec(means, tem(enc(poses, transl)))
        x_e, ls_e, q_e = apply_deformation(means, log_s, quats, out)
        m_o, q_o, _rot = lbs_gaussians(x_e, q_e, skin(x_e), A)
        rgb = col(feats, torch.randn(1, n, 3), out["f_mt"], torch.tensor([3]))
        (m_o.sum() + q_o.sum() + ls_e.sum() + rgb.sum()).backward()

    return step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--points", type=int, nargs="+", default=[10000, 35000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "components_cpu.json"))
    args = ap.parse_args()
    rows = []
    for n in args.points:
        rows.append({"what": "encoder+lstm+decoder+skinning+lbs+colour", "points": n,
                     "seconds": best_of(path_step(n), args.repeats)})
    print(f"{'what':58s} {'N':>7s} {'fwd+bwd ms':>11s}")
    for r in rows:
        print(f"{r['what']:58s} {r['points']:7d} {1000 * r['seconds']:11.1f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    meta = {"threads": torch.get_num_threads(), "torch": torch.__version__, "machine": platform.processor() or platform.machine()}
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
