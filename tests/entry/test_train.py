"""realityavatar-train end to end: a short run lowers the loss and writes its outputs, resumes from its checkpoint,
runs in float64 (the GPU path's dtype slips without a GPU), records its backend, refuses multi-GPU, trains on a
fixture dataset from the command line."""

from __future__ import annotations

import csv
import json
import sys
import warnings

import numpy as np
import pytest
import torch

import realityavatar.render.splat as rast_mod
from realityavatar.config import compose, prepare_run
from tests.fixtures_data import write_i3d
from tests.helpers import ITERATIONS, ROOT, TRAINED_RUN

TINY = ["data=synthetic_ci", "trainer=ci", "gaussians.num_points=400", "eval.save_video=false", "eval.save_images=1",
        "eval.fps_frames=1", "eval.fps_warmup=0", "schedule.skin_pretrain_steps=3", "data.frame_subsample=5",
        "eval.max_frames_per_split=1"]

_prepare = prepare_run  # compose() result -> (cfg, choices) for train.run


def test_training_step_and_evaluation_in_float64(scenes_root, tmp_path):
    """The whole fit (skinning pre-fit, steps with deformation and density control) and evaluation in float64: a
    tensor made without dtype=/device= from its inputs breaks here as a CPU tensor breaks on CUDA."""
    from hydra.utils import instantiate

    from realityavatar.build import build_data, build_module
    from realityavatar.data.lightning import TrainingData
    from realityavatar.evaluate import evaluate_module

    cfg, _ = _prepare(compose([*TINY, "iterations=4", "schedule.deform_start=2", "density.refine_every=2",
                               "density.refine_start=1", "density.refine_stop=4",
                               "density.grad_threshold=0.0"]), tmp_path)
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent).double()
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    assert torch.get_default_dtype() == torch.float32
    trainer.fit(module, datamodule=TrainingData(dm))
    assert trainer.global_step == 4
    assert all(p.dtype == torch.float64 for p in module.parameters())
    assert module.run_info["render"]["dtype"] == "torch.float64"
    metrics = evaluate_module(module, dm, trainer, cfg, tmp_path)
    assert metrics["test/novel_view/psnr"] > 0 and metrics["render_fps"] > 0
    assert metrics["render_fps_device"] == "cpu"
    # animate: float32 poses and cameras from the data feed the float64 module
    from realityavatar.animate import dataset_cameras, render_sequence

    frames = render_sequence(module.avatar, dm.scene.poses, dataset_cameras(dm, [0]), dm.window_len, dm.window_step,
                             dm.pose_sequence("novel_pose")[0].tolist()[:1])
    assert len(frames) == 1 and frames[0].dtype.name == "uint8"


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


def _gsplat_usable() -> bool:
    return torch.cuda.is_available() and rast_mod.gsplat_status() == "ok"


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


def test_short_training_lowers_loss_and_writes_outputs(trained_run):
    out, _ = trained_run
    assert (out / "last.ckpt").is_file()
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("config", "seed", "commit", "train_seconds", "iterations", "num_gaussians", "num_parameters",
                "render_fps", "perceptual", "lpips", "test/novel_view/psnr", "test/novel_view/ssim",
                "test/novel_pose/psnr", "test/novel_view/psnr_masked"):
        assert key in saved, key
    assert saved["iterations"] == ITERATIONS
    assert saved["config"]["temporal"] == "lstm"
    assert saved["lpips"].startswith("not computed") and "test/novel_view/lpips" not in saved
    with open(out / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    # The photometric term, not the total: the total also falls by itself when the skinning weight drops at
    # schedule.skin_switch, which would hide a model that learns nothing.
    l1 = [float(r["train/l1"]) for r in rows if r.get("train/l1")]
    assert len(l1) >= 4
    first, last = np.mean(l1[: len(l1) // 3]), np.mean(l1[-(len(l1) // 3):])
    assert last < 0.95 * first, f"photometric L1 did not decrease: {first:.4f} -> {last:.4f}"
    assert (out / "per_frame.csv").is_file() and (out / "images" / "novel_pose_grid.png").is_file()


def test_resume_continues_from_checkpoint_step(trained_run, tmp_path):
    from realityavatar.train import run

    out, _ = trained_run
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=True)
    assert state["global_step"] == ITERATIONS
    cfg, choices = _prepare(
        compose([*TRAINED_RUN, f"iterations={ITERATIONS + 10}", f"ckpt_path={out / 'last.ckpt'}", "test_after_fit=false"]),
        tmp_path
    )
    metrics = run(cfg, choices)
    assert metrics["iterations"] == ITERATIONS + 10
    with open(tmp_path / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    steps = [int(r["step"]) for r in rows if r.get("train/loss")]
    # the rows before the checkpoint are carried over; a restart from step 0 would log those steps twice
    assert steps == sorted(set(steps)) and min(steps) < ITERATIONS <= max(steps), f"resumed run restarted from step 0: {steps}"


@pytest.mark.slow
def test_training_command_runs_on_fixture_dataset(tmp_path):
    """`realityavatar-train data=capture ...` end to end (fit a few steps, then test) on a fixture I3D-layout dataset."""
    import json
    import subprocess

    from realityavatar.body.mannequin import MannequinBody

    write_i3d(tmp_path / "data", "fx", MannequinBody(), train_frames=tuple(range(4)), pose_frames=(4,),
              train_views=(0, 1), test_views=(2,))
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "realityavatar.train", "data=capture", f"data.root={tmp_path / 'data'}",
           "data.sequence=fx", "iterations=3", "trainer=ci", "gaussians.num_points=300", "eval.save_video=false",
           "eval.fps_frames=2", f"hydra.run.dir={run}"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=False, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["config"]["data"] == "capture" and metrics["iterations"] == 3
    assert np.isfinite(metrics["test/novel_view/psnr"]) and np.isfinite(metrics["test/novel_pose/psnr"])


@pytest.mark.gpu
def test_training_on_a_gpu_synchronises_only_on_log_steps(scenes_root, tmp_path, capfd):
    """Lightning's whole loop on CUDA (the loader, the batches' copies, the step, logging, the progress bar, the
    sampler's feedback) under torch.cuda.set_sync_debug_mode("warn"): a synchronising call only in the steps that
    log (every trainer.log_every_n_steps) and inside gsplat's rasterizer. Each step's span runs from its
    on_train_batch_start to the next one's, so it holds the next batch's copies too. A sync warned outside Python's
    reach (C++ without a Python warning handler, printed to stderr: gsplat's extension reading its intersection count,
    one per step on an H200 at 6913e4f) cannot be placed in a step: at most one per step is allowed."""
    import pytorch_lightning as pl
    from hydra.utils import instantiate

    from realityavatar.build import build_data, build_module
    from realityavatar.data.lightning import SamplerFeedback, TrainingData
    from realityavatar.render.splat import gsplat_status

    if not torch.cuda.is_available() or gsplat_status() != "ok":
        pytest.skip("needs CUDA and gsplat")
    log_every, steps = 4, 12
    overrides = [o for o in TINY if not o.startswith("trainer=")]
    cfg, _ = _prepare(compose([*overrides, "trainer=gpu", "render.backend=gsplat", f"iterations={steps}",
                               f"trainer.log_every_n_steps={log_every}", "density=off", "schedule.deform_start=0"]),
                      tmp_path)
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent)
    events: list = []  # ("step", global step) at each step's start and ("sync", where) for each warning, in order

    class Spans(pl.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            if trainer.global_step == 2:  # after the warm-up steps' one-time set-up (caches, kernels)
                torch.cuda.set_sync_debug_mode("warn")
            events.append(("step", trainer.global_step))

        def on_train_end(self, trainer, pl_module):
            torch.cuda.set_sync_debug_mode("default")

    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False, enable_progress_bar=True,
                          callbacks=[Spans(), SamplerFeedback()])
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = lambda message, category, filename, lineno, *args: events.append(
                ("sync", f"{filename}:{lineno}: {message}"))
            trainer.fit(module, datamodule=TrainingData(dm))
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert trainer.global_step == steps and module.run_info["render"]["backend"] == "gsplat"
    step, bad = None, []
    for kind, what in events:
        if kind == "step":
            step = what
        elif ("called a synchronizing" in what and "gsplat" not in what.split(":")[0]  # not torch's notice that
              and (step + 1) % log_every != 0):  # the mode is a prototype; training_step's log_now
            bad.append(f"step {step}: {what}")
    assert not bad, bad
    unplaced = capfd.readouterr().err.count("called a synchronizing CUDA operation")
    assert unplaced <= steps - 2, f"{unplaced} syncs warned by C++ in {steps - 2} steps"
