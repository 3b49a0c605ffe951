"""Shared fixtures: the tiny `ci` scene built once per session, and one run trained on it that the tests of
train / evaluate / resume / animate / export / view / the module read."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

# One thread: the suite is dominated by small ops, and 2 OpenMP threads stall badly when anything shares the cores
# (`make test` runs two pytest processes on 2 cores). The trainings and tools the tests start inherit it.
torch.set_num_threads(1)
os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session", autouse=True)
def no_weights_from_this_machine(tmp_path_factory):
    """LPIPS and the VGG19 loss look for weights in the lpips package and torch's hub cache (metrics.py): the suite
    sees neither, so its results do not depend on what this machine has installed or downloaded. Caches the package
    writes go to the session's folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TORCH_HOME", str(tmp_path_factory.mktemp("torch_home")))
        mp.setitem(sys.modules, "lpips", None)  # neither imported nor found by importlib.util.find_spec
        yield


@pytest.fixture(scope="session")
def scenes_root(tmp_path_factory) -> Path:
    """A scene root holding the `ci` preset; REALITYAVATAR_SCENES points at it for configs that read it."""
    from realityavatar.data.synthetic import build_scene

    root = tmp_path_factory.mktemp("scenes")
    build_scene("ci", root, seed=0)
    os.environ["REALITYAVATAR_SCENES"] = str(root)
    return root



@pytest.fixture(scope="session")
def trained_run(scenes_root, tmp_path_factory) -> tuple[Path, dict]:
    """(run folder, metrics) of one short training on the ci scene (tests.helpers.TRAINED_RUN), trained once.
    Tests may add files to the folder (evaluate, export) but must not change what the run wrote."""
    from realityavatar.config import compose, prepare_run
    from realityavatar.train import run
    from tests.helpers import TRAINED_RUN

    out = tmp_path_factory.mktemp("trained") / "run"
    metrics = run(*prepare_run(compose(TRAINED_RUN), out))
    return out, metrics
