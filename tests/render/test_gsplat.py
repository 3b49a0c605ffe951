"""The GPU path without a GPU: dtype/device slips (float64 stands in for CUDA), gsplat fallback rules with a fake
gsplat, the backend/device a run records, single-run multi-GPU refusal; plus `gpu` tests that run where CUDA is."""

from __future__ import annotations

import json
import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

import realityavatar.render.splat as rast_mod
from realityavatar.config import compose, prepare_run
from realityavatar.render import rasterize

ROOT = Path(__file__).resolve().parents[1]
TINY = ["data=synthetic_ci", "trainer=ci", "gaussians.num_points=400", "eval.save_video=false", "eval.save_images=1",
        "eval.fps_frames=1", "eval.fps_warmup=0", "schedule.skin_pretrain_steps=3", "data.frame_subsample=5"]


_prepare = prepare_run  # compose() result -> (cfg, choices) for train.run


def _scene(n=30, dtype=torch.float32):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from render import human_scene

    return human_scene(n, 32, dtype=dtype)


# ---------------------------------------------------------------------- dtype/device: float64 stands in for CUDA
def test_canonical_vertices_follow_the_buffers():
    from realityavatar.body import build_body

    body = build_body("mannequin").double()
    # a pose built on the default device/dtype and multiplied with moved buffers: the CUDA crash of on_fit_start
    assert body.canonical_pose().dtype == torch.float64
    assert body.canonical_vertices().dtype == torch.float64


def test_training_step_and_evaluation_in_float64(scenes_root, tmp_path):
    """The whole fit (skinning pre-fit, steps with deformation and density control) and evaluation in float64: a
    tensor made without dtype=/device= from its inputs breaks here as a CPU tensor breaks on CUDA."""
    from hydra.utils import instantiate

    from realityavatar.build import build_data, build_module
    from realityavatar.evaluate import evaluate_module

    cfg, _ = _prepare(compose([*TINY, "iterations=4", "schedule.deform_start=2", "density.refine_every=2",
                               "density.refine_start=1", "density.refine_stop=4",
                               "density.grad_threshold=0.0"]), tmp_path)
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent).double()
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    assert torch.get_default_dtype() == torch.float32
    trainer.fit(module, datamodule=dm)
    assert trainer.global_step == 4
    assert all(p.dtype == torch.float64 for p in module.parameters())
    assert module.run_info["render"]["dtype"] == "torch.float64"
    metrics = evaluate_module(module, dm, trainer, cfg, tmp_path)
    assert metrics["test/novel_view/psnr"] > 0 and metrics["render_fps"] > 0
    assert metrics["render_fps_device"] == "cpu"
    # animate: float32 poses and cameras from the data feed the float64 module
    from realityavatar.animate import dataset_cameras, render_sequence

    frames = render_sequence(module, dm.scene.poses, dataset_cameras(dm, [0]), dm.window_len, dm.window_step,
                             dm.pose_sequence("novel_pose")[0].tolist()[:1])
    assert len(frames) == 1 and frames[0].dtype.name == "uint8"


# ---------------------------------------------------------------------- gsplat: build failures fall back, others surface
def _fake_gsplat(root: Path, kernels: bool = True) -> None:
    """A package named gsplat: imports like the real one, `cuda._backend._C` is None when the 'build' failed."""
    pkg = root / "gsplat"
    (pkg / "cuda").mkdir(parents=True)
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        __version__ = "1.5.3"
        calls = []
        raise_on_call = None


        def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                          packed, **kw):
            calls.append(means.dtype)
            if raise_on_call is not None:
                raise raise_on_call
            from gsplat.cuda._backend import _C
            _C.fully_fused_projection_fwd  # no toolkit: AttributeError on NoneType, as in gsplat 1.5.3
            from realityavatar.render.splat import _rasterize_torch
            kw.pop("sh_degree")
            opts = dict(alpha_max=0.999, chunk_elements=1 << 18, tile_cull=True)
            img, alpha, meta = _rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                                sh_degree=None, near=near_plane, far=far_plane, **kw, **opts)
            vis = meta["visible"]
            info = {k: meta[k].clone() for k in ("depths", "conics", "opacities")}
            info["means2d"] = meta["means2d"]
            info["radii"] = meta["radii_xy"]
            for k in ("depths", "conics", "opacities"):  # gsplat leaves culled entries uninitialised
                info[k][~vis] = float("nan")
            return img, alpha, info
    '''))
    (pkg / "cuda" / "__init__.py").write_text("")
    (pkg / "cuda" / "_backend.py").write_text(textwrap.dedent(f'''
        import fcntl, os
        lock = os.path.join(os.environ["TORCH_EXTENSIONS_DIR"], "realityavatar-gsplat.lock")
        held_during_build = False
        os.makedirs(os.path.dirname(lock), exist_ok=True)
        try:
            with open(lock, "a") as f:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            held_during_build = True  # another open file description holds it: our build lock
        _C = {"type('C', (), {'fully_fused_projection_fwd': 1})()" if kernels else "None"}
    '''))


@pytest.fixture
def fake_gsplat(tmp_path, monkeypatch):
    def make(kernels: bool = True):
        _fake_gsplat(tmp_path / "pkgs", kernels)
        monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
        monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
        for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
            monkeypatch.delitem(sys.modules, name)
        monkeypatch.setattr(rast_mod, "_gsplat_failure", None)
        monkeypatch.setattr(rast_mod, "_gsplat_module", None)
        monkeypatch.setattr(rast_mod, "_gsplat_ran", False)
        monkeypatch.setattr(rast_mod, "_on_cuda", lambda t: True)  # the fake stands in for CUDA
        import gsplat

        return gsplat

    yield make
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        sys.modules.pop(name, None)


@pytest.mark.parametrize("broken", ["no_kernels", "first_call"])
def test_gsplat_without_toolkit_falls_back_once(fake_gsplat, broken):
    # `import gsplat` works without nvcc; gsplat 1.5.3's first kernel call then raises AttributeError on NoneType
    gs = fake_gsplat(kernels=broken != "no_kernels")
    if broken == "first_call":
        gs.raise_on_call = AttributeError("'NoneType' object has no attribute 'fully_fused_projection_fwd' (CUDA "
                                          "kernels not built: is nvcc installed?)")
    args = _scene()
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        _, _, meta = rasterize(*args, 32, 32, backend="gsplat")
        _, _, meta2 = rasterize(*args, 32, 32, backend="gsplat")
    assert meta["backend"] == meta2["backend"] == "torch"
    msgs = [str(r.message) for r in rec if "gsplat" in str(r.message)]
    assert len(msgs) == 1 and "CUDA" in msgs[0] and "nvcc" in msgs[0]
    assert len(gs.calls) <= 1


def test_gsplat_runtime_errors_surface_and_do_not_switch_it_off(fake_gsplat):
    gs = fake_gsplat()
    args = _scene()
    _, _, meta = rasterize(*args, 32, 32, backend="gsplat")
    assert meta["backend"] == "gsplat"
    gs.raise_on_call = RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB")
    with pytest.raises(RuntimeError, match="out of memory"):
        rasterize(*args, 32, 32, backend="gsplat")
    gs.raise_on_call = None
    _, _, meta = rasterize(*args, 32, 32, backend="auto")
    assert meta["backend"] == "gsplat", "one error switched gsplat off for the whole process"


def test_gsplat_float64_is_decided_before_the_call(fake_gsplat):
    gs = fake_gsplat()
    args64 = _scene(dtype=torch.float64)
    _, _, meta = rasterize(*args64, 32, 32, backend="auto")  # auto: the backend that can take float64
    assert meta["backend"] == "torch" and not gs.calls
    with pytest.raises(ValueError, match="float32"):
        rasterize(*args64, 32, 32, backend="gsplat")
    _, _, meta = rasterize(*_scene(), 32, 32, backend="auto")
    assert meta["backend"] == "gsplat"


def test_gsplat_meta_masks_culled_entries_and_rejects_packed(fake_gsplat):
    fake_gsplat()
    means, *rest = _scene()
    means = means.clone()
    means[:5, 1] = -10.0  # behind the camera: culled
    _, _, meta = rasterize(means, *rest, 32, 32, backend="gsplat")
    assert meta["backend"] == "gsplat" and not meta["visible"][0, :5].any()
    for k in ("depths", "conics", "opacities"):
        assert torch.isfinite(meta[k]).all(), k
    with pytest.raises(ValueError, match="packed"):
        rasterize(*_scene(), 32, 32, backend="gsplat", packed=True)


def test_gsplat_build_holds_a_lock(fake_gsplat):
    """Concurrent first-time JIT builds (array jobs) take turns: the kernels load under an inter-process lock."""
    fake_gsplat()
    rasterize(*_scene(), 32, 32, backend="gsplat")
    import gsplat.cuda._backend as backend

    assert backend.held_during_build


def test_check_finite_reads_the_device_once(monkeypatch):
    """Each host read of a CUDA tensor is a sync; the input checks do one, not one per tensor."""
    reads = []
    for name in ("__bool__", "item"):
        orig = getattr(torch.Tensor, name)

        def counted(self, _orig=orig):
            reads.append(1)
            return _orig(self)

        monkeypatch.setattr(torch.Tensor, name, counted)
    args = _scene()
    rast_mod._check_inputs(*args, 32, 32, None, None, 0.01, 1e10, "RGB", "classic", True)
    assert len(reads) <= 1


def test_metrics_do_not_depend_on_float32_accumulation():
    """PSNR/SSIM accumulate in float64 (no TF32 convolutions on CUDA; CPU and GPU give the same numbers)."""
    from realityavatar.metrics import psnr, ssim

    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(48, 40, 3, generator=g), torch.rand(48, 40, 3, generator=g)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(x.double(), y.double())), abs=1e-12)
    assert float(psnr(x, y)) == pytest.approx(float(psnr(x.double(), y.double())), abs=1e-12)
    assert ssim(x, y).dtype == torch.float64


# ---------------------------------------------------------------------- what a run records
def test_run_records_the_backend_it_used(scenes_root, tmp_path):
    from realityavatar.train import run

    cfg, choices = _prepare(compose([*TINY, "iterations=2", "render.backend=gsplat"]), tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gsplat on CPU tensors falls back with a warning
        metrics = run(cfg, choices)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["backend"] == "torch" and saved["backend_configured"] == "gsplat"
    assert saved["device"] == "cpu" and saved["render_fps_device"] == "cpu"
    assert saved["render_fps_backend"] == "torch"
    assert metrics["backend"] == "torch"


def test_multi_gpu_single_run_fails_fast(scenes_root, tmp_path):
    from realityavatar.train import run

    cfg, choices = _prepare(compose([*TINY, "iterations=2", "trainer.devices=2", "+trainer.strategy=ddp"]), tmp_path)
    with pytest.raises(ValueError, match="one run per GPU"):
        run(cfg, choices)
    assert not (tmp_path / "metrics.json").exists()


# ---------------------------------------------------------------------- on a GPU
def _gsplat_usable() -> bool:
    return torch.cuda.is_available() and rast_mod.gsplat_status() == "ok"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_torch_backend_forward_and_backward_on_cuda_match_cpu():
    from test_render import random_scene

    a = random_scene(200, seed=1, cams=2, dtype=torch.float32)
    out = {}
    for dev in ("cpu", "cuda"):
        # fresh leaves per device: .to('cpu') of a CPU tensor is the tensor itself, and requires_grad_ on it would
        # make the CUDA copies non-leaves (grad None)
        params = [t.detach().clone().to(dev).requires_grad_() for t in a[:5]]
        img, alpha, meta = rasterize(*params, *[t.to(dev) for t in a[5:7]], *a[7:], backend="torch")
        (img.square().sum() + alpha.sum()).backward()
        out[dev] = [img, alpha, meta["means2d"].grad, *[p.grad for p in params]]
    for c, g in zip(out["cpu"], out["cuda"]):
        assert torch.allclose(c, g.cpu(), atol=1e-4, rtol=1e-3)


@pytest.mark.gpu
@pytest.mark.skipif(not _gsplat_usable(), reason="needs CUDA and a working gsplat")
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gsplat_matches_torch_images_alphas_and_means2d_grads(mode):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from render import human_scene

    args = human_scene(5000, 256, device="cuda")
    gout = torch.rand(1, 256, 256, 3, device="cuda")
    res = {}
    for backend in ("torch", "gsplat"):
        params = [t.clone().requires_grad_() for t in args[:5]]
        img, alpha, meta = rasterize(*params, *args[5:], 256, 256, backend=backend, rasterize_mode=mode)
        assert meta["backend"] == backend
        ((img * gout).sum() + alpha.sum()).backward()
        res[backend] = (img, alpha, meta["means2d"].grad, meta["visible"], params[0].grad)
    (ti, ta, tg, tv, tm), (gi, ga, gg, gv, gm) = res["torch"], res["gsplat"]
    assert (ti - gi).abs().mean() < 1e-4 and (ta - ga).abs().mean() < 1e-4
    both = tv & gv
    assert (tv != gv).float().mean() < 1e-3
    rel = (tg[both] - gg[both]).norm() / gg[both].norm()
    assert rel < 1e-2, f"means2d gradients differ by {float(rel):.3g} (relative)"
    assert (tm - gm).norm() / gm.norm() < 1e-2


@pytest.mark.gpu
@pytest.mark.parametrize("backend", [
    pytest.param("gsplat", marks=pytest.mark.skipif(not _gsplat_usable(), reason="needs CUDA and a working gsplat")),
    pytest.param("torch", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")),
])
def test_two_step_gpu_fit_on_ci_scene(scenes_root, tmp_path, backend):
    """The LightningModule on CUDA: skinning pre-fit, steps, test loop, FPS, evaluate and animate from the folder."""
    from realityavatar.animate import main as animate_main
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.train import run

    cfg, choices = _prepare(compose([*TINY, "iterations=2", "trainer=gpu", f"render.backend={backend}",
                                     "trainer.enable_progress_bar=false"]), tmp_path)
    metrics = run(cfg, choices)
    assert metrics["device"].startswith("cuda") and metrics["backend"] == backend
    assert metrics["render_fps_device"].startswith("cuda") and metrics["render_fps_backend"] == backend
    assert metrics["iterations"] == 2 and metrics["test/novel_view/psnr"] > 0
    assert evaluate_main([f"run_dir={tmp_path}", "eval.save_video=false"]) == 0
    again = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert again["render_fps_device"].startswith("cuda")
    assert abs(again["test/novel_view/psnr"] - metrics["test/novel_view/psnr"]) < 1e-3
    # a .gif: the GPU image this ran on has no ffmpeg, and the render (not the video encoder) is what is checked here
    assert animate_main([f"run_dir={tmp_path}", "views=0", f"out={tmp_path / 'a.gif'}"]) == 0


# ---------------------------------------------------------------------- the one-command GPU benchmark
def test_gpu_benchmark_runs_and_skips_cuda_cleanly(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gpu

    out = tmp_path / "gpu.json"
    rc = gpu.main(["--n", "300", "--size", "32", "--repeats", "1", "--out", str(out), "--step", "1000",
                   "--tests", "tests/test_gpu_path.py::test_torch_backend_forward_and_backward_on_cuda_match_cpu"])
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


# ---------------------------------------------------------------------- the training step on the GPU
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
