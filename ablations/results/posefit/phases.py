"""Held-out PSNR / IoU per phase of the sweep scene's spin (rest, spin, the second after the stop, settled) from each
run's per_frame.csv, the spin's gap to rest, NV / NP and training seconds. Usage: python phases.py <run> [...]"""
import csv
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from probe import phase_of

EVENTS = {"spin_start_frame": 15, "spin_stop_frame": 42}
print("| run | NV / NP | rest | spin | after | settled | IoU rest / spin | spin below rest | train s |")
print("|---|---|---:|---:|---:|---:|---|---:|---:|")
for r in sys.argv[1:]:
    with open(f"{r}/per_frame.csv") as fh:
        rows = [x for x in csv.DictReader(fh) if x["split"] == "novel_view"]
    ph: dict[str, list] = {}
    for x in rows:
        ph.setdefault(phase_of(int(x["frame"]), EVENTS, 25.0), []).append((float(x["psnr"]), float(x["iou"])))
    p = {k: np.mean([a for a, _ in v]) for k, v in ph.items()}
    iou = {k: np.mean([b for _, b in v]) for k, v in ph.items()}
    m = json.loads(Path(f"{r}/metrics.json").read_text())
    t = m.get("train_seconds", m.get("timing", {}).get("train_s", float("nan"))) if isinstance(m, dict) else float("nan")
    print(f"| {Path(r).name} | {m['test/novel_view/psnr']:.2f} / {m['test/novel_pose/psnr']:.2f} | {p['rest']:.2f} | "
          f"{p['spin']:.2f} | {p['after']:.2f} | {p['settled']:.2f} | {iou['rest']:.3f} / {iou['spin']:.3f} | "
          f"{p['rest'] - p['spin']:.2f} | {t:.0f} |")
