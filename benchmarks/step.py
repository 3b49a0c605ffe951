"""One full training step of the demo model and its parts (data, networks, render, losses, optimizer, density).

python benchmarks/step.py [--n 10000 35000] [--size 128 256 512] [--backends torch numba] [--threads 1] [--clock cpu]
                          [--views 1 4] [--device cuda]
`--n 2000 --size 256 --override +experiment=demo` times `make demo`'s model (its garment sheet's texture slid in every
step, as on a turning training frame).
Every time is printed beside its ratio to the GEMM unit (8 float32 matmuls of 1024^3) timed in the same process,
because the project's CPU is shared and absolute seconds drift with the load. Writes benchmarks/results/step_cpu.json.

"step" is module.training_step itself (one backward; optimizers and logging stubbed, no Trainer), with learning rates 0
so that every timed step sees the same, initial model. The parts are timed inside that same training_step, where it
calls them: data (the batch) -> networks fwd (the avatar's deform and shade) -> render fwd (its splat) -> losses fwd
(module.loss: every term the run trains with) -> backward (one, through losses, render and networks) -> optimizer
(its step and the LR schedule's) -> density (control after the backward); `other` is the rest of the step (gradient
clipping, bookkeeping).
The body grids are built as training builds them (skinning weights, shading normals: ~171k voxels for the
mannequin). Data is a synthetic batch (realityavatar.data.random_batch: one of 4 random pose windows with their pose
inputs, one camera framing the body, a random target image: each made once, as the dataset caches them) built the way
the DataModule collates one.
--views V adds the whole step of a batch of V images (data.views_per_step=V): the same pose
window seen by V cameras around the body, the networks run once for them; its parts are not split out.
--device cuda runs the module and its batches on the GPU (backends `gsplat torch` there); every clock reading waits
for the GPU first (torch.cuda.synchronize), and each row also records the GPU kernels' own time per step
(`gpu_kernel_s`, from torch.profiler over 3 whole steps): a step far longer than its kernels waits on Python and
kernel launches, not on the GPU, with the kernel launches and stream syncs it counts.
On any device each row also counts the tensor operations of one whole step and the host syncs among them (scalar
reads, data-dependent output sizes), with a TorchDispatchMode: the launches and waits a GPU step would make,
measurable on a CPU. On a CPU each row also counts launches per step from a profile (`cpu_launches_per_step`:
inductor's fused kernels plus the outermost computing ATen operations), which also counts a compiled step: what
--compile's fusion leaves for a GPU to launch.
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path

import torch

_clock_base = time.perf_counter  # --clock cpu: time.process_time
_device = "cpu"


def _clock() -> float:
    if _device != "cpu":
        torch.cuda.synchronize()
    return _clock_base()

PARTS = ("data", "networks_fwd", "render_fwd", "losses_fwd", "backward", "optimizer", "density", "other")


def gemm_unit(repeats: int = 5) -> list[float]:
    """Seconds for 8 float32 matmuls of 1024^3, each of `repeats` times: the issue's reference workload."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(1024, 1024, generator=g), torch.randn(1024, 1024, generator=g)
    a @ b
    times = []
    for _ in range(repeats):
        t = _clock()
        for _ in range(8):
            a @ b
        times.append(_clock() - t)
    return times


def build(n: int, backend: str, overrides: list[str]):
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from realityavatar.build import build_module
    from realityavatar.config import config_dir
    from realityavatar.model.sheet import SlidingSheet

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose("train", overrides=[f"gaussians.num_points={n}", f"render.backend={backend}", "iterations=2000",
                                          "out_dir=/tmp/realityavatar_step_bench", *overrides])
    body = instantiate(cfg.body)
    frames = 100  # training frames the module is sized for (the colour's per-frame latents, the sliding sheet's angles)
    module = build_module(cfg, body, num_train_frames=frames, scene_extent=1.0)
    sheet = module.avatar.sheet
    if isinstance(sheet, SlidingSheet):  # sheet=skirt_slide (make demo's) is sized by the training data, which the
        # synthetic batches have none of: frames that all slide, so every step reads the slid texture as a training
        # step on a turning frame does
        sheet.live = torch.ones(frames)
        sheet.slide = torch.nn.Parameter(torch.zeros(frames, sheet.rows + 1))
    opt_cfg = module.configure_optimizers()
    # the body grids (skinning weights, shading normals) at their real resolution, as training builds them once
    # before step 0 (AvatarModule.on_fit_start): a grid lookup's cost depends on the grid's size
    module.on_fit_start()
    module.to(_device)
    opt, sched = opt_cfg["optimizer"], opt_cfg["lr_scheduler"]["scheduler"]
    # Learning rates 0 (Adam does the same arithmetic): every timed step sees the initial model. Steps towards random
    # target images drift it, and a four-camera step at 7k / 256² grew from 0.25 to 0.43 s over 20 such steps.
    for g in opt.param_groups:
        g["lr"] = 0.0
    sched.base_lrs = [0.0] * len(opt.param_groups)
    return cfg, module, opt, sched


def step_parts(module, opt, sched, make_batch, step: int) -> dict:
    """One module.training_step, timed in parts where it calls them (each callable wrapped with a clock for this step,
    then restored); seconds per part, `other` the rest of the step."""
    t = dict.fromkeys(PARTS, 0.0)

    def timed(part, f):
        @functools.wraps(f)  # keeps what the LR scheduler marks on the optimizer's step
        def call(*args, **kwargs):
            t0 = _clock()
            out = f(*args, **kwargs)
            t[part] += _clock() - t0
            return out
        return call

    a = module.avatar
    wrap = [(a, "deform", "networks_fwd"), (a, "shade", "networks_fwd"), (a, "splat", "render_fwd"),
            (module, "loss", "losses_fwd"), (module, "manual_backward", "backward"), (opt, "step", "optimizer"),
            (sched, "step", "optimizer"), (module.density, "step_post_backward", "density")]
    own = [(obj, name, obj.__dict__.get(name)) for obj, name, _ in wrap]  # instance attributes (compiled, patched)
    for obj, name, part in wrap:
        setattr(obj, name, timed(part, getattr(obj, name)))
    try:
        t0 = _clock()
        batch = make_batch()
        t["data"] = _clock() - t0
        t0 = _clock()
        module.training_step(batch, 0)
        whole = _clock() - t0
    finally:
        for obj, name, before in own:
            if before is None:
                delattr(obj, name)
            else:
                setattr(obj, name, before)
    t["other"] = whole - sum(v for k, v in t.items() if k not in ("data", "other"))
    return t


def step_whole(module, opt, sched, make_batch, step: int) -> float:
    """module.training_step itself (one backward), with the trainer's hooks stubbed: optimizers, logging."""
    t0 = _clock()
    module.training_step(make_batch(), 0)
    return _clock() - t0


def _stub_trainer_hooks(module, opt, sched, step: int) -> None:
    module.optimizers = lambda: opt
    module.lr_schedulers = lambda: sched
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *args, **kwargs: None
    module.log_every = LOG_EVERY
    # No trainer: the step the schedule sees, on a subclass of this module's own (setting it on AvatarModule itself
    # pinned every later module's global_step in the process, and a training run there never reached its stop step).
    module.__class__ = type(type(module).__name__, (type(module),), {"global_step": property(lambda self: step)})


LOG_EVERY = 25  # conf/trainer: log_every_n_steps; the timed and counted step is not a log step
PROFILED_STEPS = 3  # whole steps under torch.profiler (GPU kernel time and calls, --profile)


def count_ops(module, opt, sched, make_batch, step: int, steps: int = 3) -> dict:
    """Tensor operations per whole training step and the host syncs among them (realityavatar.runtime.OpCount)."""
    from realityavatar.runtime import DATA_DEPENDENT, OpCount

    batches = [make_batch() for _ in range(steps)]  # drawn outside the count: the DataModule's part, not the model's
    with OpCount() as c:
        for batch in batches:
            module.training_step(batch, 0)
    per = {k: v / steps for k, v in c.ops.items()}
    return {"ops_per_step": c.total / steps,
            "scalar_reads_per_step": per.get("_local_scalar_dense", 0.0),
            "data_dependent_per_step": sum(per.get(k, 0.0) for k in DATA_DEPENDENT),
            "top_ops": dict(sorted(per.items(), key=lambda kv: -kv[1])[:15])}


def profile_steps(module, opt, sched, make_batch, step: int, shapes: bool = False):
    """torch.profiler over PROFILED_STEPS whole steps (the GPU's kernels too on a GPU; input shapes with `shapes`)."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if _device != "cpu" else [])
    with profile(activities=acts, record_shapes=shapes) as prof:
        for _ in range(PROFILED_STEPS):
            module.training_step(make_batch(), 0)  # no clock: its torch.cuda.synchronize is not the step's
    return prof


# ATen operations that launch no kernel: views, metadata (OpCount's, runtime._METADATA), scalar reads (counted apart,
# as host syncs), allocations. By name: a profile records no `is_view`, which OpCount uses.
_NO_LAUNCH = {"view", "as_strided", "reshape", "_reshape_alias", "expand", "expand_as", "view_as", "unsqueeze",
              "squeeze", "select", "slice", "narrow", "t", "transpose", "permute", "movedim", "unbind", "split",
              "split_with_sizes", "chunk", "flatten", "unflatten", "resolve_conj", "resolve_neg", "contiguous", "to",
              "empty", "empty_strided", "empty_like", "item", "_local_scalar_dense", "is_nonzero", "numpy_T"}


def launches_per_step(prof) -> float:
    """Kernel launches per step that a GPU would make, counted in a CPU profile of PROFILED_STEPS whole steps:
    inductor's fused C++ kernels (with `torch._inductor.config.cpp.enable_kernel_profile`; each stands for one Triton
    kernel on a GPU) plus the outermost ATen operations that compute (an operation run inside another is part of that
    one's launch). It counts eager and compiled steps alike: OpCount cannot count a compiled step (dynamo runs
    eagerly under a TorchDispatchMode)."""
    from realityavatar.runtime import _METADATA

    no_launch = _NO_LAUNCH | set(_METADATA)

    def outermost(e) -> bool:
        return not (e.cpu_parent is not None and e.cpu_parent.name.startswith("aten::"))

    return sum("cpp_fused" in e.name or (e.name.startswith("aten::") and e.name[6:] not in no_launch and outermost(e))
               for e in prof.events()) / PROFILED_STEPS


def sync_sources(events, steps: int, k: int = 10) -> dict[str, float]:
    """Where a profile's host waits come from, per step: each CUDA synchronisation (cudaStreamSynchronize and the like)
    or device-to-host copy named by the chain of operations that issued it (innermost first, up to 3), the k most
    frequent."""
    from collections import Counter

    found: Counter = Counter()
    for e in events:
        if "Synchronize" in e.name or e.name.startswith("Memcpy DtoH"):
            chain, p = [], getattr(e, "cpu_parent", None)
            while p is not None and len(chain) < 3:
                chain.append(p.name)
                p = getattr(p, "cpu_parent", None)
            found[f"{e.name} < {' < '.join(chain) or '(top level)'}"] += 1
    return {key: n / steps for key, n in found.most_common(k)}


def top_ops(prof, k: int) -> list[dict]:
    """The k operations of a `profile_steps(shapes=True)` profile that take the most time (grouped by operation and
    input shapes; on a GPU by the time of their kernels): where a step's time goes, per step."""
    events = prof.key_averages(group_by_input_shape=True)
    key = "self_cpu_time_total" if _device == "cpu" else next(  # torch < 2.4 names the device time cuda
        n for n in ("self_device_time_total", "self_cuda_time_total") if events and hasattr(events[0], n))
    rows = sorted(events, key=lambda e: -getattr(e, key))[:k]
    n = PROFILED_STEPS
    return [{"op": e.key, "shapes": str(e.input_shapes)[:120], "calls_per_step": e.count / n,
             "ms_per_step": getattr(e, key) / 1e3 / n} for e in rows]


def timed_step(cfg) -> int:
    """The global step every timed step runs as: the motion-trend decoder on, not a densification step, nor a log
    step (module.training_step reads the device on those only)."""
    step = max(int(cfg.schedule.deform_start), 1) + 1
    return step + ((step + 1) % LOG_EVERY == 0)


def run_config(n: int, size: int, backend: str, repeats: int, overrides: list[str], views=(1,),
               compile_mode: str = "none", profile_top: int = 0) -> dict:
    torch.manual_seed(0)
    if compile_mode != "none":  # compile_stats: this row's graphs, not the process's so far
        from torch._dynamo.utils import counters

        counters.clear()
    from realityavatar.data.random_batch import make_batch_fn

    cfg, module, opt, sched = build(n, backend, overrides)
    # as training compiles (compile=MODE): the networks' path (Avatar.deform, .shade) and the losses, one graph each
    module.compile_path(compile_mode)
    make_batch = make_batch_fn(module.avatar.body, size, int(cfg.data.window_len), device=_device)
    step = timed_step(cfg)
    _stub_trainer_hooks(module, opt, sched, step)
    t0 = _clock()
    step_parts(module, opt, sched, make_batch, step)  # warm-up: numba's cache load, torch.compile's compilation
    first_step_s = _clock() - t0
    parts = {k: [] for k in PARTS}
    whole = []
    for _ in range(repeats):
        for k, v in step_parts(module, opt, sched, make_batch, step).items():
            parts[k].append(v)
        whole.append(step_whole(module, opt, sched, make_batch, step))
    med = {k: statistics.median(v) for k, v in parts.items()}
    # one profiled run for the GPU's kernel time and calls and for --profile's list
    prof = profile_steps(module, opt, sched, make_batch, step, shapes=bool(profile_top))
    # Counted last and for eager rows only: under a TorchDispatchMode dynamo runs the compiled networks eagerly, and
    # keeps doing so after it (a profile taken after the count saw eager kernels): a compiled row's launches are the
    # profile's kernel_launches_per_step.
    counts = (count_ops(module, opt, sched, make_batch, step) if compile_mode == "none" else
              {"ops_per_step": None, "scalar_reads_per_step": None, "data_dependent_per_step": None, "top_ops": {}})
    top = top_ops(prof, profile_top) if profile_top else []
    gpu_kernel_s, cuda_calls = None, {}
    if _device != "cpu":
        steps = PROFILED_STEPS  # not `n`: that is the row's number of Gaussians
        kernels = [e for e in prof.events() if str(getattr(e, "device_type", "")).endswith("CUDA")]
        gpu_kernel_s = sum(e.time_range.elapsed_us() for e in kernels) / (steps * 1e6)
        names = [e.name for e in prof.events()]
        cuda_calls = {"kernel_launches_per_step": sum("LaunchKernel" in k for k in names) / steps,
                      "stream_syncs_per_step": sum("Synchronize" in k for k in names) / steps,
                      "device_to_host_copies_per_step": sum(k.startswith("Memcpy DtoH") for k in names) / steps,
                      "sync_sources": sync_sources(prof.events(), steps)}
    multi = {}
    for V in views:
        if V == 1:
            continue
        make_v = make_batch_fn(module.avatar.body, size, int(cfg.data.window_len), V, device=_device)
        step_whole(module, opt, sched, make_v, step)  # warm-up
        multi[str(V)] = statistics.median([step_whole(module, opt, sched, make_v, step) for _ in range(repeats)])
    return {"n": n, "size": size, "backend": backend, "device": _device, "compile": compile_mode,
            "first_step_s": first_step_s,
            "num_gaussians": int(module.avatar.gaussians.num_points), "step_s": statistics.median(whole),
            "step_min_s": min(whole),
            "sum_of_parts_s": sum(med.values()), "parts_s": med, "views_step_s": multi, "gpu_kernel_s": gpu_kernel_s,
            "top_ops_time": top, **({"cpu_launches_per_step": launches_per_step(prof)} if _device == "cpu" else {}),
            **counts, **cuda_calls, **compile_stats(compile_mode)}


def compile_stats(mode: str) -> dict:
    """A compiled row's graphs and the graphs CUDA graphs skipped (reduce-overhead skips a graph with a host input,
    printing why): from dynamo's and inductor's counters, cleared when the row starts (run_config)."""
    if mode == "none":
        return {}
    from torch._dynamo.utils import counters

    return {"compiled_graphs": counters["stats"]["unique_graphs"],
            "cudagraph_skips": counters["inductor"]["cudagraph_skips"]}


def main() -> None:
    from realityavatar.model.module import COMPILE_MODES

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[10000, 35000])
    ap.add_argument("--size", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--backends", nargs="+", default=["torch", "numba"], help="render.backend values")
    ap.add_argument("--threads", type=int, default=1, help="torch (and numba) threads; 1 is the shared-CPU default")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="cpu: process CPU seconds, steadier than wall time on a shared CPU (only with --threads 1)")
    ap.add_argument("--override", nargs="*", default=[], help="extra hydra overrides, e.g. encoder=whole_pose")
    ap.add_argument("--views", type=int, nargs="+", default=[1],
                    help="also time the whole step with V cameras of one pose window per batch (data.batch_size=V)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:i] (the module and batches there)")
    ap.add_argument("--compile", default="none", choices=COMPILE_MODES,
                    help="torch.compile mode for the networks' path (Avatar.deform, .shade) and the losses "
                         "(AvatarModule.loss); first_step_s includes compiling")
    ap.add_argument("--profile", type=int, default=0, metavar="K",
                    help="also list the K operations (by input shapes) that take the most time per step")
    ap.add_argument("--out", default=None, help="JSON (default results/step_cpu.json, step_cuda.json with --device cuda)")
    ap.add_argument("--no-tune-malloc", action="store_true",
                    help="leave glibc malloc as it is (training tunes it: realityavatar.runtime.tune_malloc)")
    ap.add_argument("--torch-kernels", action="store_true",
                    help="D-SSIM and the polar rotation on their torch paths, as on a GPU, instead of Numba: on the "
                         "CPU the counts are then a GPU step's, the rasterizer's aside")
    a = ap.parse_args()
    if a.torch_kernels:
        from realityavatar import kernels

        kernels.NUMBA_ERROR = "--torch-kernels"
    global _device
    _device = a.device
    if _device == "cpu":  # inductor's C++ kernels show in the profile (launches_per_step)
        import torch._inductor.config as inductor_config

        inductor_config.cpp.enable_kernel_profile = True
    if _device != "cpu" and not torch.cuda.is_available():
        raise SystemExit(f"--device {_device}: CUDA is not available to this torch ({torch.__version__})")
    a.out = a.out or str(Path(__file__).parent / "results" / f"step_{'cpu' if _device == 'cpu' else 'cuda'}.json")
    torch.set_num_threads(a.threads)
    from realityavatar.runtime import tune_malloc

    allocator = "untouched (--no-tune-malloc)" if a.no_tune_malloc else tune_malloc()
    global _clock_base
    _clock_base = time.process_time if a.clock == "cpu" else time.perf_counter
    load_before = list(os.getloadavg())
    units = [gemm_unit()]
    results = []
    for n in a.n:
        for size in a.size:
            for backend in a.backends:
                r = run_config(n, size, backend, a.repeats, a.override, a.views, a.compile, a.profile)
                units.append(gemm_unit())  # the load drifts: each row is divided by the unit measured next to it
                r["gemm_unit_s"] = statistics.median(units[-2] + units[-1])
                # Best of both: other tenants of a shared machine only add time, and the medians' ratio moved from
                # 0.64 to 0.84 within an hour where the minima's read 0.74 and 0.75 (2-core AVX2, 10k / 256^2).
                r["gemm_unit_min_s"] = min(units[-2] + units[-1])
                results.append(r)
                u = r["gemm_unit_s"]
                gk = "" if r["gpu_kernel_s"] is None else (
                    f"; GPU kernels {r['gpu_kernel_s']:.4f}s of it, {r['kernel_launches_per_step']:.0f} launches, "
                    f"{r['stream_syncs_per_step']:.0f} stream syncs")
                print(f"  {backend:6s} N={n:6d} {size}^2  step {r['step_s']:.3f}s = {r['step_s'] / u:.2f} units "
                      f"(best of {a.repeats}: {r['step_min_s']:.3f}s / {r['gemm_unit_min_s']:.3f}s = "
                      f"{r['step_min_s'] / r['gemm_unit_min_s']:.2f}) (first step {r['first_step_s']:.1f}s, compile {r['compile']}) "
                      f"(render fwd {r['parts_s']['render_fwd']:.3f}s, backward {r['parts_s']['backward']:.3f}s{gk}); "
                      + (f"tensor ops not counted (compiled: {r['compiled_graphs']} graphs, "
                         f"{r['cudagraph_skips']} skipped by CUDA graphs)" if r["ops_per_step"] is None else
                         f"{r['ops_per_step']:.0f} tensor ops, {r['scalar_reads_per_step']:.0f} scalar reads, "
                         f"{r['data_dependent_per_step']:.0f} data-dependent shapes per step")
                      + (f"; {r['cpu_launches_per_step']:.0f} launches per step (CPU profile)"
                         if "cpu_launches_per_step" in r else "")
                      + "".join(f"; {V} views {t:.3f}s = {t / u:.2f} units ({t / r['step_s']:.2f}x)"
                                for V, t in r["views_step_s"].items()), flush=True)
                for t in r["top_ops_time"]:
                    print(f"      {t['ms_per_step']:7.2f} ms  x{t['calls_per_step']:<5.1f} {t['op']:32s} {t['shapes']}")
                for where, per_step in r.get("sync_sources", {}).items():
                    print(f"  sync {per_step:5.2f} per step  {where[:300]}")
    cols = ["step", *PARTS]
    print("\nseconds (GEMM units); GEMM unit = 8 float32 matmuls of 1024^3 timed in this process")
    print("| backend | N | image | " + " | ".join(cols) + " |")
    print("|---|---:|---:|" + "---:|" * len(cols))
    for r in results:
        u = r["gemm_unit_s"]
        vals = [r["step_s"], *(r["parts_s"][k] for k in PARTS)]
        print(f"| {r['backend']} | {r['n']} | {r['size']}² | " + " | ".join(f"{v:.3f} ({v / u:.2f})" for v in vals) + " |")
    meta = {
        "command": " ".join(["python", "benchmarks/step.py", *os.sys.argv[1:]]),
        "threads": a.threads,
        "device": a.device,
        "gpu": torch.cuda.get_device_name(torch.device(a.device)) if a.device != "cpu" else None,
        "clock": a.clock,
        "allocator": allocator,
        "torch": torch.__version__,
        "machine": platform.platform(),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": list(os.getloadavg()),
        "gemm_units_s": units,
        "note": "medians (wall or process-CPU seconds, see clock); parts are timed inside one training_step each, step without; "
                "ratio = seconds / GEMM unit measured in the same process next to the row; step_min_s / gemm_unit_min_s: "
                "the best of the repeats of each (a shared machine's other tenants only add time)",
    }
    try:
        from realityavatar.build import git_commit

        meta["commit"] = git_commit()
    except Exception as exc:  # noqa: BLE001 - a missing git is not a reason to lose the numbers
        meta["commit"] = f"unknown ({type(exc).__name__})"
    if math.isfinite(units[0][0]):
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"meta": meta, "results": results}, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
