"""collect: a hand-written multirun folder into the right tables; missing jobs listed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
import yaml

import realityavatar.config  # noqa: F401  registers the resolvers (int_mul, ...) the real tree's configs use
from realityavatar.analysis.collect import collect, load_runs

PSNR = {
    "full": {"sceneA": [30.0, 31.0, 32.0], "sceneB": [28.0, 29.0, 30.0]},
    "no_zc": {"sceneA": [30.5, 30.0, 31.0], "sceneB": [29.0, 28.5, 29.5]},
    "no_lstm": {"sceneA": [27.0, 27.2, 27.4], "sceneB": [25.0, 25.2, 25.4]},
}


def write_fake_sweep(root: Path, lpips_missing_for: str = "no_lstm") -> Path:
    """A multirun folder as `realityavatar-train -m +ablation=paper data=sceneA,sceneB` leaves it."""
    root.mkdir(parents=True)
    (root / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {
        "hydra": ["hydra.mode=MULTIRUN"], "task": ["+ablation=paper", "data=sceneA,sceneB"]}}}))
    job = 0
    for variant, scenes in PSNR.items():
        for scene, values in scenes.items():
            for seed, psnr in enumerate(values):
                d = root / str(job)
                (d / ".hydra").mkdir(parents=True)
                overrides = [f"+variant={variant}", f"data={scene}", f"seed={seed}", "+ablation=paper"]
                (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
                lp = variant != lpips_missing_for
                m = {
                    "config": {"variant": variant, "data": scene, "ablation": "paper", "color": "mlp"},
                    "overrides": overrides, "seed": seed, "commit": "abc1234", "scene": scene,
                    "train_seconds": 100.0 + 10 * seed, "iterations": 2000, "num_gaussians": 5000,
                    "num_parameters": 123456, "render_fps": 20.0 + seed, "perceptual": "dssim",
                    "lpips": "computed" if lp else "not computed: no LPIPS weights configured",
                    "test/novel_view/psnr": psnr, "test/novel_view/ssim": 0.9 + 0.01 * seed,
                    # a number next to a "not computed" status must still come out as n/c
                    "test/novel_view/lpips": 0.040 + 0.001 * seed if (lp or seed == 0) else None,
                    "test/novel_view/psnr_masked": psnr - 5, "test/novel_view/ssim_masked": 0.8,
                    "test/novel_pose/psnr": psnr - 2, "test/novel_pose/ssim": 0.85,
                    "test/novel_pose/lpips": 0.050 if lp else None,
                    "test/novel_pose/psnr_masked": psnr - 7, "test/novel_pose/ssim_masked": 0.7,
                }
                (d / "metrics.json").write_text(json.dumps(m))
                job += 1
    return root


def test_collect_table_numbers(tmp_path):
    sweep = write_fake_sweep(tmp_path / "outputs/sweeps/paper/2025-01-01_00-00-00")
    out = tmp_path / "results"
    _csv, out_dir = collect(sweep, out)
    assert out_dir == out
    t = pd.read_csv(out / "table.csv").set_index("label")
    assert list(t.index) == ["full", "no_zc", "no_lstm"]
    assert t.loc["full", "novel_view_psnr_mean"] == pytest.approx(30.0)
    assert t.loc["full", "novel_view_psnr_std"] == pytest.approx(1.0)
    assert t.loc["no_zc", "novel_view_psnr_mean"] == pytest.approx(29.75)
    assert t.loc["no_zc", "novel_view_psnr_std"] == pytest.approx(0.5)
    assert t.loc["no_lstm", "novel_view_psnr_mean"] == pytest.approx(26.2)
    assert t.loc["no_lstm", "novel_view_psnr_std"] == pytest.approx(0.2)
    assert t.loc["no_lstm", "novel_pose_psnr_mean"] == pytest.approx(24.2)
    assert bool(t.loc["no_zc", "novel_view_psnr_within_seed_spread"])
    assert not bool(t.loc["no_lstm", "novel_view_psnr_within_seed_spread"])
    assert not bool(t.loc["full", "novel_view_psnr_within_seed_spread"])
    assert float(t.loc["full", "novel_view_lpips_x1000_mean"]) == pytest.approx(41.0)
    assert t.loc["no_lstm", "novel_view_lpips_x1000_mean"] == "n/c"
    assert t.loc["no_lstm", "novel_pose_lpips_x1000_mean"] == "n/c"
    assert t.loc["full", "train_seconds_mean"] == pytest.approx(110.0)
    assert t.loc["full", "train_seconds_std"] == pytest.approx(10.0)
    assert t.loc["full", "n_runs"] == 6 and t.loc["full", "novel_view_psnr_n_seeds"] == 3

    md = (out / "table.md").read_text()
    assert "| Full model | 30.00 ± 1.00 |" in md
    assert "29.75 ± 0.50 †" in md and "26.20 ± 0.20 |" in md and "26.20 ± 0.20 †" not in md
    no_lstm_line = next(line for line in md.splitlines() if line.startswith("| w/o LSTM"))
    assert no_lstm_line.count("n/c") == 2
    assert "n/c: LPIPS not computed (not computed: no LPIPS weights configured)" in md
    assert "abc1234" in md and "realityavatar-train -m +ablation=paper data=sceneA,sceneB" in md
    assert "|Δmean| ≤ max(std of the row, std of the reference row)" in md
    tex = (out / "table.tex").read_text()
    assert r"$30.00 \pm 1.00$" in tex and r"$29.75 \pm 0.50^{\dagger}$" in tex and "n/c" in tex
    assert tex.startswith("% generated by python -m realityavatar.analysis.collect") and "% commit(s): abc1234" in tex
    assert r"\begin{tabular}" in tex and r"w/o latent code $\mathcal{Z}_c$" in tex
    assert (out / "per_scene.csv").is_file() and len(pd.read_csv(out / "runs.csv")) == 18
    ps = pd.read_csv(out / "per_scene.csv")
    r = ps[(ps.label == "full") & (ps.scene == "sceneB") & (ps.quantity == "test/novel_view/psnr")].iloc[0]
    assert (r["mean"], r["std"], r["n_seeds"]) == (pytest.approx(29.0), pytest.approx(1.0), 3)


def test_collect_cli_and_errors(tmp_path):
    sweep = write_fake_sweep(tmp_path / "sweep")
    from realityavatar.analysis.collect import main

    assert main([str(sweep), "--out", str(tmp_path / "o"), "--reference", "no_lstm"]) == 0
    t = pd.read_csv(tmp_path / "o" / "table.csv")
    assert t["label"].iloc[0] == "no_lstm" and bool(t["reference"].iloc[0])
    with pytest.raises(ValueError, match="reference row"):
        collect(sweep, tmp_path / "x", reference="nope")
    bad = sweep / "0" / "metrics.json"
    m = json.loads(bad.read_text())
    del m["num_gaussians"]
    bad.write_text(json.dumps(m))
    with pytest.raises(ValueError, match=r"0/metrics.json: missing field\(s\) \['num_gaussians'\]"):
        collect(sweep, tmp_path / "x")
    with pytest.raises(FileNotFoundError):
        collect(tmp_path / "nothing", tmp_path / "x")


def test_reevaluation_replaces_training_metrics_and_axes_label(tmp_path):
    sweep = write_fake_sweep(tmp_path / "s", lpips_missing_for="none")
    m = json.loads((sweep / "0" / "metrics.json").read_text())
    (sweep / "0" / "eval").mkdir()
    (sweep / "0" / "eval" / "metrics.json").write_text(json.dumps({**m, "test/novel_view/psnr": 40.0}))
    runs = load_runs(sweep)
    assert len(runs.frame) == 18 and runs.axes == ["variant"]
    assert runs.frame[runs.frame.job_dir == str(sweep / "0")]["test/novel_view/psnr"].item() == 40.0
    assert load_runs(sweep, prefer="train").frame["test/novel_view/psnr"].iloc[0] == 30.0


def _fake_job(d: Path, seed: int, metrics: bool = True) -> None:
    (d / ".hydra").mkdir(parents=True)
    ov = ["+variant=full", f"seed={seed}"]
    (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(ov))
    if metrics:
        (d / "metrics.json").write_text(json.dumps({
            "config": {"variant": "full", "data": "synthetic_ci"}, "overrides": ov, "seed": seed, "commit": "abc",
            "scene": "ci", "train_seconds": 1.0, "iterations": 10, "num_gaussians": 5, "num_parameters": 7,
            "lpips": "not computed: x", "test/novel_view/psnr": 20.0 + seed, "test/novel_pose/psnr": 19.0,
        }))


def test_collector_lists_missing_jobs(tmp_path):
    from realityavatar.analysis.collect import main

    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {
        "hydra": ["hydra.mode=MULTIRUN"], "task": ["+variant=full", "seed=0,1,2"]}}}))
    for i in range(3):
        _fake_job(sweep / str(i), i, metrics=i != 1)
    assert main([str(sweep), "--out", str(tmp_path / "o")]) != 0
    md = (tmp_path / "o" / "table.md").read_text()
    assert "seed=1" in md and "missing" in md.lower()
    assert main([str(sweep), "--out", str(tmp_path / "o2"), "--allow-missing"]) == 0
    assert "seed=1" in (tmp_path / "o2" / "table.md").read_text()
    shutil.rmtree(sweep / "2")  # the launcher stopped before job 2: the sweep's expansion still lists it
    assert main([str(sweep), "--out", str(tmp_path / "o3")]) != 0
    md = (tmp_path / "o3" / "table.md").read_text()
    assert "seed=2): never started" in md and "(2 of 3)" in md
