"""realityavatar-evaluate from a run folder: the run's numbers again, fewer frames per split."""

from __future__ import annotations

import csv
import json

import numpy as np


def test_evaluate_and_export_from_run_folder(trained_run):
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.export import main as export_main
    from realityavatar.export import read_ply

    out, metrics = trained_run
    assert evaluate_main([f"run_dir={out}", "eval.save_video=false"]) == 0
    again = json.loads((out / "eval" / "metrics.json").read_text())
    assert abs(again["test/novel_view/psnr"] - metrics["test/novel_view/psnr"]) < 1e-3
    assert export_main([f"run_dir={out}", f"out={out / 'c.ply'}"]) == 0
    ply = read_ply(out / "c.ply")
    assert ply["means"].shape == (metrics["num_gaussians"], 3)


def test_max_frames_per_split(trained_run):
    from realityavatar.evaluate import main as evaluate_main

    out, full = trained_run
    assert evaluate_main([f"run_dir={out}", "eval.max_frames_per_split=2"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    for split in ("novel_view", "novel_pose"):
        with open(out / "per_frame.csv") as f:
            views = {int(r["view"]) for r in csv.DictReader(f) if r["split"] == split}
        assert m[f"test/{split}/num_images"] == 2 * len(views) < full[f"test/{split}/num_images"]


def test_evaluate_records_where_lpips_weights_came_from(trained_run, tmp_path, monkeypatch):
    """metrics.lpips_weights unset and LPIPS weights found (the lpips package's lin file, torch's hub cache): the
    pure-torch LPIPS computes, and metrics.json says where its weights came from."""
    from realityavatar.evaluate import format_table
    from realityavatar.evaluate import main as evaluate_main
    from tests.helpers import plant_found_weights

    out, _ = trained_run
    found = plant_found_weights(tmp_path, monkeypatch)
    assert evaluate_main([f"run_dir={out}", "eval.max_frames_per_split=1", "eval.save_video=false",
                          "eval.save_images=0"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert m["lpips"] == f"computed (weights: lpips package {found['lin']} + torch hub {found['vgg16']})"
    assert m["test/novel_view/lpips"] > 0 and m["test/novel_pose/lpips_masked"] > 0
    assert f"LPIPS {m['lpips']}" in format_table(m)


def test_results_table_prints_a_zero_iou_as_zero():
    """A silhouette that misses the mask everywhere has IoU 0.0, which the table prints as such (it printed nan)."""
    from realityavatar.evaluate import format_table

    m = {f"test/novel_view/{k}": v for k, v in {"psnr": 20.0, "ssim": 0.5, "iou": 0.0, "psnr_masked": 15.0,
                                                "ssim_masked": 0.1, "num_images": 3}.items()}
    row = format_table(m).splitlines()[1].split()
    assert row[:4] == ["novel_view", "20.00", "0.5000", "0.000"], row


def test_evaluate_and_probe_a_run_below_its_resolution_supersampled(trained_run, monkeypatch):
    """A run evaluated on its scene at half the size, each image rendered at 2x and averaged (as paper_scale's
    512 px run on the 128 px sweep scene, docs/gpu.md): metrics.json says so and has the smaller size (rendered
    directly instead, it says which eval.supersample to set); the probe, given the same settings, renders the same way
    and reads its novel-pose phases from that evaluation's per_frame.csv."""
    from realityavatar.analysis import probe
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.evaluate import undersampled
    from realityavatar.model.avatar import Avatar

    out, full = trained_run
    # rendered directly at half the size: evaluate says what to set (the checkpoint records the training size)
    assert evaluate_main([f"run_dir={out}", "eval.save_video=false", "eval.max_frames_per_split=1",
                          "data.image_scale=0.5"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert "eval.supersample=2" in m["eval_undersampled"]
    # the rendered size unknown (the FPS stage failed): no advice, and no division by it
    assert undersampled({"render": {"resolution": [64, 64]}}, 1, 0) is None
    settings = ["data.image_scale=0.5", "eval.supersample=2"]
    assert evaluate_main([f"run_dir={out}", "eval.save_video=false", "eval.max_frames_per_split=2", *settings]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert m["eval_supersample"] == 2 and "eval_undersampled" not in m
    assert m["render_resolution"] == [s // 2 for s in full["render_resolution"]]
    render, supersampled, folders = Avatar.render_batch, [], []
    monkeypatch.setattr(Avatar, "render_batch",
                        lambda self, *a, **k: supersampled.append(k.get("supersample", 1)) or render(self, *a, **k))
    phases = probe.novel_pose_phases
    monkeypatch.setattr(probe, "novel_pose_phases", lambda folder, *a: folders.append(folder) or phases(folder, *a))
    rows, _ = probe.probe_run(out, kinds=("heldout",), overrides=settings)
    assert rows and set(supersampled) == {2} and folders == [out / "eval"]


def test_a_bad_setting_given_to_evaluate_or_the_probe_names_its_key(trained_run):
    """Settings given to a run folder are checked before anything is built from them (`int('abc')` in the module's
    construction said nothing of the key); the run's earlier evaluation stays as it was."""
    import pytest

    from realityavatar.analysis import probe
    from realityavatar.evaluate import main as evaluate_main

    out, _ = trained_run
    before = {p: p.read_bytes() for p in (out / "eval").glob("*.*")} if (out / "eval").is_dir() else {}
    for value in ("abc", "0", "1.5"):
        with pytest.raises(ValueError, match=rf"^eval\.supersample={value!r}|^eval\.supersample={value}:"):
            evaluate_main([f"run_dir={out}", f"eval.supersample={value}"])
    with pytest.raises(ValueError, match=r"^data\.image_scale"):
        probe.probe_run(out, kinds=("heldout",), overrides=["data.image_scale=-1"])
    assert {p: p.read_bytes() for p in before} == before


def test_evaluation_without_ffmpeg_keeps_its_outputs_and_says_why_no_video(tmp_path, monkeypatch, capsys):
    """No imageio-ffmpeg (a GPU image without it): the per-frame CSV and grids are written, and the missing video
    names the package, not imageio's TIFF writer's TypeError on `fps` (what the H100 printed on 2026-11-28)."""
    import sys

    import torch

    from realityavatar.evaluate import write_outputs

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    img = torch.rand(8, 8, 3)
    records = [{"split": "novel_view", "frame": f, "view": 0, "psnr": 30.0, "_pred": img, "_gt": img} for f in range(3)]
    paths = write_outputs(records, tmp_path, save_images=2, save_video=True)
    assert set(paths) == {"per_frame_csv", "novel_view_grid"}
    err = capsys.readouterr().err
    assert "video for novel_view not written" in err and "imageio-ffmpeg" in err and "TiffWriter" not in err, err


def test_run_reports_the_garment_per_motion_phase(trained_run):
    """A run on a synthetic scene scores the garment's pixels per split and motion phase: metrics.json has the
    garment's PSNR / SSIM / FLIP / detail for the rest and spin phases of both held-out splits, per_frame.csv a
    phase for every image (and garment scores on nearly every held-out image), the printed table a row per phase."""
    from realityavatar.evaluate import format_table

    out, m = trained_run
    for split in ("novel_view", "novel_pose"):
        for phase in ("rest", "spin"):
            for k in ("psnr_garment", "ssim_garment", "flip_garment", "detail_garment", "psnr_masked", "flip"):
                assert np.isfinite(m[f"test/{split}/{phase}/{k}"]), (split, phase, k)
        assert 0 < m[f"test/{split}/flip_garment"] < 1 and 0 < m[f"test/{split}/detail_garment"] < 2
    with open(out / "per_frame.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["phase"] for r in rows} >= {"rest", "spin", "after"}
    assert sum(bool(r["psnr_garment"]) for r in rows) > 0.9 * len(rows)  # 64 px: a few labels erode away
    table = format_table(m)
    assert "novel_view spin" in table and "PSNR(garm)" in table
