"""Issue 58, item 9: a run folder is read as data. A last.ckpt that also carries a pickled object (one whose
unpickling creates a file) is refused, naming the file, by every tool that opens a run folder, and never runs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from tests.helpers import TRAINED_RUN, train


class _Payload:
    """Unpickling this calls open(marker, "w"): the file appears only if a loader ran the checkpoint's code."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _planted(trained_run, tmp_path: Path) -> tuple[Path, Path, dict]:
    """A copy of the suite's run whose last.ckpt also holds a _Payload; (run folder, marker, the clean checkpoint)."""
    src, _ = trained_run
    run = tmp_path / "shared_run"
    shutil.copytree(src, run, ignore=shutil.ignore_patterns("images", "videos", "eval", "animations", "export"))
    clean = torch.load(src / "last.ckpt", map_location="cpu", weights_only=True)
    marker = tmp_path / "code_ran"
    torch.save({**clean, "note": _Payload(marker)}, run / "last.ckpt")
    assert not marker.exists()
    return run, marker, clean


def test_a_checkpoint_carrying_code_is_refused_by_every_tool(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main
    from realityavatar.build import load_avatar, load_run
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.export import main as export_main

    run, marker, _ = _planted(trained_run, tmp_path)
    tools = {
        "realityavatar-export": lambda: export_main([f"run_dir={run}", f"out={tmp_path / 'a.ply'}"]),
        "realityavatar-evaluate": lambda: evaluate_main([f"run_dir={run}", "eval.save_video=false"]),
        "realityavatar-view (load_avatar)": lambda: load_avatar(run),
        "load_run (the probes)": lambda: load_run(run),
        "realityavatar-animate": lambda: animate_main([f"run_dir={run}", "views=0", f"out={tmp_path / 'a.gif'}"]),
        "realityavatar-train resume=true": lambda: train(run, *TRAINED_RUN, "resume=true"),
    }
    for name, tool in tools.items():
        try:
            tool()
            error = "none (it went on)"
        except ValueError as e:
            error = str(e)
        assert not marker.exists(), f"{name} ran code from {run / 'last.ckpt'}"
        assert f"checkpoint {run / 'last.ckpt'} refused: it holds io.open" in error, f"{name}: error {error}"


def test_lightnings_resume_reads_the_checkpoint_as_data_too(trained_run, tmp_path, monkeypatch):
    """Resume reads last.ckpt twice: read_checkpoint (above) and Lightning's trainer.fit(ckpt_path=...). With the first
    read made to see the clean checkpoint, Lightning's own load must still refuse the object, also where torch.load
    defaults to unpickling anything (torch < 2.6, or TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 as here): Lightning passes
    fit's weights_only to torch.load and leaves None to torch's default."""
    import pickle

    from realityavatar import runs

    run, marker, clean = _planted(trained_run, tmp_path)
    monkeypatch.setattr(runs, "read_checkpoint", lambda path: clean)
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed"):
        train(run, *TRAINED_RUN, "resume=true")
    assert not marker.exists(), "Lightning's resume ran code from last.ckpt"


def test_our_checkpoints_load_as_data(trained_run):
    from realityavatar.runs import read_checkpoint

    state = read_checkpoint(trained_run[0] / "last.ckpt")
    assert state["global_step"] > 0 and state["realityavatar"]
