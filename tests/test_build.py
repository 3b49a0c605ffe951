"""Rebuilding a run from its folder: overrides move the keys interpolated from them."""

from __future__ import annotations

import pytest


def test_rebuild_overrides_move_interpolated_keys(trained_run):
    """evaluate/animate/export apply key=value overrides as train does: keys interpolated from them follow."""
    from realityavatar.build import load_run

    out, _ = trained_run
    cfg, _, _ = load_run(out, ["seed=5", "iterations=1000"])
    assert cfg.gaussians.seed == 5 and cfg.density.seed == 5  # ${seed}
    assert cfg.schedule.skin_switch == 100 and cfg.density.refine_start == 100  # ${int_mul:${iterations},0.1}
    assert cfg.data.root == load_run(out)[0].data.root  # environment values stay those of the run
    # Hydra's "+key=value" adds a key, as on the train command line (it used to land under a key named "+data").
    cfg, _, _ = load_run(out, ["+data.build_overrides={ambient: 1.0, diffuse: 0.0}"])
    assert cfg.data.build_overrides.ambient == 1.0 and "+data" not in cfg
    with pytest.raises(ValueError, match="key=value"):
        load_run(out, ["~data.root"])
