"""The pose table: windows at the sequence start and on subsampled tables, NaN refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from realityavatar.data.poses import PoseTable


def test_pose_window_clamps_at_sequence_start():
    frames = np.arange(10, 20)
    poses = torch.arange(10, 20, dtype=torch.float32)[:, None, None].expand(10, 24, 3)
    table = PoseTable(frames, poses, torch.zeros(10, 3))
    p, t = table.window(12, window_len=4, window_step=1)
    assert t.shape == (4, 3)
    assert p[:, 0, 0].tolist() == [10, 10, 11, 12]  # t-3 = 9 is before the start: clamped to 10
    p, _ = table.window(19, window_len=3, window_step=4)
    assert p[:, 0, 0].tolist() == [11, 15, 19]
    p, _ = table.window(10, window_len=6, window_step=25)
    assert p[:, 0, 0].tolist() == [10] * 6


def test_pose_window_on_subsampled_table_takes_latest_earlier_frame():
    frames = np.array([0, 10, 20, 30])
    table = PoseTable(frames, torch.as_tensor(frames, dtype=torch.float32)[:, None, None].expand(4, 24, 3),
                      torch.zeros(4, 3))
    p, _ = table.window(30, window_len=3, window_step=7)  # targets 16, 23, 30
    assert p[:, 0, 0].tolist() == [10, 20, 30]
    with pytest.raises(KeyError, match="frame 25 has no pose"):
        table.window(25, 2, 1)


def test_pose_table_rejects_nan():
    poses = torch.zeros(3, 24, 3)
    poses[1, 4, 2] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite .* frames \[8\]"):
        PoseTable([7, 8, 9], poses, torch.zeros(3, 3), source="test")


def _ramp(frames, dense_every=None, source="ramp.pkl"):
    """A table whose pose[...,0] is its frame id, so a window reads as the frames it took."""
    frames = np.asarray(frames)
    poses = torch.as_tensor(frames, dtype=torch.float32)[:, None, None].expand(len(frames), 24, 3)
    return PoseTable(frames, poses, torch.zeros(len(frames), 3), source=source, dense_every=dense_every)


def test_dense_window_reads_exact_frames_and_clamps_at_frame_zero_only():
    """A dense table (frameid_pose.pkl) gives t - k*s exactly; targets before frame 0 read frame 0 (Dyco's
    max(t - i, 0)); the same table without the dense flag snaps the same targets to its stored frames."""
    table = _ramp(range(60), dense_every=1)
    p, _ = table.window(52, window_len=6, window_step=25)
    assert p[:, 0, 0].tolist() == [0, 0, 0, 2, 27, 52]
    sparse = _ramp([0, 5, 10, 15, 20, 25, 30])
    assert sparse.window(30, 3, 7)[0][:, 0, 0].tolist() == [15, 20, 30]  # 16 -> 15, 23 -> 20: today's snapping
    exact = _ramp(range(31), dense_every=1)
    assert exact.window(30, 3, 7)[0][:, 0, 0].tolist() == [16, 23, 30]


def test_dense_window_every_k_frames_reads_the_sample_at_or_before():
    """frame_interval 3 (I3D-Human ID2_x / ID3_x): entry k is frame 3k; a target reads entry target // 3, the frame
    itself its own fit (an image frame between samples)."""
    table = PoseTable.union([_ramp(range(0, 61, 3), dense_every=3), _ramp([50], source="mesh_infos.pkl")])
    assert table.dense_every == 3
    assert table.window(50, 4, 8)[0][:, 0, 0].tolist() == [24, 33, 42, 50]


def test_dense_window_missing_target_names_file_and_frame():
    table = _ramp(list(range(20)) + [40], dense_every=1, source="seq-train/frameid_pose.pkl")
    with pytest.raises(KeyError, match=r"seq-train/frameid_pose\.pkl: no pose for frame 20, which the pose window of "
                                       r"frame 40 reads \(T=3, s=10"):
        table.window(40, 3, 10)


def test_union_keeps_dense_sampling_and_refuses_two_samplings():
    a, b = _ramp(range(10), dense_every=1, source="a.pkl"), _ramp([3, 12], source="b.pkl")
    u = PoseTable.union([b, a])
    assert u.dense_every == 1 and u.source == "a.pkl" and len(u) == 11
    assert PoseTable.union([b]).dense_every is None
    with pytest.raises(ValueError, match="dense pose tables sampled differently: a.pkl every 1 frames, c.pkl every 3"):
        PoseTable.union([a, _ramp([0, 3], dense_every=3, source="c.pkl")])
    with pytest.raises(ValueError, match="dense_every must be None or a whole number >= 1"):
        _ramp([0], dense_every=0)


def test_every_motion_phase_is_reported_by_evaluate_and_collect():
    """PHASES (data/poses.py) lists every phase PoseTable.motion_phases gives a turning sequence, in time order, and
    evaluate's summary and collect's table read that one list: a phase left out of it loses its scores."""
    from realityavatar.analysis.collect import EXTRA
    from realityavatar.data.poses import PHASES
    from realityavatar.evaluate import summarise
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

    yaw = np.radians(np.concatenate([np.zeros(5), 20.0 * np.arange(1, 6), np.full(40, 100.0)]))  # still, turn, still
    frames = np.arange(len(yaw))
    poses = torch.zeros(len(frames), 24, 3)
    poses[:, 0] = matrix_to_axis_angle(axis_angle_to_matrix(torch.tensor(yaw)[:, None] * torch.tensor([0.0, 1.0, 0.0])))
    phases = PoseTable(frames, poses, torch.zeros(len(frames), 3)).motion_phases(frames, 10.0)
    assert tuple(dict.fromkeys(phases[f] for f in frames)) == PHASES
    out = summarise([{"split": "novel_view", "phase": p, "psnr": 20.0} for p in phases.values()])
    assert all(f"test/novel_view/{p}/psnr" in out for p in PHASES)
    assert all(any(f"/{p}/" in k for k in EXTRA) for p in PHASES)
