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
