"""stability: the extreme-pose check measured against the training frames' own scales."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.model.test_sheet import _ci_sheet_module


def test_stability_report_measures_extreme_poses_against_the_training_frames(scenes_root):
    """The stability report's extreme-pose check reports the largest scale over the training frames' own pose
    windows (every training frame, not only the first) as the reference its growth is measured against."""
    from torch.utils.data import default_collate

    from realityavatar.analysis.stability import extreme_poses, training_scale_max, training_scales

    _, dm, module = _ci_sheet_module()
    module.on_fit_start()
    ds = dm.datasets["train"]
    per_frame = {}
    with torch.no_grad():
        for i, rec in enumerate(ds.records):
            if rec.frame not in per_frame:
                b = default_collate([ds[i]])
                per_frame[rec.frame] = float(module.avatar.deform(b)["scales"].max())
    assert len(per_frame) > 1 and max(per_frame.values()) > min(per_frame.values())  # the sheet stretches per frame
    got = training_scales(module, dm, batch=5)
    assert got.keys() == per_frame.keys()
    assert all(got[f] == pytest.approx(per_frame[f], rel=1e-5) for f in per_frame)
    assert training_scale_max(module, dm) == pytest.approx(max(per_frame.values()), rel=1e-5)
    e = extreme_poses(module, dm, n=4)
    assert e["finite"] and e["max_training_scale_m"] == pytest.approx(max(per_frame.values()), rel=1e-5)
    assert e["scale_growth_vs_training"] == pytest.approx(e["max_scale_m"] / e["max_training_scale_m"], rel=1e-6)
    r = e["_renders"]  # the joint-limit poses (every second one of n), drawn for the report's extreme_poses.png
    assert r.shape[0] == 2 and r.dtype == np.uint8 and r.shape[-1] == 3 and r.max() > 0


def test_stop_frames_of_a_capture_without_events_are_where_its_phases_stop(scenes_root):
    """A real capture has no event list: the stability report's stops are where the evaluation's phases (read from
    the poses) go from the spin to the second after it, within 2 frames of the simulator's own stop on the CI scene."""
    from hydra.utils import instantiate

    from realityavatar.analysis.stability import stop_frames
    from realityavatar.build import build_data
    from realityavatar.config import compose

    cfg = compose(["data=synthetic_ci", "trainer=ci"])
    dm = build_data(cfg, instantiate(cfg.body))
    events = dm.scene.meta["motion"]["events"]
    assert stop_frames(dm) == [events["spin_stop_frame"]]
    dm.scene.meta["motion"]["events"] = {}  # as a capture reads
    stops = stop_frames(dm)
    assert len(stops) == 1 and abs(stops[0] - events["spin_stop_frame"]) <= 2
    phases = dm.scene.poses.motion_phases(dm.scene.poses.frames, dm.fps)
    assert phases[stops[0]] == "after" and phases[stops[0] - 1] == "spin"


def test_extreme_poses_simulate_a_physics_garment_into_each_pose(scenes_root):
    """sheet=physics: each extreme pose is reached by a simulated motion (none blows up on the ci skirt), its renders
    and statistics come from that cloth, and the dataset's motion is simulated again afterwards."""
    from hydra.utils import instantiate

    from realityavatar.analysis.stability import extreme_poses, ramp_into
    from realityavatar.build import build_data, build_module
    from realityavatar.config import compose
    from tests.model.test_garment import FAST

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300", "sheet=physics", *FAST])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    module.on_fit_start()
    g = module.avatar.sheet
    before = g.track.clone()
    out = extreme_poses(module, dm, n=4, show=1)
    assert out["finite"] and out["garment_blowups"] == [] and out["poses"] == 4
    assert out["_renders"].shape[0] == 1
    assert torch.equal(g.track_frames, torch.as_tensor(dm.scene.poses.frames)) and torch.allclose(g.track, before)
    table = ramp_into(torch.zeros(24, 3), torch.zeros(3), torch.ones(3, 24, 3), torch.ones(3, 3))
    assert len(table) == 13 and torch.equal(table.poses[-3:], torch.ones(3, 24, 3))
    assert torch.equal(table.poses[0], torch.zeros(24, 3))
