"""Issue 14 ("Nothing lost"): resume restores exactly, one run per folder, results survive evaluation failures,
settings and images are validated up front, clear messages, SIGINT/SIGKILL."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from realityavatar.config import compose

# Tiny runs of their own (the tests that need a trained run read conftest's trained_run): few Gaussians, no video,
# one FPS frame, two frames per test split.
TINY = ["data=synthetic_ci", "trainer=ci", "gaussians.num_points=400", "eval.save_video=false", "eval.save_images=2",
        "eval.fps_frames=1", "eval.fps_warmup=0", "eval.max_frames_per_split=2"]

from tests.helpers import ITERATIONS, TRAINED_RUN, train


def _cfg(out: Path, *overrides: str):
    cfg = compose([*TINY, *overrides])
    choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra") and v is not None}
    with open_dict(cfg):
        del cfg["hydra"]
        cfg.out_dir = str(out)
    return cfg, choices


def _run(out: Path, *overrides: str) -> dict:
    from realityavatar.train import run

    return run(*_cfg(out, *overrides))


def _state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def _log_steps(out: Path) -> list[int]:
    with open(out / "logs" / "csv" / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    return [int(r["step"]) for r in rows if r.get("train/loss")]


class _StopAt:
    """Patch AvatarModule.training_step to raise `exc` when it reaches `step` (an interrupted run)."""

    def __init__(self, monkeypatch, step: int, exc: BaseException):
        from realityavatar.model.module import AvatarModule

        orig = AvatarModule.training_step

        def stepper(module, batch, batch_idx):
            if module.global_step == step:
                raise exc
            return orig(module, batch, batch_idx)

        monkeypatch.setattr(AvatarModule, "training_step", stepper)


def test_resume_of_finished_run_changes_nothing_and_accumulates(trained_run, tmp_path):
    out, first = trained_run
    before = _state(out / "last.ckpt")
    again = tmp_path / "again"
    metrics = train(again, *TRAINED_RUN, f"ckpt_path={out / 'last.ckpt'}", "test_after_fit=false")
    after = _state(again / "last.ckpt")
    changed = [k for k, v in before["state_dict"].items() if not torch.equal(v, after["state_dict"][k])]
    assert not changed, f"resume with no steps left changed {changed}"
    assert metrics["iterations"] == ITERATIONS
    assert metrics["train_seconds"] >= first["train_seconds"], "train_seconds counts only the resumed part"
    steps = _log_steps(again)
    assert steps and min(steps) < ITERATIONS, "rows logged before the resume point are missing from logs/csv/metrics.csv"


@pytest.mark.parametrize("sampler", ["uniform", "hard_frames"])
def test_interrupted_and_resumed_equals_uninterrupted(scenes_root, tmp_path, monkeypatch, sampler):
    """A run stopped after its step-6 checkpoint and resumed ends where an uninterrupted run ends (bit-equal here),
    with one image per step in a uniform order and with frames drawn by their loss (hard_frames, the default: six
    one-camera training frames, so the crash falls in the second, loss-driven epoch). Both runs' samplers must end in
    the same state: with nearly equal scores a resume that lost them can still draw the same frames, so the draws
    alone would not show it. The uniform run's folder is moved before it resumes: its checkpoint and log folders
    (derived from the folder) differed from the saved config, and resume=true refused."""
    hard = ["data.max_train_frames=6", "data.train_views=[0]", "data.sampler.mix=0", "data.sampler.power=8"]
    opts = ["iterations=12", f"sampler={sampler}", *(hard if sampler == "hard_frames" else [])]
    ref = tmp_path / "ref"
    ref_metrics = _run(ref, *opts)
    cut = tmp_path / "cut"
    with monkeypatch.context() as m:
        _StopAt(m, 7, RuntimeError("simulated crash"))
        with pytest.raises(RuntimeError, match="simulated crash"):
            _run(cut, *opts)
    at6 = _state(cut / "last.ckpt")
    assert at6["global_step"] == 6
    if sampler == "uniform":  # a run folder moved (renamed, copied to another disk) resumes where it is now
        cut = Path(shutil.move(cut, tmp_path / "moved"))
    metrics = _run(cut, *opts, "resume=true")
    assert metrics["train_seconds"] > at6["callbacks"]["RunState"]["train_seconds"] > 0
    ref_ckpt, cut_ckpt = _state(ref / "last.ckpt"), _state(cut / "last.ckpt")
    # the training sampler ends in the same state (position; hard_frames: the frames' loss scores)
    (sa,), (sb,) = (c["loops"]["fit_loop"]["state_dict"]["combined_loader"] for c in (ref_ckpt, cut_ckpt))
    assert sa.keys() == sb.keys() and {k: v for k, v in sa.items() if k != "score"} == {
        k: v for k, v in sb.items() if k != "score"}, (sa, sb)
    np.testing.assert_allclose(sb.get("score", []), sa.get("score", []), rtol=1e-5, err_msg="sampler scores")
    a, b = ref_ckpt["state_dict"], cut_ckpt["state_dict"]
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)
    for split in ("novel_view", "novel_pose"):
        assert abs(metrics[f"test/{split}/psnr"] - ref_metrics[f"test/{split}/psnr"]) < 0.05
    steps = _log_steps(cut)
    assert len(steps) == len(set(steps)) and min(steps) < 6 and max(steps) > 6, steps


def test_a_run_stopped_by_its_time_limit_resumes_with_a_longer_one(scenes_root, tmp_path, monkeypatch):
    """trainer.max_time (a job's wall time) stops a run with a checkpoint; resume=true may raise the limit (it counts
    the earlier parts' time) and the run goes on to its iterations. Lightning's timer reads a clock that advances 1 s
    per reading here, so the first part stops after a few steps on any machine."""
    from pytorch_lightning.callbacks import timer

    ticks = iter(range(10**6))
    monkeypatch.setattr(timer, "time", type("Clock", (), {"monotonic": staticmethod(lambda: float(next(ticks)))}))
    out = tmp_path / "r"
    first = _run(out, "iterations=6", "+trainer.max_time=00:00:00:03", "test_after_fit=false")
    assert 0 < first["iterations"] < 6
    metrics = _run(out, "iterations=6", "+trainer.max_time=00:00:10:00", "resume=true", "test_after_fit=false")
    assert metrics["iterations"] == 6 and metrics["resumed_from"]["step"] == first["iterations"]


def test_second_run_into_a_run_folder_refuses(trained_run, tmp_path):
    out, _ = trained_run
    folder = tmp_path / "f"
    shutil.copytree(out, folder)
    saved = (folder / "config.yaml").read_text()
    ckpt_bytes = (folder / "last.ckpt").read_bytes()
    # hydra rewrites .hydra/ before a run starts; a refused run puts the owner's record back
    (folder / ".hydra-run").mkdir()
    (folder / ".hydra-run" / "overrides.yaml").write_text("- seed=0\n")
    (folder / ".hydra").mkdir()
    (folder / ".hydra" / "overrides.yaml").write_text("- seed=3\n")
    with pytest.raises(FileExistsError, match=r"resume=true.*overwrite=true"):
        _run(folder, "iterations=8", "seed=3")
    # a failing run into the folder does not touch it either
    with pytest.raises(ValueError, match="data.image_scale"):
        _run(folder, "iterations=8", "data.image_scale=0", "overwrite=true")
    assert (folder / "config.yaml").read_text() == saved
    assert (folder / "last.ckpt").read_bytes() == ckpt_bytes
    assert (folder / ".hydra" / "overrides.yaml").read_text() == "- seed=0\n"


def test_config_written_only_once_the_run_is_valid(scenes_root, tmp_path):
    with pytest.raises(ValueError, match="data.max_train_frames"):
        _run(tmp_path / "new", "iterations=8", "data.max_train_frames=0")
    assert not (tmp_path / "new" / "config.yaml").exists()


def test_a_gpu_trainer_without_cuda_stops_before_the_scene_is_read(tmp_path, monkeypatch):
    """`+experiment=paper_scale` on a machine without CUDA: named before its 512² scene is built (minutes), nothing
    written; the same command on the CPU trainer gets past the check."""
    from realityavatar import train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setenv("REALITYAVATAR_SCENES", str(tmp_path / "scenes"))
    built = []
    monkeypatch.setattr(train, "_run", lambda *a, **k: built.append(a) or {})
    # trainer=gpu as the experiment sets it (after TINY's trainer=ci, the later value wins)
    with pytest.raises(RuntimeError, match=r"trainer\.accelerator=gpu.*trainer=cpu render\.backend=numba"):
        train.run(*_cfg(tmp_path / "run", "+experiment=paper_scale", "trainer=gpu"))
    assert not built and not (tmp_path / "run").exists() and not (tmp_path / "scenes").exists()
    train.run(*_cfg(tmp_path / "cpu", "+experiment=paper_scale", "trainer=cpu"))
    assert len(built) == 1


def test_save_images_zero_and_eval_failure_keep_training_results(scenes_root, tmp_path, monkeypatch):
    out = tmp_path / "z"
    metrics = _run(out, "iterations=3", "eval.save_images=0")
    assert "test/novel_view/psnr" in metrics and not list((out / "images").glob("*.png"))
    from realityavatar import evaluate

    def broken(*a, **k):
        raise OSError("image novel_pose/x.png is corrupt")

    monkeypatch.setattr(evaluate, "write_outputs", broken)
    out2 = tmp_path / "broken"
    with pytest.raises(Exception, match="corrupt"):
        _run(out2, "iterations=3")
    assert (out2 / "last.ckpt").is_file()
    saved = json.loads((out2 / "metrics.json").read_text())
    assert saved["iterations"] == 3 and "train_seconds" in saved and "test/novel_view/psnr" in saved
    assert "corrupt" in json.dumps(saved.get("evaluation_errors"))


def test_numeric_settings_name_the_key(scenes_root, tmp_path):
    for value in ("0", "abc", "-5", "-1", "2.5"):
        with pytest.raises(ValueError, match=r"^iterations"):
            _run(tmp_path / f"it{value}", f"iterations={value}")
    with pytest.raises(ValueError, match=r"data\.image_scale"):
        _run(tmp_path / "scale", "iterations=4", "data.image_scale=0")
    with pytest.raises(ValueError, match=r"eval\.save_images"):
        _run(tmp_path / "si", "iterations=4", "eval.save_images=-1")
    assert not any(tmp_path.rglob("config.yaml"))


@pytest.mark.parametrize("damage", ["corrupt", "wrong_size"])
def test_bad_training_image_found_before_step_0(scenes_root, tmp_path, damage, body_model, caplog):
    import logging

    from PIL import Image

    from realityavatar.data.datamodule import AvatarDataModule
    from realityavatar.data.i3d import I3DReader

    for p in scenes_root.glob("skirt_spin_ci-*"):
        (shutil.copytree if p.is_dir() else shutil.copy)(p, tmp_path / p.name)
    victim = max((tmp_path / "skirt_spin_ci-train" / "images").glob("*.png"))
    if damage == "corrupt":
        victim.write_bytes(victim.read_bytes()[:100])
    else:
        Image.open(victim).resize((32, 32)).save(victim)
    dm = AvatarDataModule(str(tmp_path), "skirt_spin_ci", I3DReader(1), body=body_model, window_len=4, window_step=2)
    with pytest.raises((OSError, ValueError), match=victim.name):
        dm.setup("fit")
    good = AvatarDataModule(str(scenes_root), "skirt_spin_ci", I3DReader(1), body=body_model, window_len=4, window_step=2)
    with caplog.at_level(logging.INFO, logger="realityavatar.data.datamodule"):
        good.setup("fit")
    assert any("checked" in r.getMessage() and " s" in r.getMessage() for r in caplog.records)


@pytest.fixture(scope="module")
def body_model():
    from realityavatar.body import build_body

    return build_body("mannequin")


def test_truncated_checkpoint_and_bad_pose_files_are_named(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main
    from realityavatar.build import load_run

    out, _ = trained_run
    run = tmp_path / "r"
    run.mkdir()
    shutil.copy(out / "config.yaml", run / "config.yaml")
    data = (out / "last.ckpt").read_bytes()
    (run / "last.ckpt").write_bytes(data[: len(data) // 2])
    with pytest.raises(Exception, match=r"last\.ckpt.*(truncated|corrupt)"):
        load_run(run)
    F = 3
    np.savez(tmp_path / "rh.npz", poses=np.zeros((F, 72), np.float32), Rh=np.zeros((F, 2)), Th=np.zeros((F, 3)))
    with pytest.raises(ValueError, match=r"rh\.npz.*'Rh'.*\[3,3\]"):
        animate_main([f"run_dir={out}", f"poses={tmp_path / 'rh.npz'}"])
    np.savez(tmp_path / "empty.npz", poses=np.zeros((0, 72), np.float32))
    with pytest.raises(ValueError, match=r"empty\.npz.*'poses'.*no frames"):
        animate_main([f"run_dir={out}", f"poses={tmp_path / 'empty.npz'}"])


def test_sigint_keeps_checkpoint_and_exits_130(scenes_root, tmp_path, monkeypatch, capsys):
    out = tmp_path / "int"
    _StopAt(monkeypatch, 3, KeyboardInterrupt())  # Ctrl-C lands inside a step: the step-3 checkpoint is kept
    with pytest.raises(SystemExit) as e:
        _run(out, "iterations=12")
    assert e.value.code == 130
    assert "checkpoint kept" in capsys.readouterr().err
    assert _state(out / "last.ckpt")["global_step"] == 3


def test_sigint_signal_stops_after_the_step_and_saves(scenes_root, tmp_path, monkeypatch, capsys):
    from realityavatar.model.module import AvatarModule

    orig = AvatarModule.training_step

    def step(module, batch, batch_idx):
        if module.global_step == 4:
            os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C while step 4 runs
        return orig(module, batch, batch_idx)

    monkeypatch.setattr(AvatarModule, "training_step", step)
    out = tmp_path / "sig"
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN when the suite runs as a background job
    with pytest.raises(SystemExit) as e:
        _run(out, "iterations=12")
    assert e.value.code == 130 and "checkpoint kept" in capsys.readouterr().err
    assert _state(out / "last.ckpt")["global_step"] == 5  # step 4 finished, then saved
    assert signal.getsignal(signal.SIGINT) is before  # the run's handler is gone again


def test_stale_scene_temp_folders_are_removed(scenes_root):
    """A build's temporary folder left by a dead process is removed by the next build into the root (also when that
    build finds its scene cached, as here in the session's scene root); a live process's is kept."""
    from realityavatar.data.synthetic import build_scene

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = scenes_root / f".tmp-skirt_spin_ci-{dead.pid}-abc"
    (stale / "skirt_spin_ci-train").mkdir(parents=True)
    live = scenes_root / f".tmp-skirt_spin_ci-{os.getpid()}-def"
    live.mkdir()
    try:
        build_scene("ci", scenes_root, seed=0, progress=False)
        assert not stale.exists() and live.exists()
    finally:
        shutil.rmtree(stale, ignore_errors=True)
        shutil.rmtree(live, ignore_errors=True)


KILL_AT = r"""
import os, signal, sys
from realityavatar.model.module import AvatarModule
orig = AvatarModule.training_step
def step(self, batch, i):
    if self.global_step == int(os.environ["KILL_AT_STEP"]):
        os.kill(os.getpid(), signal.SIGKILL)
    return orig(self, batch, i)
AvatarModule.training_step = step
from realityavatar.train import main
sys.argv = ["realityavatar-train", *sys.argv[1:]]
main()
"""


@pytest.mark.slow
def test_sigkill_resume_matches_uninterrupted(scenes_root, tmp_path):
    """SIGKILL mid-training (after the step-10 checkpoint), resume: same parameters and metrics as one run. The killed
    run is a process of its own (SIGKILL ends it where it stands); the uninterrupted run and the resume run here."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "REALITYAVATAR_SCENES": str(scenes_root)}
    args = ["iterations=20", "threads=1"]
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    _run(ref, *args)
    r = subprocess.run([sys.executable, "-c", KILL_AT, *TINY, *args, f"hydra.run.dir={cut}"],
                       env={**env, "KILL_AT_STEP": "13"}, capture_output=True, text=True, timeout=900, check=False)
    assert r.returncode == -signal.SIGKILL, r.stderr[-3000:]
    assert _state(cut / "last.ckpt")["global_step"] == 10 and not (cut / "metrics.json").exists()
    _run(cut, *args, "resume=true")
    a, b = _state(ref / "last.ckpt")["state_dict"], _state(cut / "last.ckpt")["state_dict"]
    diffs = {k: float((a[k] - b[k]).abs().max()) for k in a if a[k].is_floating_point()}
    assert max(diffs.values()) <= 1e-6, max(diffs.items(), key=lambda kv: kv[1])
    ma, mb = json.loads((ref / "metrics.json").read_text()), json.loads((cut / "metrics.json").read_text())
    for split in ("novel_view", "novel_pose"):
        assert abs(ma[f"test/{split}/psnr"] - mb[f"test/{split}/psnr"]) <= 0.05
    assert mb["iterations"] == 20 and mb["train_seconds"] > 0


def test_a_run_folder_of_an_older_version_names_its_config_and_the_commit(trained_run, tmp_path):
    """A config.yaml with a key that a removed option had (gaussians.deform_code_dim, before the consolidation;
    color.use_fmt, up to 3b9168b) stops with an error naming the file and the commit that reads it (the one its
    metrics.json records), not hydra's instantiation trace."""
    import yaml

    from realityavatar.build import load_avatar, load_run

    out, _ = trained_run
    run = tmp_path / "old"
    run.mkdir()
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    cfg["gaussians"]["deform_code_dim"] = 0
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    shutil.copy(out / "last.ckpt", run / "last.ckpt")
    with pytest.raises(ValueError, match=r"(?s)old/config\.yaml does not build.*deform_code_dim.*git checkout c46aa26"):
        load_run(run)
    del cfg["gaussians"]["deform_code_dim"]
    cfg["color"]["use_fmt"] = True
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    (run / "metrics.json").write_text(json.dumps({"commit": "3b9168b-dirty"}))
    for load in (load_run, load_avatar):  # evaluate's and export's, view's, animate's
        with pytest.raises(ValueError, match=r"(?s)old/config\.yaml does not build.*use_fmt.*git checkout 3b9168b$"):
            load(run)


def test_compile_trains_through_the_compiled_path(scenes_root, tmp_path, monkeypatch):
    """compile=default trains and evaluates through torch.compile'd deform, shade and loss, across density control's
    changes of the Gaussian count; an unknown mode names the key before the run folder is taken. Dynamo with the
    aot_eager backend stands in for inductor (the same graphs, no C++ compile)."""
    compile_, calls = torch.compile, []

    def traced(f, **kw):
        g = compile_(f, backend="aot_eager")

        def wrapper(*a, **k):
            calls.append(f.__name__)
            return g(*a, **k)
        return wrapper

    monkeypatch.setattr(torch, "compile", traced)
    from realityavatar.model.module import DYNAMO_CONFIG

    with pytest.raises(ValueError, match="compile: expected one of none, default"):
        _run(tmp_path / "bad", "compile=fast")
    assert not (tmp_path / "bad" / "config.yaml").exists()
    # compile_path sets dynamo's process-wide settings: put back after the run
    with torch._dynamo.config.patch(**{k: getattr(torch._dynamo.config, k) for k in DYNAMO_CONFIG}):
        m = _run(tmp_path / "r", "compile=default", "iterations=8", "density.refine_every=3", "test_after_fit=false")
    assert m["iterations"] == 8 and {"deform", "shade", "loss"} <= set(calls), set(calls)
    assert calls.count("loss") == 8  # every training step's losses ran compiled


def test_a_run_with_its_training_set_on_the_device_trains_as_one_without(scenes_root, tmp_path, monkeypatch):
    """data.device_cache (a GPU's training set kept there, data/device_cache.py DeviceSamples) is invisible to training:
    the trainer takes every batch's tensors from the kept set (TrainingData's transfer hook), the steps leave the
    kept tensors as they were (a batch of one sample is a view of them), and the run ends bit-equal to one whose
    batches are collated and copied. Kept on the CPU here, where a run would not keep it."""
    from realityavatar.data.datamodule import AvatarDataModule
    from realityavatar.data.device_cache import DeviceSamples

    ref = _run(tmp_path / "host", "iterations=4", "data.device_cache=false")
    gathered = []  # (the kept set, index, its tensors as they were when gathered)
    gather = DeviceSamples.gather

    def spy(self, index):
        gathered.append((self, index, [{k: v.clone() for k, v in self.tensors[i].items()} for i in index]))
        return gather(self, index)

    monkeypatch.setattr(AvatarDataModule, "_store_device", lambda self: torch.device("cpu"))
    monkeypatch.setattr(DeviceSamples, "gather", spy)
    metrics = _run(tmp_path / "dev", "iterations=4")
    assert len(gathered) == 4
    for kept, index, before in gathered:
        for i, row in zip(index, before):
            assert all(torch.equal(kept.tensors[i][k], v) for k, v in row.items()), f"sample {i} changed in place"
    a, b = (_state(tmp_path / d / "last.ckpt")["state_dict"] for d in ("host", "dev"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert metrics["test/novel_view/psnr"] == ref["test/novel_view/psnr"]
    assert ref["training_set"] == "host" and metrics["training_set"]["device"] == "cpu"  # metrics.json says where


def test_reading_a_run_folder_imports_no_lightning(trained_run, tmp_path):
    """runs.py, build.load_avatar (canonical export) and the data a run's poses and cameras come from (build_data:
    data/datamodule.py AvatarDataModule, a plain object) import no Lightning: posed export (frame=, frames=), animate
    and the viewer's loading run in a process that never imports it. Training's Lightning pieces are train.py's
    (RunState) and data/lightning.py's (TrainingData, SamplerFeedback), which only training imports."""
    from tests.entry.test_view import free_port

    out, _ = trained_run
    script = (
        "import sys; from realityavatar.build import load_avatar; import realityavatar.runs\n"
        "from realityavatar import animate, export\n"
        "from realityavatar.view import compose_view, load_viewer\n"
        f"run, tmp = {str(out)!r}, {str(tmp_path)!r}\n"
        "load_avatar(run)\n"
        "assert export.main([f'run_dir={run}', 'frame=3', f'out={tmp}/posed.ply']) == 0\n"
        "assert export.main([f'run_dir={run}', 'frames=2:4', f'out={tmp}/frames']) == 0\n"
        "assert animate.main([f'run_dir={run}', 'views=0', f'out={tmp}/a.gif']) == 0\n"
        f"viewer = load_viewer(*compose_view([f'run_dir={{run}}', 'port={free_port()}']))\n"
        "assert viewer.sequences and viewer.dm.scene is not None\n"
        "viewer.close()\n"
        "print([m for m in sys.modules if m.split('.')[0] in ('pytorch_lightning', 'lightning', 'lightning_fabric')])")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert (tmp_path / "posed.ply").is_file() and len(list((tmp_path / "frames").glob("*.ply"))) == 2
