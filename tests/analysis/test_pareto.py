"""pareto: the chart and CSV, the budget choice (fewest Gaussians within a tolerance of the best)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest
import yaml

import realityavatar.config  # noqa: F401  registers the resolvers (int_mul, ...) the real tree's configs use
from realityavatar.analysis.pareto import main as pareto_main
from realityavatar.analysis.pareto import pareto, smallest_within
from tests.analysis.sweeps import write_fake_sweep


def test_pareto_chart_and_csv(tmp_path):
    sweep = write_fake_sweep(tmp_path / "sweep")
    df = pareto(sweep, tmp_path / "p")
    assert (tmp_path / "p" / "pareto.png").stat().st_size > 10_000
    c = pd.read_csv(tmp_path / "p" / "pareto.csv").set_index("label")
    assert c.loc["full", "novel_view_psnr_mean"] == pytest.approx(30.0)
    assert c.loc["full", "train_seconds_mean"] == pytest.approx(110.0)
    assert c.loc["full", "render_fps_mean"] == pytest.approx(21.0)
    assert c.loc["full", "render_fps_std"] == pytest.approx(1.0)
    assert c.loc["no_lstm", "num_gaussians_mean"] == 5000
    # every row trains equally long here, so only the most accurate one is on the time frontier
    assert list(c.index[c["pareto_time"]]) == ["full"]
    assert len(df) == 3 and not math.isnan(df["novel_view_psnr_std"].iloc[0])


def write_fake_budget(root: Path) -> Path:
    """A `+ablation=budget` multirun: num_points x density x 2 seeds, with final counts and PSNRs chosen so that the
    answer is known: 10000/off is the best (30.3), 5000/default (final 7000) is the smallest within 0.2 dB (30.15);
    by the garment's PSNR, 10000/default is the best (25.1) and 10000/off the smallest within 0.2 dB (25.0)."""
    root.mkdir(parents=True)
    (root / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {"task": ["+ablation=budget"]}}}))
    # (num_points, density) -> (final Gaussians, NV PSNR mean, train seconds, NV garment PSNR mean)
    table = {(2000, "off"): (2000, 29.0, 50.0, 22.0), (2000, "default"): (4000, 29.9, 60.0, 23.0),
             (5000, "off"): (5000, 29.7, 70.0, 23.5), (5000, "default"): (7000, 30.15, 80.0, 24.0),
             (10000, "off"): (10000, 30.3, 100.0, 25.0), (10000, "default"): (12000, 30.25, 110.0, 25.1)}
    job = 0
    for (n, dens), (final, psnr, secs, garment) in table.items():
        for seed in (0, 1):
            d = root / str(job)
            (d / ".hydra").mkdir(parents=True)
            overrides = [f"gaussians.num_points={n}", f"density={dens}", "data=synthetic_sweep", f"seed={seed}",
                         "+ablation=budget"]
            (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
            m = {"config": {"data": "synthetic_sweep", "ablation": "budget", "density": dens},
                 "overrides": overrides, "seed": seed, "commit": "abc1234", "scene": "skirt_spin",
                 "train_seconds": secs, "iterations": 1000, "num_gaussians": final, "num_parameters": 1,
                 "render_fps": 30.0, "perceptual": "dssim", "lpips": "not computed",
                 "test/novel_view/psnr": psnr + (0.05 if seed else -0.05), "test/novel_pose/psnr": psnr - 1,
                 "test/novel_view/psnr_garment": garment + (0.05 if seed else -0.05)}
            (d / "metrics.json").write_text(json.dumps(m))
            job += 1
    return root


def test_budget_choice_is_the_smallest_within_tolerance(tmp_path, capsys):
    sweep = write_fake_budget(tmp_path / "budget")
    df = pareto(sweep, tmp_path / "chart")
    assert {"gaussians.num_points", "density"} <= set(df.columns)
    choice = smallest_within(df, 0.2)
    assert choice["best"]["label"] == df.loc[df.novel_view_psnr_mean.idxmax(), "label"]
    assert choice["best"]["num_gaussians_mean"] == 10000
    assert (choice["choice"]["gaussians.num_points"], choice["choice"]["density"]) == ("5000", "default")
    assert choice["choice"]["num_gaussians_mean"] == 7000
    # a tighter tolerance leaves only the rows at 30.25 and above: 10000/default (12000) is bigger than 10000/off
    assert smallest_within(df, 0.06)["choice"]["num_gaussians_mean"] == 10000
    # the size panel's frontier: no row is both smaller and more accurate than 4000/29.9
    front = df[df.pareto_size].sort_values("num_gaussians_mean")["num_gaussians_mean"].tolist()
    assert front == [2000, 4000, 7000, 10000]
    # by the garment the budget is larger: 10000/off is within 0.2 dB of 10000/default's 25.1
    by_garment = smallest_within(df, 0.2, "novel_view_psnr_garment_mean")
    assert by_garment["choice"]["num_gaussians_mean"] == 10000 and by_garment["best"]["num_gaussians_mean"] == 12000
    assert pareto_main([str(sweep), "--out", str(tmp_path / "cli")]) == 0
    saved = json.loads((tmp_path / "cli" / "choice.json").read_text())
    assert saved["whole_image"]["choice"]["num_gaussians_mean"] == 7000
    assert saved["local"]["choice"]["num_gaussians_mean"] == 10000
    assert "choice by novel_view_psnr_mean (fewest Gaussians within 0.2 dB of the best)" in capsys.readouterr().out
