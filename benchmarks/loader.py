"""The training process's time per batch of the training loader: what a host-bound GPU step waits on besides itself.

python benchmarks/loader.py "+experiment=paper_scale" --workers 0 4 [--device-cache] [--device cuda] [--batches 60]
                            [--pause 0.04] [--out FILE]

For each loader-worker count, one epoch is drawn first (images and distance fields cached, as after the first epoch
of a training), then `--batches` batches are timed in the main process with `--pause` seconds between them (a
training step's place: caches cool and workers get ahead): the loader's next batch and the trainer's move of it to
`--device` (data/lightning.py TrainingData's transfer hook; pinned batches on a GPU). Prints median and 90th percentile per row, and
the median time of `composite` (the image over its background, where the batch is), and writes JSON (default
benchmarks/results/loader_cpu.json). `--device-cache` adds a row with the training set kept on the device
(data.device_cache, DeviceSamples): on a CPU it is kept in the process's memory, as a GPU run keeps it on the GPU.
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


def fetch_times(overrides: list[str], workers: int, batches: int, pause: float, device: str = "cpu",
                device_cache: bool = False) -> tuple[list[float], list[float]]:
    """Seconds per batch in the main process: the loader's next batch with its move to `device`, and `composite`'s
    (done where the batch is after its transfer)."""
    from types import SimpleNamespace

    from realityavatar.build import build_data
    from realityavatar.config import compose
    from realityavatar.data.datamodule import composite
    from realityavatar.data.lightning import TrainingData

    cfg = compose([*overrides, f"data.num_workers={workers}", f"data.device_cache={device_cache}"])
    dm = TrainingData(build_data(cfg, instantiate(cfg.body)))
    target = torch.device(device)
    dm.trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=target), training=True)  # as in fit
    dm.setup("fit")
    if device_cache and target.type == "cpu":
        dm.data._store_device = lambda: target  # kept in the process, as a GPU run keeps it on the GPU
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
        batch = dm.transfer_batch_to_device(dm.on_before_batch_transfer(batch, 0), target, 0)
        t1 = time.perf_counter()
        composite(batch)
        if target.type == "cuda":
            torch.cuda.synchronize()
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
    ap.add_argument("--device", default="cpu", help="where the trainer moves the batches (cpu, cuda)")
    ap.add_argument("--device-cache", action="store_true",
                    help="also a row with the training set kept on the device (data.device_cache)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "loader_cpu.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for w, kept in [(w, False) for w in args.workers] + ([(0, True)] if args.device_cache else []):
        t, c = fetch_times(shlex.split(args.overrides), w, args.batches, args.pause, args.device, kept)
        t = sorted(t)
        rows.append({"workers": w, "device_cache": kept, "device": args.device,
                     "median_ms": 1e3 * statistics.median(t), "p90_ms": 1e3 * t[int(0.9 * (len(t) - 1))],
                     "composite_ms": 1e3 * statistics.median(c), "batches": len(t)})
        print(f"workers {w}{', training set kept on the device' if kept else ''}: main process "
              f"{rows[-1]['median_ms']:.2f} ms per batch moved to {args.device} (median), p90 "
              f"{rows[-1]['p90_ms']:.2f} ms, {len(t)} batches; composite {rows[-1]['composite_ms']:.2f} ms")
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
