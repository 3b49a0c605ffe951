"""Forward+backward time of the per-Gaussian model path (encoder, temporal, decoder, skinning, colour) and of the
motion-trend decoder alone, each beside its ratio to the GEMM unit (8 float32 1024^3 matmuls) timed in the same
process, and the decoder's floor: its matmul FLOPs at the GEMM unit's rate.

python benchmarks/components.py [--points 10000 35000] [--repeats 3] [--out benchmarks/results/components_cpu.json]
Times are the best of `repeats` runs (the machine may be shared); batch of 1 frame, 6-frame window, 1 thread.
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
from realityavatar.model.encoders import LatentBoneEncoder, pose_features
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
    features = pose_features(torch.randn(1, 6, 24, 3) * 0.2, torch.randn(1, 6, 3))  # made by the dataset
    A = torch.eye(4).expand(1, 24, 4, 4)

    def step():
        out = dec(means, tem(enc(features)))
        x_e, ls_e, q_e = apply_deformation(means, log_s, quats, out)
        m_o, q_o, _rot = lbs_gaussians(x_e, q_e, skin(x_e), A)
        rgb = col(feats, torch.randn(1, n, 3), out["f_mt"], torch.tensor([3]))
        (m_o.sum() + q_o.sum() + ls_e.sum() + rgb.sum()).backward()

    return step


def decoder_step(n: int):
    torch.manual_seed(0)
    dec = MotionTrendDecoder(cond_dim=128, activation="relu")  # conf/deformer/motion_trend.yaml
    means = (torch.rand(n, 3) - 0.5).requires_grad_()
    dec.fit_bounds(means.detach())
    h = torch.randn(1, 128, requires_grad=True)

    def step():
        out = dec(means, h)
        sum(v.sum() for v in out.values()).backward()

    return step, decoder_flops(dec, n)


def decoder_flops(dec: MotionTrendDecoder, n: int) -> float:
    """Matmul FLOPs of one forward + backward of the decoder over n points (no input gradient for the first layer)."""
    layers = [dec.in_x] + [m for m in dec.hidden if isinstance(m, torch.nn.Linear)] + [dec.out]
    fwd = sum(2 * n * m.in_features * m.out_features for m in layers)
    return fwd + 2 * fwd - 2 * n * dec.in_x.in_features * dec.in_x.out_features


def gemm_unit(repeats: int = 3) -> float:
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    return best_of(lambda: [a @ b for _ in range(8)], repeats)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--points", type=int, nargs="+", default=[10000, 35000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "components_cpu.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    unit = gemm_unit()
    unit_rate = 8 * 2 * 1024**3 / unit  # FLOP/s
    rows = []
    for n in args.points:
        rows.append({"what": "encoder+lstm+decoder+skinning MLP+lbs+colour", "points": n,
                     "seconds": best_of(path_step(n), args.repeats)})
        step, flops = decoder_step(n)
        rows.append({"what": "decoder (motion trend, ReLU)", "points": n, "seconds": best_of(step, args.repeats),
                     "matmul_gflop": flops / 1e9, "floor_seconds": flops / unit_rate})
    print(f"GEMM unit {unit:.3f} s ({unit_rate / 1e9:.0f} GFLOP/s)")
    print(f"{'what':44s} {'N':>7s} {'fwd+bwd ms':>11s} {'units':>6s} {'floor units':>12s}")
    for r in rows:
        floor = f"{r['floor_seconds'] / unit:12.2f}" if "floor_seconds" in r else f"{'':12s}"
        print(f"{r['what']:44s} {r['points']:7d} {1000 * r['seconds']:11.1f} {r['seconds'] / unit:6.2f} {floor}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    meta = {"threads": torch.get_num_threads(), "torch": torch.__version__, "gemm_unit_s": unit,
            "machine": platform.processor() or platform.machine(), "note": "floor: matmul FLOPs at the GEMM unit's rate"}
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
