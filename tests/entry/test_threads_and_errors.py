"""One rule for threads at every entry point (runtime.set_threads), and a user's data or config error ending training
with its message alone."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from tests.helpers import ROOT


def test_set_threads_sets_torch_and_refuses_what_is_not_a_count():
    from realityavatar.runtime import set_threads

    try:
        torch.set_num_threads(2)
        assert set_threads(None) == 2 and set_threads("null") == 2  # torch's default kept
        assert set_threads("1") == 1 and torch.get_num_threads() == 1
        for bad in ("0", "-1", "two", "1.5"):
            with pytest.raises(ValueError, match=f"threads={bad}: expected a whole number >= 1"):
                set_threads(bad)
    finally:
        torch.set_num_threads(1)


@pytest.mark.parametrize("tool", ["evaluate", "export", "animate", "view"])
def test_every_entry_point_takes_threads(tool, tmp_path, capsys):
    """A bad count is refused by the entry point before the run is read (so `threads=` reaches set_threads there);
    a good one is applied before it (the run folder does not exist: the error after it is about the folder)."""
    import importlib

    main = importlib.import_module(f"realityavatar.{tool}").main
    assert main([f"run_dir={tmp_path / 'none'}", "threads=0"]) == 2
    assert "threads=0: expected a whole number >= 1" in capsys.readouterr().err
    try:
        torch.set_num_threads(2)
        try:
            rc = main([f"run_dir={tmp_path / 'none'}", "threads=1"])
        except FileNotFoundError:
            rc = None
        assert rc != 0 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(1)


@pytest.mark.parametrize("tool", ["oracle", "probe", "frames", "stability"])
def test_the_analysis_tools_take_threads(tool):
    """Each analysis tool that renders has --threads (runtime.add_threads_option), applied with set_threads."""
    r = subprocess.run([sys.executable, "-m", f"realityavatar.analysis.{tool}", "--help"], capture_output=True,
                       text=True, timeout=300, check=False, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0 and "--threads" in r.stdout and "runtime.set_threads" in r.stdout, r.stderr[-2000:]


def test_a_data_error_ends_training_with_its_message_and_the_trace_behind_hydra_full_error(tmp_path):
    cmd = [sys.executable, "-m", "realityavatar.train", "data=capture", f"data.root={tmp_path / 'captures'}",
           "data.sequence=me", "threads=1", f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False, cwd=ROOT, env=env)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    mine = [line for line in r.stderr.splitlines() if line.startswith("realityavatar-train:")]
    assert len(mine) == 1 and f"scene folder {tmp_path / 'captures' / 'me-train'} not found" in mine[0], r.stderr
    assert "HYDRA_FULL_ERROR=1 shows the trace" in mine[0]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False, cwd=ROOT,
                       env={**env, "HYDRA_FULL_ERROR": "1"})
    assert r.returncode == 1 and "Traceback" in r.stderr and "FileNotFoundError" in r.stderr, r.stderr[-3000:]


def test_a_config_error_ends_training_with_one_line_naming_the_key(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    r = subprocess.run([sys.executable, "-m", "realityavatar.train", "iterations=0", "threads=1",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=300,
                       check=False, cwd=ROOT, env=env)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert "realityavatar-train: iterations=0: expected a whole number of training steps >= 1" in r.stderr
