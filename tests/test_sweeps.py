"""Sweep configs (conf/ablation) expand to the intended jobs and compose; launcher configs compose; a tiny sweep
trains end to end and the collectors read what it wrote."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser

import realityavatar.config  # noqa: F401  registers the resolvers (int_mul, ...) the real tree's configs use
from realityavatar.analysis.collect import collect
from realityavatar.analysis.pareto import pareto
from tests.helpers import ROOT

CONF = ROOT / "conf"


SEEDS = {"0", "1", "2"}


EXPECTED = {
    "paper": (12, {"+variant": {"full", "no_zc", "no_lstm", "no_split"}, "seed": SEEDS, "data": {"synthetic_sweep"}}),
    "temporal": (9, {"temporal": {"lstm", "gru", "none"}, "seed": SEEDS}),
    "color": (6, {"color": {"mlp", "sh"}, "seed": SEEDS}),
    "budget": (9, {"gaussians.num_points": {"2000", "5000", "10000"}, "seed": SEEDS}),  # on `make demo`'s recipe
    "speed": (18, {"iterations": {"500", "1000", "2000"}, "data.image_scale": {"0.5", "1.0"}, "render.backend": {"numba"},
                   "seed": SEEDS}),
    "tiny": (2, {"+variant": {"full", "no_lstm"}, "seed": {"0"}, "data": {"synthetic_ci"}, "trainer": {"ci"}}),
    "scenes": (8, {"+variant": {"full", "no_lstm"}, "seed": {"0"},
                   "data": {"synthetic_sweep", "synthetic_sweep_dress_spin", "synthetic_sweep_skirt_flap",
                            "synthetic_sweep_dress_walk"}}),
    "dynamics": (3, {"seed": SEEDS, "data": {"synthetic_sweep"}}),  # its variants: one override per command
}


VARIANT_CHOICES = {"full": ("latentbone", "lstm"), "no_zc": ("no_zc", "lstm"),
                   "no_lstm": ("latentbone", "none"), "no_split": ("no_split", "lstm")}


def _assert_job_has_its_overrides(cfg, choices, ov: dict) -> None:
    """The composed job chose what its overrides say: variant rows, group options, the render backend."""
    if "+variant" in ov:
        assert (choices["encoder"], choices["temporal"]) == VARIANT_CHOICES[ov["+variant"]]
    for key in ("temporal", "color", "density", "trainer", "data"):
        if key in ov:
            assert choices[key] == ov[key]
    if "render.backend" in ov:
        assert cfg.render.backend == ov["render.backend"]


GROUPS = {
    "data": ["synthetic_ci", "synthetic_demo", "synthetic_sweep", "synthetic_sweep_dress_spin",
             "synthetic_sweep_skirt_flap", "synthetic_sweep_dress_walk"], "sampler": ["uniform", "hard_frames"], "body": ["mannequin", "smpl"],
    "gaussians": ["default"], "encoder": ["latentbone", "no_split", "no_zc"], "temporal": ["lstm", "gru", "none"],
    "deformer": ["motion_trend"], "silhouette": ["chamfer", "none"], "skinning": ["mlp", "grid"], "color": ["mlp", "sh"],
    "shading": ["irradiance", "none"], "density": ["default", "off"], "sheet": ["none", "skirt", "skirt_slide"],
    "loss": ["default"], "render": ["default"], "optim": ["default"], "trainer": ["cpu", "gpu", "ci"],
}


@pytest.fixture(autouse=True)
def _clear_hydra():
    GlobalHydra.instance().clear()
    yield
    GlobalHydra.instance().clear()


@pytest.fixture(scope="module")
def standin_conf(tmp_path_factory) -> Path:
    """conf/ with this project's ablation, variant, preset, experiment and launcher files and one-line stand-ins for every other option."""
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
    for sub in ("ablation", "variant", "preset", "experiment", "hydra/launcher"):
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


def composed_jobs(jobs: list[list[str]]) -> list[list[str]]:
    """The jobs worth composing: one per setting apart from the seed (the seed changes only `seed`; the expansion
    checks its values), and the last job, whose seed is another than the first ones'."""
    seen, out = set(), []
    for job in jobs:
        key = tuple(sorted(o for o in job if not o.startswith("seed=")))
        if key not in seen:
            seen.add(key)
            out.append(job)
    return out + ([jobs[-1]] if jobs[-1] not in out else [])


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
    for job in composed_jobs(jobs):
        cfg, choices = _job_choices(standin_conf, name, job)
        ov = dict(o.split("=", 1) for o in job)
        assert str(cfg.seed) == ov["seed"]
        _assert_job_has_its_overrides(cfg, choices, ov)
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
    for job in composed_jobs(jobs):
        cfg, choices = _job_choices(CONF, name, job)
        ov = dict(o.split("=", 1) for o in job)
        _assert_job_has_its_overrides(cfg, choices, ov)
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
        cfg = compose("train", overrides=["+ablation=paper", "hydra/launcher=slurm_cpu",
                                          "hydra.launcher.cpus_per_task=2"], return_hydra_config=True)
        la = cfg.hydra.launcher
        assert la._target_.endswith("SlurmLauncher")
        # no GPU request, the cluster's default partition, and the job's threads follow the CPUs it asked for
        assert (la.partition, la.gpus_per_node, la.tasks_per_node) == (None, None, 1)
        assert la.setup == ["export OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2"]
        cfg = compose("train", overrides=["+ablation=tiny"], return_hydra_config=True)
        assert cfg.hydra.launcher._target_.endswith("BasicLauncher")


@pytest.mark.slow
def test_tiny_sweep_end_to_end(tmp_path):
    """`realityavatar-train -m +ablation=tiny` trains both jobs; the collectors read what they wrote. The jobs are
    cut shorter than the preset on the command line (what is checked is the launcher and the collectors)."""
    import subprocess

    _assert_real_tree_complete()
    sweep = tmp_path / "sweep"
    short = ["iterations=4", "gaussians.num_points=300", "eval.max_frames_per_split=2", "eval.save_images=0",
             "eval.fps_frames=1", "eval.fps_warmup=0"]
    cmd = [sys.executable, "-m", "realityavatar.train", "-m", "+ablation=tiny", *short, f"hydra.sweep.dir={sweep}"]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800, check=False)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert len(list(sweep.rglob("metrics.json"))) == 2
    csv, _ = collect(sweep, tmp_path / "table")
    assert list(csv["label"]) == ["full", "no_lstm"]
    assert csv["novel_view_psnr_mean"].notna().all() and csv["num_gaussians_mean"].gt(0).all()
    md = (tmp_path / "table" / "table.md").read_text()
    assert f"realityavatar-train -m +ablation=tiny {' '.join(short)} hydra.sweep.dir=" in md and "One seed (0)" in md
    assert len(pareto(sweep, tmp_path / "chart")) == 2
