"""End-to-end: configs compose and instantiate, a short run trains/evaluates/resumes, bad input fails clearly, PLY export."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import open_dict

from realityavatar.config import CONFIG_DIR, compose

SMALL = ["trainer=ci", "gaussians.num_points=1500", "eval.save_video=false", "eval.fps_frames=2", "eval.fps_warmup=1"]
COMPONENT_GROUPS = ("gaussians", "encoder", "temporal", "deformer", "skinning", "color", "density", "loss",
                    "silhouette")


def _prepare(cfg, out_dir: Path):
    choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra") and v is not None}
    with open_dict(cfg):
        del cfg["hydra"]
        cfg.out_dir = str(out_dir)
    return cfg, choices


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


@pytest.fixture(scope="module")
def body():
    from realityavatar.body import build_body

    return build_body("mannequin")


@pytest.mark.parametrize("group", COMPONENT_GROUPS + ("render", "optim", "trainer", "body", "data"))
def test_every_option_composes(group):
    opts = _options(group)
    assert opts, f"conf/{group} has no options"
    for opt in opts:
        cfg = compose([f"{group}={opt}"])
        assert cfg.hydra.runtime.choices[group] == opt


@pytest.mark.parametrize("group", COMPONENT_GROUPS)
def test_every_component_option_instantiates(group, body):
    for opt in _options(group):
        cfg = compose([f"{group}={opt}"])
        node = cfg[group]
        kwargs = {"body": body} if group == "gaussians" else {"num_frames": 4} if group == "color" else {}
        obj = instantiate(node, **kwargs)
        assert obj is not None, f"{group}={opt}"


def test_unknown_option_names_the_group():
    with pytest.raises(Exception) as e:
        compose(["temporal=transformer"])
    assert "temporal" in str(e.value) and "transformer" in str(e.value)


@pytest.fixture(scope="module")
def trained_run(scenes_root, tmp_path_factory):
    from realityavatar.train import run

    out = tmp_path_factory.mktemp("run")
    cfg, choices = _prepare(compose(["data=synthetic_ci", "iterations=60", *SMALL]), out)
    metrics = run(cfg, choices)
    return out, metrics


def test_short_training_lowers_loss_and_writes_outputs(trained_run):
    out, metrics = trained_run
    assert (out / "last.ckpt").is_file()
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("config", "seed", "commit", "train_seconds", "iterations", "num_gaussians", "num_parameters",
                "render_fps", "perceptual", "lpips", "test/novel_view/psnr", "test/novel_view/ssim",
                "test/novel_pose/psnr", "test/novel_view/psnr_masked"):
        assert key in saved, key
    assert saved["iterations"] == 60
    assert saved["config"]["temporal"] == "lstm"
    assert saved["lpips"].startswith("not computed") and "test/novel_view/lpips" not in saved
    rows = list(csv.DictReader(open(out / "logs" / "csv" / "metrics.csv")))
    losses = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    assert len(losses) >= 4
    first, last = np.mean(losses[: len(losses) // 3]), np.mean(losses[-(len(losses) // 3):])
    assert last < first, f"loss did not decrease: {first:.4f} -> {last:.4f}"
    assert (out / "per_frame.csv").is_file() and (out / "images" / "novel_pose_grid.png").is_file()


def test_resume_continues_from_checkpoint_step(trained_run, tmp_path):
    from realityavatar.train import run

    out, _ = trained_run
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=False)
    assert state["global_step"] == 60
    cfg, choices = _prepare(
        compose(["data=synthetic_ci", "iterations=70", f"ckpt_path={out / 'last.ckpt'}", "test_after_fit=false", *SMALL]), tmp_path
    )
    metrics = run(cfg, choices)
    assert metrics["iterations"] == 70
    rows = list(csv.DictReader(open(tmp_path / "logs" / "csv" / "metrics.csv")))
    steps = [int(r["step"]) for r in rows if r.get("train/loss")]
    # the rows before the checkpoint are carried over; a restart from step 0 would log those steps twice
    assert steps == sorted(set(steps)) and min(steps) < 60 <= max(steps), f"resumed run restarted from step 0: {steps}"


def test_evaluate_and_export_from_run_folder(trained_run):
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.export import main as export_main, read_ply

    out, metrics = trained_run
    assert evaluate_main([f"run_dir={out}", "eval.save_video=false"]) == 0
    again = json.loads((out / "eval" / "metrics.json").read_text())
    assert abs(again["test/novel_view/psnr"] - metrics["test/novel_view/psnr"]) < 1e-3
    assert export_main([f"run_dir={out}", f"out={out / 'c.ply'}"]) == 0
    ply = read_ply(out / "c.ply")
    assert ply["means"].shape == (metrics["num_gaussians"], 3)


def test_ply_round_trip(tmp_path):
    from realityavatar.export import read_ply, write_ply

    rng = np.random.default_rng(0)
    N = 50
    means, quats = rng.normal(size=(N, 3)), rng.normal(size=(N, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales, op = rng.uniform(0.01, 0.1, (N, 3)), rng.uniform(0.05, 0.95, N)
    sh = rng.normal(size=(N, 16, 3))
    write_ply(tmp_path / "g.ply", means, quats, scales, op, sh=sh)
    back = read_ply(tmp_path / "g.ply")
    for k, v in (("means", means), ("quats", quats), ("scales", scales), ("opacities", op), ("sh", sh)):
        np.testing.assert_allclose(back[k], v, rtol=1e-4, atol=1e-5, err_msg=k)
    with pytest.raises(ValueError, match="means"):
        write_ply(tmp_path / "bad.ply", means[:, :2], quats, scales, op, sh=sh)


def test_missing_scene_folder_is_named(tmp_path, body):
    cfg = compose(["data=synthetic_ci", f"data.root={tmp_path / 'nowhere'}"])
    with open_dict(cfg):
        cfg.data.build_preset = None
    dm = instantiate(cfg.data, body=body)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        dm.prepare_data()
        dm.setup("fit")


def test_nan_pose_gives_clear_error(body):
    from realityavatar.body.base import check_pose

    pose = torch.zeros(24, 3)
    pose[5, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        body(pose, torch.zeros(3))
    with pytest.raises(ValueError, match=r"\[\.\.\.,24,3\]"):
        check_pose(torch.zeros(23, 3), None)


def test_animate_writes_video_from_pose_file(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main

    out, _ = trained_run
    poses = np.zeros((5, 24, 3), np.float32)
    poses[:, 16, 2] = np.linspace(0, 1.2, 5)  # raise the left arm
    np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((5, 3), np.float32))
    assert animate_main([f"run_dir={out}", f"poses={tmp_path / 'wave.npz'}", "views=0", f"out={tmp_path / 'wave.mp4'}"]) == 0
    assert (tmp_path / "wave.mp4").stat().st_size > 0
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((5, 23, 3), np.float32))
    with pytest.raises(ValueError, match="poses"):
        animate_main([f"run_dir={out}", f"poses={bad}"])
