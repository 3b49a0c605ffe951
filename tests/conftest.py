"""Shared fixtures: composing configs as the command line does, and the tiny `ci` scene built once per session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# One thread: the suite is dominated by small ops, and 2 OpenMP threads stall badly when anything shares the cores.
torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def scenes_root(tmp_path_factory) -> Path:
    """A scene root holding the `ci` preset; REALITYAVATAR_SCENES points at it for configs that read it."""
    from realityavatar.data.synthetic import build_scene

    root = tmp_path_factory.mktemp("scenes")
    build_scene("ci", root, seed=0)
    os.environ["REALITYAVATAR_SCENES"] = str(root)
    return root

