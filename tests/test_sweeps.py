"""Sweep configs expand to the intended jobs and compose; launcher configs compose; the collectors turn a
small hand-written multirun folder into the right tables and chart."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser

import realityavatar.config  # noqa: F401  registers the resolvers (int_mul, ...) the real tree's configs use
from realityavatar.analysis.collect import collect, load_runs
from realityavatar.analysis.pareto import main as pareto_main
from realityavatar.analysis.pareto import pareto, smallest_within

ROOT = Path(__file__).resolve().parents[1]

CONF = ROOT / "conf"
SEEDS = {"0", "1", "2"}
# ablation name -> (number of jobs, {override key: the values it must take})
EXPECTED = {
    "paper": (12, {"+variant": {"full", "no_zc", "no_lstm", "no_split"}, "seed": SEEDS, "data": {"synthetic_sweep"}}),
    "temporal": (9, {"temporal": {"lstm", "gru", "none"}, "seed": SEEDS}),
    "color": (6, {"color": {"mlp", "sh"}, "seed": SEEDS}),
    "budget": (24, {"gaussians.num_points": {"2000", "5000", "10000", "35000"}, "density": {"default", "off"},
                    "seed": SEEDS}),
    "speed": (18, {"iterations": {"500", "1000", "2000"}, "data.image_scale": {"0.5", "1.0"}, "render.backend": {"torch"},
                   "seed": SEEDS}),
    "tiny": (2, {"+variant": {"full", "no_lstm"}, "seed": {"0"}, "data": {"synthetic_ci"}, "trainer": {"ci"}}),
    "scenes": (8, {"+variant": {"full", "no_lstm"}, "seed": {"0"},
                   "data": {"synthetic_sweep", "synthetic_sweep_dress_spin", "synthetic_sweep_skirt_flap",
                            "synthetic_sweep_dress_walk"}}),
    "dynamics": (3, {"seed": SEEDS, "data": {"synthetic_sweep"}}),  # its variants: one override per command
}
VARIANT_CHOICES = {"full": ("latentbone", "lstm"), "no_zc": ("no_zc", "lstm"),
                   "no_lstm": ("latentbone", "none"), "no_split": ("no_split", "lstm")}
# Option names fixed by the project; a stand-in tree with exactly these lets the sweep files be checked on
# their own, independent of the other groups' contents.
GROUPS = {
    "data": ["synthetic_ci", "synthetic_demo", "synthetic_sweep", "synthetic_sweep_dress_spin",
             "synthetic_sweep_skirt_flap", "synthetic_sweep_dress_walk"], "sampler": ["uniform", "hard_frames"], "body": ["mannequin", "smpl"],
    "gaussians": ["default"], "encoder": ["latentbone", "no_split", "no_zc"], "temporal": ["lstm", "gru", "none"],
    "deformer": ["motion_trend"], "silhouette": ["chamfer", "none"], "skinning": ["mlp", "grid"], "color": ["mlp", "sh"],
    "shading": ["irradiance", "none"], "density": ["default", "off"], "sheet": ["none", "skirt"],
    "loss": ["default"], "render": ["default"], "optim": ["default"], "trainer": ["cpu", "gpu", "ci"],
}


@pytest.fixture(autouse=True)
def _clear_hydra():
    GlobalHydra.instance().clear()
    yield
    GlobalHydra.instance().clear()


@pytest.fixture(scope="module")
def standin_conf(tmp_path_factory) -> Path:
    """conf/ with this project's ablation, variant, preset and launcher files and one-line stand-ins for every other option."""
    conf = tmp_path_factory.mktemp("conf")
    for group, options in GROUPS.items():
        (conf / group).mkdir()
        for opt in options:
            body = {"name": opt}
            if group == "data":
                body["image_scale"] = 1.0
            if group == "gaussians":
                body["num_points"] = 10000
            if group == "render":
                body["backend"] = "auto"
            (conf / group / f"{opt}.yaml").write_text(yaml.safe_dump(body))
    for sub in ("ablation", "variant", "preset", "hydra/launcher"):
        (conf / sub).mkdir(parents=True)
        for f in (CONF / sub).glob("*.yaml"):
            (conf / sub / f.name).write_text(f.read_text())
    primary = {"defaults": [{g: o[0] if g != "data" else "synthetic_demo"} for g, o in GROUPS.items()] + ["_self_"],
               "seed": 0, "iterations": 2000}
    primary["defaults"][list(GROUPS).index("trainer")] = {"trainer": "cpu"}
    (conf / "train.yaml").write_text(yaml.safe_dump(primary, sort_keys=False))
    return conf


def expand(conf: Path, name: str) -> list[list[str]]:
    """The jobs `realityavatar-train -m +ablation=<name>` launches, as the basic sweeper computes them."""
    with initialize_config_dir(str(conf), version_base="1.3"):
        cfg = compose("train", overrides=[f"+ablation={name}"], return_hydra_config=True)
        params = cfg.hydra.sweeper.params
        assert params, f"conf/ablation/{name}.yaml sets no hydra.sweeper.params"
        assert cfg.hydra.sweep.dir.startswith(f"outputs/sweeps/{name}/"), cfg.hydra.sweep.dir
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    (jobs,) = BasicSweeper.split_arguments(parsed, None)
    return jobs


def _job_choices(conf: Path, name: str, job: list[str]):
    with initialize_config_dir(str(conf), version_base="1.3"):
        cfg = compose("train", overrides=[f"+ablation={name}", *job], return_hydra_config=True)
    return cfg, dict(cfg.hydra.runtime.choices)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sweep_expands_to_expected_jobs(standin_conf, name):
    n_jobs, axes = EXPECTED[name]
    assert {p.stem for p in (CONF / "ablation").glob("*.yaml")} == set(EXPECTED)
    jobs = expand(standin_conf, name)
    assert len(jobs) == n_jobs
    assert len({tuple(sorted(j)) for j in jobs}) == n_jobs, "duplicate jobs"
    for key, values in axes.items():
        got = {o.split("=", 1)[1] for j in jobs for o in j if o.split("=", 1)[0] == key}
        assert got == values, f"{name}: {key} takes {got}, expected {values}"
    for job in jobs:
        cfg, choices = _job_choices(standin_conf, name, job)
        ov = dict(o.split("=", 1) for o in job)
        assert str(cfg.seed) == ov["seed"]
        if "+variant" in ov:
            assert (choices["encoder"], choices["temporal"]) == VARIANT_CHOICES[ov["+variant"]]
        for key in ("temporal", "color", "density", "trainer", "data"):
            if key in ov:
                assert choices[key] == ov[key]
        if "render.backend" in ov:
            assert cfg.render.backend == ov["render.backend"]
        if "gaussians.num_points" in ov:
            assert cfg.gaussians.num_points == int(ov["gaussians.num_points"])


def test_command_line_values_replace_the_files_axis(standin_conf):
    with initialize_config_dir(str(standin_conf), version_base="1.3"):
        cfg = compose("train", overrides=["+ablation=paper"], return_hydra_config=True)
    args = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()] + ["seed=5", "+variant=full,no_lstm"]
    (jobs,) = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(args), None)
    assert sorted(map(sorted, jobs)) == sorted(
        sorted(["+variant=" + v, "seed=5", "data=synthetic_sweep"]) for v in ("full", "no_lstm"))


def test_dynamics_commands_compose_and_each_changes_the_model():
    """The dynamics sweep is one command per mechanism (conf/ablation/dynamics.yaml's header): each composes in the
    real tree, builds its density strategy, and differs from the default model's config (a command that changes
    nothing would measure the default twice)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from realityavatar.config import _register

    _register()
    prefix = "#   realityavatar-train -m +ablation=dynamics"
    commands = [line[len(prefix):].split("(")[0].split() for line in (CONF / "ablation" / "dynamics.yaml").read_text()
                .splitlines() if line.startswith(prefix)]
    assert len(commands) >= 2 and commands[0] == [], commands  # the default model first, then one per mechanism
    with initialize_config_dir(str(CONF), version_base="1.3"):
        base = OmegaConf.to_container(compose("train", overrides=["+ablation=dynamics", "seed=0"]))
        for extra in commands[1:]:
            cfg = compose("train", overrides=["+ablation=dynamics", "seed=0", *extra])
            instantiate(cfg.density)
            assert OmegaConf.to_container(cfg) != base, extra


def _assert_real_tree_complete() -> None:
    """Every group a sweep uses has options in the real conf/: a missing one is a failure, not a skip."""
    groups = set(GROUPS) | {"variant", "ablation"}
    gaps = sorted(g for g in groups if not any((CONF / g).glob("*.yaml")))
    assert not gaps, f"conf/ groups without any option: {gaps}"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sweep_jobs_compose_in_the_real_tree(name):
    _assert_real_tree_complete()
    jobs = expand(CONF, name)
    assert len(jobs) == EXPECTED[name][0]
    for job in jobs:
        cfg, choices = _job_choices(CONF, name, job)
        ov = dict(o.split("=", 1) for o in job)
        if "+variant" in ov:
            assert (choices["encoder"], choices["temporal"]) == VARIANT_CHOICES[ov["+variant"]]
        for key in ("temporal", "color", "density", "trainer", "data"):
            if key in ov:
                assert choices[key] == ov[key]
        if "render.backend" in ov:
            assert cfg.render.backend == ov["render.backend"]
        assert cfg.seed == int(ov["seed"])
        # the job's density strategy builds with what the preset merged into it (density=off under preset=sweep's
        # density.prune_opacity crashed every density=off job of the budget sweep)
        from hydra.utils import instantiate

        from realityavatar.config import _register

        _register()  # the ${int_mul:...} resolver the training entry point registers
        instantiate(cfg.density)
        if name == "tiny":
            assert (cfg.iterations, cfg.gaussians.num_points, cfg.eval.save_video) == (30, 1500, False)


@pytest.mark.parametrize("real", [False, True], ids=["standin", "real"])
def test_launcher_configs_compose(standin_conf, real):
    conf = CONF if real else standin_conf
    if real:
        _assert_real_tree_complete()
    with initialize_config_dir(str(conf), version_base="1.3"):
        cfg = compose("train", overrides=["+ablation=paper", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
                      return_hydra_config=True)
        assert cfg.hydra.launcher._target_.endswith("JoblibLauncher") and cfg.hydra.launcher.n_jobs == 2
        cfg = compose("train", overrides=["+ablation=paper", "hydra/launcher=slurm_gpu",
                                          "hydra.launcher.partition=a100"], return_hydra_config=True)
        la = cfg.hydra.launcher
        assert la._target_.endswith("SlurmLauncher")
        assert (la.partition, la.gpus_per_node, la.timeout_min) == ("a100", 1, 240)
        assert la.submitit_folder.startswith("outputs/sweeps/paper/")
        cfg = compose("train", overrides=["+ablation=tiny"], return_hydra_config=True)
        assert cfg.hydra.launcher._target_.endswith("BasicLauncher")


# ----------------------------------------------------------------------------------------------- collectors

# variant -> scene -> PSNR per seed 0,1,2. Per-seed scene averages: full 29,30,31 (mean 30, std 1);
# no_zc 29.75,29.25,30.25 (mean 29.75, std 0.5: |Δ| 0.25 < 1 -> marked); no_lstm 26,26.2,26.4 (26.2, std 0.2).
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
    answer is known: 10000/off is the best (30.3), 5000/default (final 7000) is the smallest within 0.2 dB (30.15)."""
    root.mkdir(parents=True)
    (root / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {"task": ["+ablation=budget"]}}}))
    # (num_points, density) -> (final Gaussians, NV PSNR mean, train seconds)
    table = {(2000, "off"): (2000, 29.0, 50.0), (2000, "default"): (4000, 29.9, 60.0),
             (5000, "off"): (5000, 29.7, 70.0), (5000, "default"): (7000, 30.15, 80.0),
             (10000, "off"): (10000, 30.3, 100.0), (10000, "default"): (12000, 30.25, 110.0)}
    job = 0
    for (n, dens), (final, psnr, secs) in table.items():
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
                 "test/novel_view/psnr": psnr + (0.05 if seed else -0.05), "test/novel_pose/psnr": psnr - 1}
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
    assert pareto_main([str(sweep), "--out", str(tmp_path / "cli")]) == 0
    saved = json.loads((tmp_path / "cli" / "choice.json").read_text())
    assert saved["choice"]["num_gaussians_mean"] == 7000
    assert "choice (fewest Gaussians within 0.2 dB of the best)" in capsys.readouterr().out


@pytest.mark.slow
def test_tiny_sweep_end_to_end(tmp_path):
    """`realityavatar-train -m +ablation=tiny` trains both jobs; the collectors read what they wrote."""
    import subprocess

    _assert_real_tree_complete()
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "realityavatar.train", "-m", "+ablation=tiny", f"hydra.sweep.dir={sweep}"]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800, check=False)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert len(list(sweep.rglob("metrics.json"))) == 2
    csv, _ = collect(sweep, tmp_path / "table")
    assert list(csv["label"]) == ["full", "no_lstm"]
    assert csv["novel_view_psnr_mean"].notna().all() and csv["num_gaussians_mean"].gt(0).all()
    md = (tmp_path / "table" / "table.md").read_text()
    assert "realityavatar-train -m +ablation=tiny hydra.sweep.dir=" in md and "One seed (0)" in md
    assert len(pareto(sweep, tmp_path / "chart")) == 2


def test_probe_cloth_tracking_measures_sliding(tmp_path):
    """probe's cloth tracking: points glued to the cloth keep their material position (drift 0) while
    the cloth moves 20 cm; points left in place while the cloth slides 5 cm under them drift 5 cm; points far from
    the cloth at rest are not the garment's."""
    import numpy as np

    from realityavatar.analysis.probe import ClothTracker, cloth_tracking

    u, v = np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11), indexing="ij")
    flat = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)  # a 1 m square in z = 0
    faces = [(i * 11 + j, (i + 1) * 11 + j, i * 11 + j + 1) for i in range(10) for j in range(10)]
    faces += [((i + 1) * 11 + j, (i + 1) * 11 + j + 1, i * 11 + j + 1) for i in range(10) for j in range(10)]
    shift = [np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0]), np.array([0.2, 0.0, 0.1])]
    np.savez(tmp_path / "g.npz", vertices=np.stack([flat + s for s in shift]), faces=np.array(faces),
             frames=np.arange(4))
    tr = ClothTracker(tmp_path / "g.npz")
    pts = np.array([[0.3, 0.3, 0.0], [0.5, 0.6, 0.0], [0.5, 0.5, 0.5]])  # two on the cloth, one 50 cm above it
    phase = {0: "rest", 1: "rest", 2: "spin", 3: "settled"}
    glued = {f: tr.locate(f, pts + shift[f]) for f in range(4)}
    still = {f: tr.locate(f, pts + (shift[f] if f != 2 else 0.0)) for f in range(4)}
    g, s = cloth_tracking(glued, phase), cloth_tracking(still, phase)
    assert g[2][1] < 0.01 and g[3][1] < 0.01 and g[3][0] < 0.01  # cloth_p50, drift_p50 in metres
    assert abs(s[2][1] - 0.05) < 0.01 and s[3][1] < 0.01


def test_probe_novel_pose_phases_follow_the_root(tmp_path):
    """probe's held-out-sequence phases: rest until the root turns, spin while it turns by more than
    0.5 degrees a frame, after from the first still frame; PSNR per phase from per_frame.csv's novel-pose rows."""
    import pickle

    import numpy as np

    from realityavatar.analysis.probe import heading_stops, novel_pose_phases

    turn = [0, 0, 0, 5, 10, 10, 10, 3, 0, 0]  # degrees per frame about y
    angle, infos = 0.0, {}
    for i, t in enumerate(turn):
        angle += np.radians(t)
        for view in (0, 1):
            infos[f"frame_{100 + i:06d}_view_{view:02d}"] = {
                "poses": np.zeros(72, np.float32), "Rh": np.array([0.0, angle, 0.0], np.float32),
                "Th": np.zeros(3, np.float32)}
    mesh = tmp_path / "seq-novelpose"
    mesh.mkdir()
    with open(mesh / "mesh_infos.pkl", "wb") as f:
        pickle.dump(infos, f)
    phases = heading_stops(mesh)
    assert [phases[100 + i] for i in range(10)] == ["np_rest"] * 3 + ["np_spin"] * 5 + ["np_after"] * 2
    run = tmp_path / "run"
    run.mkdir()
    lines = ["split,frame,view,psnr,iou"] + [f"novel_pose,{100 + i},0,{20 + i},0.9" for i in range(10)]
    lines += ["novel_view,109,1,99,1.0"]
    (run / "per_frame.csv").write_text("\n".join(lines) + "\n")
    out = novel_pose_phases(run, mesh)
    assert out["novel_pose/np_after/psnr"] == 28.5 and out["novel_pose/np_rest/psnr"] == 21.0
    assert out["novel_pose/np_spin/images"] == 5


def test_probe_garment_shape_change_ignores_the_turn(tmp_path):
    """probe's garment shape change: a cloth turned and moved rigidly with its waist has none (a spin
    at a fixed pose), a hem swung 30 cm out shows it as the median vertex's displacement, and the reference is the
    given settled frame."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from realityavatar.analysis.probe import garment_curves

    theta, y = np.meshgrid(np.linspace(0, 2 * np.pi, 12, endpoint=False), np.linspace(0.0, -0.5, 6), indexing="ij")
    tube = np.stack([0.2 * np.cos(theta), y, 0.2 * np.sin(theta)], -1).reshape(-1, 3)  # waist ring at y = 0
    turned = Rotation.from_rotvec([0.0, 2.0, 0.0]).apply(tube) + [0.3, 0.0, -0.1]
    swung = tube.copy()
    low = swung[:, 1] < -0.15  # the lower four of six rings (two thirds of the vertices) move 0.3 m sideways
    swung[low, 0] += 0.3
    np.savez(tmp_path / "g.npz", vertices=np.stack([tube, turned, swung, tube]), faces=np.zeros((0, 3), int),
             frames=np.arange(4))
    c = garment_curves(tmp_path / "g.npz", settled_frame=3)
    assert c[0][2] < 1e-9 and c[1][2] < 1e-6  # same shape, turned 115 degrees and moved
    assert abs(c[2][2] - 0.3) < 1e-6
    assert garment_curves(tmp_path / "g.npz", settled_frame=2)[2][2] < 1e-9
