"""benchmarks/: the one-command GPU benchmark, the training-step benchmark (on the CPU, its CUDA refusal, on a GPU)."""

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
        assert r["n"] == 2000 and r["size"] == 64  # the row's own settings, not the profiled step count


def test_lpips_check_needs_the_lpips_package(capsys):
    """Without lpips (as here: tests/conftest.py hides any installed one) the cross-check says so and exits 2."""
    assert benchmark("lpips_check").main(["--device", "cpu"]) == 2
    assert "the lpips package does not import here" in capsys.readouterr().err


@pytest.mark.parametrize("scale", [1.0, 1.01])
def test_lpips_check_compares_with_the_package(tmp_path, monkeypatch, scale):
    """A stand-in lpips package whose LPIPS is ours on the same found files, times `scale`: the check reads the
    package's lin file and torch's hub cache and reports the difference (0, then 1%)."""
    import types
    from pathlib import Path

    from realityavatar.metrics import LPIPS
    from tests.helpers import plant_found_weights

    found = plant_found_weights(tmp_path, monkeypatch)

    class PackageLike(torch.nn.Module):  # lpips.LPIPS's interface: [B,3,H,W] in [-1,1] -> [B,1,1,1]
        def __init__(self, net="alex", verbose=True):
            super().__init__()
            self.ours = LPIPS(net, found["vgg16"], found["lin"])

        def forward(self, in0, in1):
            x, y = ((t + 1) / 2 for t in (in0, in1))
            return scale * self.ours(x.permute(0, 2, 3, 1), y.permute(0, 2, 3, 1)).view(-1, 1, 1, 1)

    fake = types.ModuleType("lpips")
    fake.LPIPS, fake.__file__ = PackageLike, str(Path(found["lin"]).parents[2] / "__init__.py")
    monkeypatch.setitem(sys.modules, "lpips", fake)
    out = tmp_path / "check.json"
    assert benchmark("lpips_check").main(["--device", "cpu", "--sizes", "32", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["weights"] == {"lin": found["lin"], "backbone": found["vgg16"]}
    assert [r["pair"] for r in res["pairs"]][-1] == "thin_box_12x40" and len(res["pairs"]) == 7
    assert res["max_rel_diff"] == pytest.approx(1 - 1 / scale, abs=1e-5)  # relative to the package
    assert all(r["lpips_package"] > 0 for r in res["pairs"] if not r["pair"].endswith("same"))


def test_device_script_trains_configs_that_compose():
    """benchmarks/device.sh's training stages name configs that compose: a GPU session has minutes, not enough to
    find a wrong override there."""
    import re
    import shlex

    from realityavatar.config import compose

    text = (ROOT / "benchmarks" / "device.sh").read_text().replace("\\\n", " ")  # continuation lines joined
    text = text.replace('"${RESUME[@]}"', "resume=true").replace("${COMPILE:+compile=$COMPILE}", "compile=reduce-overhead")
    text = text.replace("${PAPER_ARGS:-}", "data.num_workers=2")  # the header's example
    calls = re.findall(r'^\s*run_train "\$\w+" "\$WORK/\w+" (?:\$\(\(.*?\)\)|\S+) (.+)$', text, re.MULTILINE)
    assert len(calls) == 3, calls
    for overrides in calls:
        cfg = compose(shlex.split(overrides.replace("$MAXT", "00:00:04:00")))
        assert cfg.trainer.accelerator == "gpu" or "paper_scale" in overrides
    assert compose(shlex.split(calls[0])).data.image_scale == 0.5  # the sweep scene: 128 px
    assert compose(shlex.split(calls[2].replace("$MAXT", "00:00:04:00"))).trainer.max_time == "00:00:04:00"
    # the scenes built while the gpu tests run are the ones the sweep and paper_scale trainings read
    built = re.findall(r'SCENES\+=\("([^"]+)"\)', text)
    assert len(built) == 2, built
    scene = ("root", "sequence", "build_preset", "build_sequence", "build_seed", "build_overrides")
    for pre, train in zip(sorted(built, key=lambda b: "sweep" not in b), (calls[0], calls[2])):
        a, b = compose(pre.split()).data, compose(shlex.split(train.replace("$MAXT", "00:00:04:00"))).data
        assert [a.get(k) for k in scene] == [b.get(k) for k in scene], (pre, train)


def test_step_benchmark_on_the_cpu_counts_and_profiles(tmp_path, monkeypatch, capsys):
    """benchmarks/step.py on the CPU: the step and its parts, tensor operations and host syncs counted (none between
    log steps), and --profile's list of the operations that take the most time."""
    out = tmp_path / "step.json"
    monkeypatch.setattr(sys, "argv", ["step.py", "--backends", "numba", "--profile", "5", "--n", "2000", "--size", "64",
                                      "--repeats", "1", "--no-tune-malloc", "--out", str(out), "--override",
                                      "skinning.voxel_size=0.1", "shading.voxel_size=0.1"])  # small grids: quick
    benchmark("step").main()
    (row,) = json.loads(out.read_text())["results"]
    parts = row["parts_s"]  # timed inside training_step: every part ran, and they add up to no more than a step
    assert row["step_s"] > 0 and list(parts) == list(benchmark("step").PARTS) and all(v > 0 for v in parts.values())
    # the best of the repeats beside the medians (a shared machine's other tenants only add time)
    assert 0 < row["step_min_s"] <= row["step_s"] and 0 < row["gemm_unit_min_s"] <= row["gemm_unit_s"]
    assert row["ops_per_step"] > 100 and row["scalar_reads_per_step"] == 0 and row["data_dependent_per_step"] == 0
    # the profile's launch count of an eager step: OpCount's operations, less those run inside another (~5 %)
    assert 0.8 * row["ops_per_step"] < row["cpu_launches_per_step"] <= row["ops_per_step"]
    top = row["top_ops_time"]
    assert len(top) == 5 and all(t["ms_per_step"] > 0 and t["calls_per_step"] > 0 for t in top)
    assert [t["ms_per_step"] for t in top] == sorted((t["ms_per_step"] for t in top), reverse=True)
    assert "ms  x" in capsys.readouterr().out


def test_step_benchmark_times_one_model_state():
    """The timed steps do not train: learning rates 0, so every row and repeat sees the initial model (steps towards
    random targets drifted it, and a later row's rasterizer had more to draw). Whole and in parts, they are the
    module's training_step."""
    from realityavatar.data.random_batch import make_batch_fn

    step = benchmark("step")
    cfg, module, opt, sched = step.build(500, "numba", ["skinning.voxel_size=0.1", "shading.voxel_size=0.1"])
    make = make_batch_fn(module.avatar.body, 32, int(cfg.data.window_len))
    s = step.timed_step(cfg)
    step._stub_trainer_hooks(module, opt, sched, s)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    steps = []
    real = type(module).training_step
    type(module).training_step = lambda self, *a: (steps.append(1), real(self, *a))[1]
    try:
        for _ in range(3):
            step.step_whole(module, opt, sched, make, s)
            parts = step.step_parts(module, opt, sched, make, s)
    finally:
        type(module).training_step = real
    assert all(torch.equal(before[k], v) for k, v in module.state_dict().items() if k in before)
    # the parts are timed inside training_step itself (one call each), its callables put back afterwards
    assert len(steps) == 6 and all(v > 0 for v in parts.values()), parts
    assert "deform" not in vars(module.avatar) and "loss" not in vars(module) and "step" not in vars(module.density)


def test_step_benchmark_times_the_demo_models_sliding_sheet():
    """`make demo`'s sheet (sheet=skirt_slide) is sized by the training frames, which the benchmark's synthetic batches
    have none of: the benchmark gives it frames that all slide, and a timed step reads the slid texture."""
    from realityavatar.data.random_batch import make_batch_fn

    step = benchmark("step")
    cfg, module, opt, sched = step.build(500, "numba", ["sheet=skirt_slide", "sheet.rows=4", "sheet.cols=12",
                                                        "skinning.voxel_size=0.1", "shading.voxel_size=0.1"])
    sheet = module.avatar.sheet
    assert sheet.live.shape == (100,) and bool(sheet.live.all()) and sheet.slide.shape == (100, 5)
    assert any(p is sheet.slide for g in opt.param_groups for p in g["params"])  # trained as in a run (rate 0 here)
    make = make_batch_fn(module.avatar.body, 32, int(cfg.data.window_len))
    s = step.timed_step(cfg)
    step._stub_trainer_hooks(module, opt, sched, s)
    step.step_whole(module, opt, sched, make, s)
    assert sheet.slide.grad is not None and bool(sheet.slide.grad.abs().sum() > 0)  # the slid texture was read


def test_step_benchmark_profiles_the_compiled_networks(tmp_path, monkeypatch):
    """--compile: the profiled steps run the compiled networks (a TorchDispatchMode count before them made dynamo run
    them eagerly from then on), and no eager count is reported as theirs. Dynamo with the aot_eager backend (no C++
    compiler, seconds) stands in for inductor: the same graphs, which the profile shows as CompiledFunction."""
    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda f, mode=None: compile_(f, backend="aot_eager"))
    from realityavatar.model.module import DYNAMO_CONFIG

    saved = {k: getattr(torch._dynamo.config, k) for k in DYNAMO_CONFIG}  # compile_path sets them process-wide
    out = tmp_path / "step.json"
    monkeypatch.setattr(sys, "argv", ["step.py", "--backends", "numba", "--profile", "300", "--n", "500", "--size", "32",
                                      "--repeats", "1", "--no-tune-malloc", "--out", str(out), "--compile", "default",
                                      "--override", "skinning.voxel_size=0.1", "shading.voxel_size=0.1"])
    with torch._dynamo.config.patch(**saved):  # put back after the run
        benchmark("step").main()
    (row,) = json.loads(out.read_text())["results"]
    assert any("CompiledFunction" in t["op"] for t in row["top_ops_time"]), [t["op"] for t in row["top_ops_time"]]
    assert row["ops_per_step"] is None and row["cpu_launches_per_step"] > 100  # the profile counts it


def test_loader_benchmark_times_the_main_process(scenes_root, tmp_path):
    """benchmarks/loader.py: per loader-worker count, and with the training set kept on the device, the training
    process's time per batch after one epoch."""
    out = tmp_path / "loader.json"
    assert benchmark("loader").main(["data=synthetic_ci", "--workers", "0", "--device-cache", "--batches", "3",
                                     "--pause", "0", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert [(r["workers"], r["device_cache"]) for r in res["results"]] == [(0, False), (0, True)]
    for row in res["results"]:
        assert row["batches"] == 3 and 0 < row["median_ms"] < 1000 and 0 < row["composite_ms"] < 1000
    assert res["meta"]["overrides"] == "data=synthetic_ci" and "--workers 0" in res["meta"]["command"]


def test_step_benchmark_names_where_syncs_come_from():
    """A GPU row's sync_sources: each synchronisation or device-to-host copy of a profile, named by the operations
    that issued it (innermost first), counted per step."""
    from types import SimpleNamespace as E

    step = benchmark("step")
    item = E(name="aten::_local_scalar_dense", cpu_parent=E(name="aten::item", cpu_parent=E(name="isect_tiles", cpu_parent=None)))
    events = [E(name="cudaStreamSynchronize", cpu_parent=item), E(name="Memcpy DtoH (Device -> Pageable)", cpu_parent=item),
              E(name="cudaStreamSynchronize", cpu_parent=item), E(name="cudaLaunchKernel", cpu_parent=item),
              E(name="cudaDeviceSynchronize", cpu_parent=None)]
    assert step.sync_sources(events, steps=2) == {
        "cudaStreamSynchronize < aten::_local_scalar_dense < aten::item < isect_tiles": 1.0,
        "Memcpy DtoH (Device -> Pageable) < aten::_local_scalar_dense < aten::item < isect_tiles": 0.5,
        "cudaDeviceSynchronize < (top level)": 0.5}
