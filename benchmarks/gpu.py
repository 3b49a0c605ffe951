"""GPU check in one command: the `gpu` tests, then renderer forward+backward for torch on CUDA, gsplat and the CPU.

    python benchmarks/gpu.py                      # pytest -m gpu, then 10k/35k Gaussians at 256²/512² -> JSON
    python benchmarks/gpu.py --skip-tests --n 10000 --size 256
    python benchmarks/gpu.py --step                # also the training step on the GPU (benchmarks/step.py --device cuda)

Writes benchmarks/results/gpu_<device>.json (gpu_cpu.json on a machine without CUDA, where the CUDA rows are
recorded as skipped with the reason). Each timing runs in a fresh process (benchmarks/render.py --child), so
peak memory is its own.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def environment() -> dict:
    """What the numbers were measured with: torch/CUDA/gsplat versions, the GPU, nvcc, gsplat's kernel status."""
    from realityavatar.render.splat import gsplat_status

    env = {"python": platform.python_version(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
           "cuda_available": torch.cuda.is_available(), "machine": platform.platform(),
           "cpu_count": os.cpu_count(), "nvcc": shutil.which("nvcc"),
           "tf32_matmul": torch.backends.cuda.matmul.allow_tf32, "tf32_cudnn": torch.backends.cudnn.allow_tf32}
    if torch.cuda.is_available():
        env["gpu"] = torch.cuda.get_device_name(0)
        env["gpu_capability"] = list(torch.cuda.get_device_capability(0))
    try:
        import gsplat

        env["gsplat"] = getattr(gsplat, "__version__", "unknown")
    except Exception as exc:  # noqa: BLE001 - record why, do not stop the benchmark
        env["gsplat"] = f"not importable: {type(exc).__name__}: {exc}"
    # loads (or JIT-builds) the kernels; 'ok' or the reason they are unusable
    env["gsplat_status"] = gsplat_status() if torch.cuda.is_available() else "not tried: no CUDA"
    return env


def run_gpu_tests(selection: list[str], timeout: int) -> dict:
    """`pytest -m gpu` on the selection; per-test outcome from its JUnit XML."""
    with tempfile.TemporaryDirectory() as d:
        xml = Path(d) / "gpu.xml"
        cmd = [sys.executable, "-m", "pytest", "-q", "-m", "gpu", "-p", "no:cacheprovider", f"--junitxml={xml}",
               *selection]
        try:
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout, check=False)
        except subprocess.TimeoutExpired:
            return {"command": " ".join(["python -m pytest -q -m gpu", *selection]), "rc": None,
                    "error": f"timed out after {timeout} s"}
        tests = []
        if xml.is_file():
            for case in ET.parse(xml).getroot().iter("testcase"):
                outcome, message = "passed", ""
                for tag in ("failure", "error", "skipped"):
                    el = case.find(tag)
                    if el is not None:
                        outcome, message = {"failure": "failed"}.get(tag, tag), el.get("message", "")[:500]
                tests.append({"test": f"{case.get('classname')}::{case.get('name')}", "outcome": outcome,
                              "seconds": float(case.get("time", 0)), "message": message})
    counts = {k: sum(t["outcome"] == k for t in tests) for k in ("passed", "failed", "error", "skipped")}
    return {"command": " ".join(["python -m pytest -q -m gpu", *selection]), "rc": p.returncode, **counts,
            "tests": tests, "tail": p.stdout[-2000:]}


def plan(ns: list[int], sizes: list[int], repeats: int, cpu_threads: int) -> tuple[list[dict], list[dict]]:
    """Configurations to time and the ones skipped here (with why)."""
    cuda = torch.cuda.is_available()
    runs, skipped = [], []
    for n in ns:
        for size in sizes:
            rows = [("cpu", "torch"), ("cuda", "torch"), ("cuda", "gsplat")]
            for dev, method in rows:
                cfg = {"n": n, "size": size, "method": method, "device": dev, "repeats": repeats,
                       "threads": cpu_threads if dev == "cpu" else 0}
                if dev == "cuda" and not cuda:
                    skipped.append({**cfg, "skipped": "no CUDA device"})
                else:
                    runs.append(cfg)
    return runs, skipped


def time_one(cfg: dict, timeout: int) -> dict:
    p = subprocess.run([sys.executable, str(HERE / "render.py"), "--child", json.dumps(cfg)], capture_output=True,
                       text=True, timeout=timeout, check=False, cwd=ROOT)
    if p.returncode != 0:
        return {**cfg, "error": p.stderr.strip().splitlines()[-1] if p.stderr.strip() else f"rc {p.returncode}"}
    return json.loads(p.stdout.strip().splitlines()[-1])


def time_step(ns: list[int], timeout: int) -> dict:
    """benchmarks/step.py --device cuda in a fresh process; its JSON, or why it did not run."""
    if not torch.cuda.is_available():
        return {"skipped": "no CUDA device"}
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "step.json"
        cmd = [sys.executable, str(HERE / "step.py"), "--device", "cuda", "--backends", "gsplat", "torch", "--size",
               "128", "--repeats", "5", "--n", *map(str, ns), "--out", str(out)]
        try:
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout, check=False)
        except subprocess.TimeoutExpired:
            return {"error": f"timed out after {timeout} s"}
        if p.returncode != 0 or not out.is_file():
            return {"error": (p.stderr.strip().splitlines() or [f"rc {p.returncode}"])[-1]}
        return json.loads(out.read_text())


def compare(rows: list[dict]) -> list[dict]:
    """Speed-ups per (N, size): torch-CUDA over CPU, gsplat over torch-CUDA (forward+backward)."""
    key = {(r["n"], r["size"], r["device"], r["method"]): r for r in rows if "forward_backward_s" in r}
    out = []
    for n, size in sorted({(r["n"], r["size"]) for r in rows}):
        cpu, tc, gs = (key.get((n, size, d, m)) for d, m in (("cpu", "torch"), ("cuda", "torch"), ("cuda", "gsplat")))
        row = {"n": n, "size": size}
        if cpu and tc:
            row["torch_cuda_vs_cpu"] = cpu["forward_backward_s"] / tc["forward_backward_s"]
        if tc and gs:
            row["gsplat_vs_torch_cuda"] = tc["forward_backward_s"] / gs["forward_backward_s"]
            row["gsplat_backend_used"] = gs.get("backend")
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[10000, 35000])
    ap.add_argument("--size", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cpu-threads", type=int, default=0, help="torch threads for the CPU rows (0: torch default)")
    ap.add_argument("--skip-tests", action="store_true", help="timings only")
    ap.add_argument("--step", type=int, nargs="*", default=None, metavar="N",
                    help="also time the training step on the GPU (benchmarks/step.py --device cuda, 128², gsplat and "
                         "torch) at these Gaussian counts (default with the flag alone: 7000)")
    ap.add_argument("--tests", nargs="*", default=["tests"], help="what pytest -m gpu collects")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per subprocess")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/gpu_<device>.json)")
    a = ap.parse_args(argv)

    env = environment()
    result: dict = {"command": " ".join(["python", "benchmarks/gpu.py", *(sys.argv[1:] if argv is None else argv)]),
                    "environment": env}
    if not a.skip_tests:
        print("running pytest -m gpu ...", file=sys.stderr)
        result["pytest_gpu"] = run_gpu_tests(a.tests, a.timeout)
        t = result["pytest_gpu"]
        print(f"  gpu tests: {t.get('passed', 0)} passed, {t.get('failed', 0)} failed, {t.get('error', 0)} errors, "
              f"{t.get('skipped', 0)} skipped (rc {t.get('rc')})", file=sys.stderr)
    runs, skipped = plan(a.n, a.size, a.repeats, a.cpu_threads)
    rows = []
    for cfg in runs:
        r = time_one(cfg, a.timeout)
        rows.append(r)
        msg = f"fwd+bwd {r['forward_backward_s']:.4f}s" if "forward_backward_s" in r else f"error: {r['error']}"
        print(f"  {cfg['device']:4s} {cfg['method']:6s} N={cfg['n']:6d} {cfg['size']}²  {msg}", file=sys.stderr)
    result["render"] = rows
    result["render_skipped"] = skipped
    result["speedups"] = compare(rows)
    if a.step is not None:
        result["step"] = time_step(a.step or [7000], a.timeout)
        for r in result["step"].get("results", []):
            print(f"  step {r['device']} {r['backend']:6s} N={r['n']} {r['size']}²: {r['step_s']:.4f}s, GPU kernels "
                  f"{r['gpu_kernel_s']:.4f}s", file=sys.stderr)

    lines = ["| device | backend | N | image | forward s | fwd+bwd s | peak MB |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "forward_backward_s" in r:
            lines.append(f"| {r['device']} | {r.get('backend', r['method'])} | {r['n']} | {r['size']}² | "
                         f"{r['forward_s']:.4f} | {r['forward_backward_s']:.4f} | {r['peak_mem_mb']:.0f} |")
    for r in skipped:
        lines.append(f"| {r['device']} | {r['method']} | {r['n']} | {r['size']}² | skipped: {r['skipped']} | | |")
    print("\n".join(lines))
    device = "cuda" if torch.cuda.is_available() else "cpu"
    out = Path(a.out or HERE / "results" / f"gpu_{device}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")
    failed = result.get("pytest_gpu", {}).get("failed", 0) + result.get("pytest_gpu", {}).get("error", 0)
    return 1 if failed or any("error" in r for r in rows) or "error" in result.get("step", {}) else 0


if __name__ == "__main__":
    raise SystemExit(main())
