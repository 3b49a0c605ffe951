"""Scene-generation benchmark: seconds per frame (cloth + ray casting + writing) and disk size per preset.

Prints a table and writes benchmarks/results/scene.json. Usage: python benchmarks/scene.py [--presets ci demo]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from realityavatar.data.synthetic import build_scene, resolve_params, scene_paths


def disk_bytes(prefix: Path) -> int:
    total = 0
    for p in scene_paths(prefix).values():
        files = [p] if p.is_file() else [q for q in p.rglob("*") if q.is_file()]
        total += sum(f.stat().st_size for f in files)
    return total


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--presets", nargs="+", default=["ci", "demo"])
    ap.add_argument("--sequence", default="skirt_spin")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "scene.json"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as root:
        for preset in args.presets:
            p = resolve_params(preset, sequence=args.sequence)
            frames = p["train_frames"] + p["novel_frames"]
            t0 = time.perf_counter()
            prefix = build_scene(preset, root, seed=0, sequence=args.sequence, force=True, progress=False)
            sec = time.perf_counter() - t0
            size = disk_bytes(prefix)
            rows.append({"preset": preset, "sequence": args.sequence, "frames": frames, "cameras": p["cameras"],
                         "resolution": f"{p['width']}x{p['height']}", "images": frames * p["cameras"],
                         "seconds": round(sec, 2), "seconds_per_frame": round(sec / frames, 4),
                         "disk_mb": round(size / 2**20, 2)})
    hdr = f"{'preset':8}{'frames':>8}{'cams':>6}{'res':>10}{'total s':>10}{'s/frame':>10}{'disk MB':>10}"
    print(hdr)
    for r in rows:
        print(f"{r['preset']:8}{r['frames']:>8}{r['cameras']:>6}{r['resolution']:>10}{r['seconds']:>10.1f}"
              f"{r['seconds_per_frame']:>10.3f}{r['disk_mb']:>10.2f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "machine": platform.processor() or platform.machine(),
                               "cpus": os.cpu_count()}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
