"""benchmarks/: the one-command GPU benchmark and the training-step benchmark's CUDA refusal (and run, on a GPU)."""

from __future__ import annotations

import json
import sys

import pytest
import torch

from tests.helpers import ROOT, benchmark


def test_gpu_benchmark_runs_and_skips_cuda_cleanly(tmp_path):
    gpu = benchmark("gpu")

    out = tmp_path / "gpu.json"
    rc = gpu.main(["--n", "300", "--size", "32", "--repeats", "1", "--out", str(out), "--step", "1000",
                   "--tests", "tests/render/test_gsplat.py::test_torch_backend_forward_and_backward_on_cuda_match_cpu"])
    res = json.loads(out.read_text())
    assert rc == 0 and res["environment"]["cuda_available"] == torch.cuda.is_available()
    assert res["pytest_gpu"]["rc"] == 0 and len(res["pytest_gpu"]["tests"]) == 1
    timed = {(r["device"], r["method"]) for r in res["render"] if "forward_backward_s" in r}
    assert ("cpu", "torch") in timed
    if not torch.cuda.is_available():
        assert {(r["device"], r["method"]) for r in res["render_skipped"]} == {("cuda", "torch"), ("cuda", "gsplat")}
        assert res["pytest_gpu"]["skipped"] == 1
        assert res["step"] == {"skipped": "no CUDA device"}
    else:
        assert {("cuda", "torch"), ("cuda", "gsplat")} <= timed
        assert {r["backend"] for r in res["step"]["results"]} == {"gsplat", "torch"}


def _step_bench(tmp_path, *args):
    import subprocess

    out = tmp_path / "step.json"
    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "step.py"), *args, "--n", "2000", "--size", "64",
                        "--repeats", "1", "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600,
                       check=False)
    return p, out


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal without CUDA")
def test_step_benchmark_refuses_cuda_without_it(tmp_path):
    p, out = _step_bench(tmp_path, "--device", "cuda", "--backends", "torch")
    assert p.returncode != 0 and "--device cuda: CUDA is not available" in p.stderr and not out.exists()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_step_benchmark_on_cuda(tmp_path):
    """benchmarks/step.py --device cuda: the whole step and its parts on the GPU, with the kernels' own time."""
    p, out = _step_bench(tmp_path, "--device", "cuda", "--backends", "gsplat", "torch")
    assert p.returncode == 0, p.stderr[-2000:]
    rows = json.loads(out.read_text())["results"]
    assert {r["backend"] for r in rows} == {"gsplat", "torch"}
    for r in rows:
        assert r["device"] == "cuda" and r["step_s"] > 0 and r["gpu_kernel_s"] > 0
