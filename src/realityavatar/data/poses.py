"""Per-frame pose tables, the pose-window lookup t-(T-1)s, ..., t-s, t used by datasets and `animate`, and the
motion phases (rest, spin, after the stop, settled) that evaluation reports on."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from realityavatar.body.base import NUM_JOINTS

# Turning faster than this (degrees per second about the body's axis) is a spin; ~0.6 degrees a frame at 25 fps.
TURNING_DEG_S = 15.0
# The motion phases in time order (PoseTable.motion_phases; "all": a sequence that never turns).
PHASES = ("rest", "spin", "after", "settled")


class PoseTable:
    """Body poses indexed by global frame id (SMPL convention: pose[0] = global orientation about the pelvis).

    frames: [F] int (any order, unique), poses: [F,24,3] axis-angle, transl: [F,3]. Stored sorted by frame id.

    dense_every: None for a table that may skip frames (the poses of a release's sparse image folders): a window
    target between stored frames takes the latest stored frame at or before it, an approximation. An int k for a
    table that holds a pose every k frames from frame 0 (I3D-Human's frameid_pose.pkl, a contiguous motion): a
    target reads the pose sample at or before it, (t // k) * k, as Dyco and SeqAvatar index that file, targets
    before frame 0 read frame 0 (their `max(t - i, 0)`), and a target with no pose is an error naming `source`.
    """

    def __init__(self, frames, poses, transl, source: str = "pose table", dense_every: int | None = None) -> None:
        frames = np.asarray(frames, dtype=np.int64).reshape(-1)
        poses = torch.as_tensor(np.asarray(poses), dtype=torch.float32)
        transl = torch.as_tensor(np.asarray(transl), dtype=torch.float32)
        if poses.shape != (len(frames), NUM_JOINTS, 3):
            raise ValueError(f"{source}: expected poses of shape [{len(frames)},24,3], got {tuple(poses.shape)}")
        if transl.shape != (len(frames), 3):
            raise ValueError(f"{source}: expected transl of shape [{len(frames)},3], got {tuple(transl.shape)}")
        if len(frames) == 0:
            raise ValueError(f"{source}: no frames")
        if len(np.unique(frames)) != len(frames):
            raise ValueError(f"{source}: duplicate frame ids")
        bad = (~torch.isfinite(poses).reshape(len(frames), -1).all(1)) | (~torch.isfinite(transl).all(1))
        if bad.any():
            raise ValueError(f"{source}: non-finite (NaN/inf) pose or translation at frames {frames[bad.numpy()][:10].tolist()}")
        if dense_every is not None and (isinstance(dense_every, bool) or int(dense_every) != dense_every
                                        or dense_every < 1):
            raise ValueError(f"{source}: dense_every must be None or a whole number >= 1, got {dense_every!r}")
        self.source = source
        self.dense_every = None if dense_every is None else int(dense_every)
        order = np.argsort(frames)
        self.frames = frames[order]  # [F] sorted
        self.poses = poses[torch.as_tensor(order)]  # [F,24,3]
        self.transl = transl[torch.as_tensor(order)]  # [F,3]
        self._row = {int(f): i for i, f in enumerate(self.frames)}

    @classmethod
    def from_sequence(cls, poses, transl, frame_ids: Sequence[int] | None = None) -> PoseTable:
        """A table for an arbitrary sequence (e.g. an animation): frame ids default to 0..F-1."""
        n = len(poses)
        return cls(np.arange(n) if frame_ids is None else frame_ids, poses, transl, source="pose sequence")

    @classmethod
    def union(cls, tables: Sequence[PoseTable]) -> PoseTable:
        """Merge tables (e.g. all splits of one sequence). A frame in several tables must have the same pose and
        translation in each (to 1e-4): two fits of one frame are refused rather than one of them taken. The result
        is dense (exact windows) when any table is, with their common sampling; dense tables sampled differently
        are refused."""
        dense = [t for t in tables if t.dense_every is not None]
        if len({t.dense_every for t in dense}) > 1:
            raise ValueError("dense pose tables sampled differently: " + ", ".join(
                f"{t.source} every {t.dense_every} frames" for t in dense))
        rows: dict[int, tuple[torch.Tensor, torch.Tensor, str]] = {}
        for t in tables:
            for i, f in enumerate(t.frames):
                pose, transl, source = rows.setdefault(int(f), (t.poses[i], t.transl[i], t.source))
                diff = max((pose - t.poses[i]).abs().max().item(), (transl - t.transl[i]).abs().max().item())
                if diff > 1e-4:
                    raise ValueError(f"frame {int(f)} has different poses in {source} and {t.source} (by up to "
                                     f"{diff:.3g}): one fit per frame is expected across the splits")
        frames = sorted(rows)
        source = " + ".join(dict.fromkeys(t.source for t in (dense or tables)))  # the files a window reads
        return cls(frames, torch.stack([rows[f][0] for f in frames]), torch.stack([rows[f][1] for f in frames]),
                   source=source, dense_every=dense[0].dense_every if dense else None)

    def __len__(self) -> int:
        return len(self.frames)

    def __contains__(self, frame: int) -> bool:
        return int(frame) in self._row

    def get(self, frame: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact lookup: pose [24,3], transl [3]."""
        i = self._row.get(int(frame))
        if i is None:
            raise KeyError(f"frame {frame} has no pose (available {self.frames[0]}..{self.frames[-1]})")
        return self.poses[i], self.transl[i]

    def window_rows(self, frame: int, window_len: int, window_step: int) -> np.ndarray:
        """Row indices [T] for frames t-(T-1)s .. t; the last is `frame` itself. Earlier targets as `dense_every`
        says: on a dense table the pose sample at or before each target (targets before frame 0 read frame 0), a
        missing one an error; on a sparse table the latest stored frame at or before each target, the first frame
        for targets before it (approximate windows)."""
        if window_len < 1 or window_step < 0:
            raise ValueError(f"pose window: window_len must be >= 1 and window_step >= 0, got {window_len}, {window_step}")
        if int(frame) not in self._row:
            raise KeyError(f"frame {frame} has no pose (available {self.frames[0]}..{self.frames[-1]})")
        targets = int(frame) - window_step * np.arange(window_len - 1, -1, -1)  # [T], oldest first
        if self.dense_every is None:
            rows = np.searchsorted(self.frames, targets, side="right") - 1
            return np.clip(rows, 0, len(self.frames) - 1)
        k = self.dense_every
        wanted = np.maximum(targets, 0) // k * k  # [T]: Dyco's frameid_pose[int(max(t - i, 0) / frame_interval)]
        wanted[-1] = int(frame)  # the frame's own pose (its mesh_infos fit), as Dyco poses the body with it
        rows = np.minimum(np.searchsorted(self.frames, wanted), len(self.frames) - 1)
        missing = wanted[self.frames[rows] != wanted]
        if missing.size:
            raise KeyError(f"{self.source}: no pose for frame {int(missing[0])}, which the pose window of frame "
                           f"{frame} reads (T={window_len}, s={window_step}, a pose every {k} frame(s) from frame 0 "
                           f"expected; the file holds frames {self.frames[0]}..{self.frames[-1]})")
        return rows

    def window(self, frame: int, window_len: int, window_step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose window [T,24,3] and translation window [T,3]; the last entry is `frame` itself."""
        rows = torch.as_tensor(self.window_rows(frame, window_len, window_step))
        return self.poses[rows], self.transl[rows]

    def windows(self, frames: Sequence[int], window_len: int, window_step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Batched windows: poses [N,T,24,3], transl [N,T,3]."""
        rows = torch.as_tensor(np.stack([self.window_rows(f, window_len, window_step) for f in frames]))
        return self.poses[rows], self.transl[rows]

    def motion_phases(self, frames: Sequence[int], fps: float, still_deg_s: float = TURNING_DEG_S) -> dict[int, str]:
        """The motion phase of each of `frames` (a split's, sorted here) from how fast the body turns about its own
        axis between consecutive ones: "rest" before it first turns faster than `still_deg_s` degrees per second,
        "spin" while it does, "after" for the second that follows the turning's end, "settled" later (a new turn
        is "spin" again). A sequence that never turns (a walk) is "all". Real captures have no event list, so the
        phases come from the poses, for every dataset alike."""
        from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

        frames = sorted(int(f) for f in frames)
        R = axis_angle_to_matrix(torch.stack([self.get(f)[0][0] for f in frames]).double())  # [F,3,3]
        dt = np.maximum(np.diff(frames), 1) / float(fps)  # [F-1] seconds
        step = torch.rad2deg(matrix_to_axis_angle(R[1:] @ R[:-1].transpose(-1, -2)).norm(dim=-1)).numpy()
        turning = np.concatenate([[False], step / dt > still_deg_s])  # [F]: turning since the previous frame
        if not turning.any():
            return dict.fromkeys(frames, "all")
        out, state, stopped = {}, "rest", None
        for f, turns in zip(frames, turning):
            if turns:
                state, stopped = "spin", None
            elif state != "rest":
                stopped = f if stopped is None else stopped
                state = "after" if (f - stopped) / float(fps) < 1.0 else "settled"
            out[f] = state
        return out
