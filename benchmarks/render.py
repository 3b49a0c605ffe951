"""Renderer benchmark: torch and numba backends (gsplat on CUDA) vs the dense reference on a human-sized scene.

Prints a table and writes JSON. Each configuration runs in a fresh subprocess so peak memory (ru_maxrss) is its own.
Each configuration also times the GEMM unit (8 float32 matmuls of 1024^3) in its process: on a shared CPU the ratio
to it is steadier than the seconds. numba's one-time compile/cache-load time is reported per process.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from realityavatar.render.reference import human_scene  # the renderer tests' scene

_loadavg_before: list = []


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _current_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


_clock = time.perf_counter  # --clock cpu: time.process_time (CPU seconds of this process)


def _time(fn, repeats: int, device: str, warmup: bool = True) -> float:
    if warmup:
        fn()
    _sync(device)
    best = []
    for _ in range(repeats):
        t0 = _clock()
        fn()
        _sync(device)
        best.append(_clock() - t0)
    return float(sorted(best)[len(best) // 2])  # median


def _gemm_unit(device: str) -> float:
    """The reference workload: 8 float32 matmuls of 1024^3 (median of 3), on this process's threads."""
    a, b = torch.randn(1024, 1024, device=device), torch.randn(1024, 1024, device=device)

    def gemm():
        for _ in range(8):
            a @ b

    return _time(gemm, 3, device)


def run_one(cfg: dict) -> dict:
    """One configuration (in its own process): forward and forward+backward seconds, peak memory."""
    from realityavatar.render import rasterize
    from realityavatar.render.project import project_gaussians
    from realityavatar.render.reference import composite_dense_rows, pixel_centres, rasterize_reference

    global _clock
    _clock = time.process_time if cfg.get("clock") == "cpu" else time.perf_counter
    torch.set_num_threads(cfg["threads"]) if cfg["threads"] else None
    dev, n, size, method = cfg["device"], cfg["n"], cfg["size"], cfg["method"]
    jit_s = None
    if method == "numba":
        from realityavatar.render.numba_backend import warm_up

        jit_s = warm_up()  # compiles on the first run on a machine, loads numba's cache afterwards
    args = human_scene(n, size, device=dev)
    params = [t.requires_grad_() for t in args[:5]]
    cams = args[5:]
    gout = torch.rand(1, size, size, 3, device=dev)
    if dev == "cuda":
        torch.cuda.reset_peak_memory_stats()
    base = _current_rss_mb()

    if method == "dense":
        def render():
            return rasterize_reference(*params, *cams, size, size, method="matrix", pixel_chunk=cfg["pixel_chunk"])
    else:
        def render():
            return rasterize(*params, *cams, size, size, backend=method, **cfg.get("options", {}))

    def fwd():
        with torch.no_grad():
            render()

    def fwd_bwd():
        if method == "dense":
            # backward a chunk of pixels at a time: the whole [HW,N] graph would not fit in memory
            proj = project_gaussians(*params[:4], *cams, size, size, 0.01, 1e10)
            order = torch.argsort(proj.depths[0])
            g = [proj.means2d[0][order], proj.conics[0][order], proj.opacities[0][order], params[4][order],
                 proj.visible[0][order]]
            pix = pixel_centres(size, size, dev, torch.float32)
            go = gout.reshape(-1, 3)
            for s in range(0, pix.shape[0], cfg["pixel_chunk"]):
                img, _ = composite_dense_rows(*g, pix[s : s + cfg["pixel_chunk"]])
                (img * go[s : s + cfg["pixel_chunk"]]).sum().backward(retain_graph=True)
        else:
            img = render()[0]
            (img * gout).sum().backward()
        for p in params:
            p.grad = None

    with torch.no_grad():  # a full dense graph would not fit in memory
        img, alpha, meta = render()
    info: dict = {}
    if method != "dense":
        info = {k: meta[k] for k in ("tile_pairs", "padded_elements", "n_chunks", "backend") if k in meta}
        info["visible"] = int(meta["visible"].sum())
        info["coverage"] = float((alpha > 0.5).float().mean())
    del img, alpha, meta
    warm = method != "dense"  # the dense reference takes minutes; its one run is already warm
    t_f = _time(fwd, cfg["repeats"], dev, warm)
    t_fb = _time(fwd_bwd, cfg["repeats"], dev, warm)
    res = dict(cfg, forward_s=t_f, forward_backward_s=t_fb, **info)
    res["gemm_unit_s"] = _gemm_unit(dev)
    if jit_s is not None:
        res["numba_compile_or_cache_load_s"] = jit_s
    if dev == "cuda":
        res["peak_mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
        res["peak_mem_kind"] = "cuda max_memory_allocated"
    else:
        res["peak_mem_mb"] = _rss_mb()
        res["peak_mem_above_start_mb"] = _rss_mb() - base
        res["peak_mem_kind"] = "process peak RSS"
    return res


def _child(cfg_json: str) -> None:
    print(json.dumps(run_one(json.loads(cfg_json))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, nargs="+", default=[5000, 10000, 35000])
    ap.add_argument("--size", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--backends", nargs="+", default=None, help="default: torch and numba (torch and gsplat on CUDA)")
    ap.add_argument("--dense", nargs="*", default=["10000x256", "5000x128"],
                    help="NxSIZE configurations also timed with the dense reference (slow); none with --dense")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="cpu: process CPU seconds, steadier than wall time on a shared CPU (only with --threads 1)")
    ap.add_argument("--quick", action="store_true", help="10k at 256^2 only, dense reference included")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/render_<device>.json)")
    a = ap.parse_args()
    if a.quick:
        a.n, a.size, a.repeats = [10000], [256], 3
    backends = a.backends or (["torch", "gsplat"] if a.device == "cuda" else ["torch", "numba"])
    runs = []
    for n in a.n:
        for size in a.size:
            for m in backends:
                runs.append({"n": n, "size": size, "method": m, "device": a.device, "repeats": a.repeats,
                             "threads": a.threads, "clock": a.clock})
            if f"{n}x{size}" in (a.dense or []):
                runs.append({"n": n, "size": size, "method": "dense", "device": a.device, "repeats": 1,
                             "threads": a.threads, "pixel_chunk": 1024, "clock": a.clock})
    global _loadavg_before
    _loadavg_before = list(__import__("os").getloadavg())  # the machine is shared: record how busy it was
    results = []
    for cfg in runs:
        p = subprocess.run([sys.executable, __file__, "--child", json.dumps(cfg)], capture_output=True, text=True, check=False)
        if p.returncode != 0:
            print(p.stderr, file=sys.stderr)
            raise SystemExit(f"benchmarks/render.py: configuration {cfg} failed")
        r = json.loads(p.stdout.strip().splitlines()[-1])
        results.append(r)
        print(f"  done {r['method']:6s} N={r['n']:6d} {r['size']}^2  fwd+bwd {r['forward_backward_s']:.3f}s",
              file=sys.stderr)
    # speed-up of torch over dense where both ran
    for r in results:
        if r["method"] == "dense":
            for t in results:
                if t["method"] in ("torch", "numba") and (t["n"], t["size"]) == (r["n"], r["size"]):
                    t["speedup_vs_dense_fwd"] = r["forward_s"] / t["forward_s"]
                    t["speedup_vs_dense_fwd_bwd"] = r["forward_backward_s"] / t["forward_backward_s"]
    hdr = ("| backend | N | image | forward s | fwd+bwd s | fwd+bwd GEMM units | peak MB | vs dense (fwd+bwd) | "
           "tile pairs | chunks |")
    lines = [hdr, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        sp = f"{r['speedup_vs_dense_fwd_bwd']:.0f}x" if "speedup_vs_dense_fwd_bwd" in r else ""
        lines.append(
            f"| {r['method']} | {r['n']} | {r['size']}² | {r['forward_s']:.3f} | {r['forward_backward_s']:.3f} | "
            f"{r['forward_backward_s'] / r['gemm_unit_s']:.3f} | "
            f"{r['peak_mem_mb']:.0f} | {sp} | {r.get('tile_pairs', '')} | {r.get('n_chunks', '')} |"
        )
    print("\n".join(lines))
    out = Path(a.out or Path(__file__).parent / "results" / f"render_{a.device}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "torch": torch.__version__,
        "threads": torch.get_num_threads() if not a.threads else a.threads,
        "clock": a.clock,
        "machine": platform.platform(),
        "load_average_before": _loadavg_before,
        "load_average_after": list(__import__("os").getloadavg()),
        "cpu": platform.processor() or platform.machine(),
        "device": a.device if a.device == "cpu" else torch.cuda.get_device_name(0),
        "note": "median of repeats; GEMM units = seconds / (8 float32 1024^3 matmuls timed in the same process); peak memory is the process peak RSS on CPU (includes ~torch itself) and "
                "torch.cuda.max_memory_allocated on CUDA; dense = every Gaussian x every pixel, float32, "
                "1024-pixel chunks",
    }
    out.write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        _child(sys.argv[2])
    else:
        mp.freeze_support()
        main()
