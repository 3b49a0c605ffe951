"""The training process's time per batch of the training loader: what a host-bound GPU step waits on besides itself.

python benchmarks/loader.py "+experiment=paper_scale" --workers 0 4 [--batches 60] [--pause 0.04] [--out FILE]

For each loader-worker count, one epoch is drawn first (images and distance fields cached, as after the first epoch
of a training), then `--batches` batches are timed in the main process with `--pause` seconds between them (a
training step's place: caches cool and workers get ahead). Prints median and 90th percentile per count, and the
median time of `composite` (the image over its background: after the transfer, on the device on a GPU; on the host
in a CPU run), and writes JSON (default benchmarks/results/loader_cpu.json).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch
from hydra.utils import instantiate


def fetch_times(overrides: list[str], workers: int, batches: int, pause: float) -> tuple[list[float], list[float]]:
    """Seconds per batch in the main process: the loader's, and `composite`'s (done where the batch is after its
    transfer: on the device on a GPU, here on the host as in a CPU run)."""
    from realityavatar.build import build_data
    from realityavatar.config import compose
    from realityavatar.data.datamodule import composite

    cfg = compose([*overrides, f"data.num_workers={workers}"])
    dm = build_data(cfg, instantiate(cfg.body))
    loader = dm.train_dataloader()
    it = iter(loader)
    for _ in range(len(loader)):  # one epoch: every sample's image and distance field cached
        next(it)
    it, times, comp = iter(loader), [], []
    for _ in range(batches):
        time.sleep(pause)
        t0 = time.perf_counter()
        try:
            batch = next(it)
        except StopIteration:
            it = iter(loader)
            batch = next(it)
        t1 = time.perf_counter()
        composite(batch)
        times.append(t1 - t0)
        comp.append(time.perf_counter() - t1)
    return times, comp


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("overrides", help="hydra overrides of the training run, one string")
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 4])
    ap.add_argument("--batches", type=int, default=60)
    ap.add_argument("--pause", type=float, default=0.04, help="seconds between batches (a training step's place)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "loader_cpu.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for w in args.workers:
        t, c = fetch_times(shlex.split(args.overrides), w, args.batches, args.pause)
        t = sorted(t)
        rows.append({"workers": w, "median_ms": 1e3 * statistics.median(t), "p90_ms": 1e3 * t[int(0.9 * (len(t) - 1))],
                     "composite_host_ms": 1e3 * statistics.median(c), "batches": len(t)})
        print(f"workers {w}: main process {rows[-1]['median_ms']:.2f} ms per batch (median), "
              f"p90 {rows[-1]['p90_ms']:.2f} ms, {len(t)} batches; composite on the host "
              f"{rows[-1]['composite_host_ms']:.2f} ms (on a GPU: on the device)")
    from realityavatar.build import git_commit

    used = sys.argv[1:] if argv is None else argv
    meta = {"command": "python benchmarks/loader.py " + " ".join(shlex.quote(a) for a in used), "commit": git_commit(),
            "overrides": args.overrides, "pause_s": args.pause, "threads": args.threads,
            "machine": platform.platform(), "cores": len(os.sched_getaffinity(0))}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"meta": meta, "results": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
