"""Reader for ZJU-MoCap in the ARAH-preprocessed layout (as used by 3DGS-Avatar).

<root>/CoreView_XXX/cam_params.json  {"all_cam_names": [...], "<cam>": {"K": [3,3], "D": [5,1], "R": [3,3], "T": [3,1] m}}
<root>/CoreView_XXX/<cam>/<idx:06d>.jpg (image) and .png (mask, labels != 0 are the person)
<root>/CoreView_XXX/models/<idx:06d>.npz  (root_orient [3], pose_body [63], pose_hand [6], trans [3], betas, ...)
Frame ids are positions in the sorted models/ list (3DGS-Avatar's frame indices); poses are already SMPL-convention.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from itertools import pairwise
from pathlib import Path

import numpy as np

from realityavatar.data.poses import PoseTable
from realityavatar.data.records import (
    ImageRecord,
    SceneData,
    SceneFormatError,
    camera_problems,
    check_shape,
    require_key,
)

log = logging.getLogger(__name__)

MODEL_KEYS = {"root_orient": 3, "pose_body": 63, "pose_hand": 6, "trans": 3}


def read_cam_params(subject_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    """cam_params.json -> {cam_name: {"K", "viewmat" [4,4] world-to-camera, "dist" [5]}} in file order."""
    path = subject_dir / "cam_params.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found (ZJU-MoCap in the ARAH layout: see docs/data.md)")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SceneFormatError(f"{path}: not valid JSON ({e})") from e
    names = raw.get("all_cam_names") or [k for k in raw if k != "all_cam_names"]
    cams = {}
    for name in names:
        name = str(name)
        if name not in raw:
            raise SceneFormatError(f"{path}: camera {name!r} is listed in all_cam_names but has no entry")
        c, where = raw[name], f"camera {name!r}"
        K = check_shape(require_key(c, "K", path, where, "[3,3] intrinsics"), (3, 3), path, f"{where} K")
        R = check_shape(require_key(c, "R", path, where, "[3,3] world-to-camera rotation"), (3, 3), path, f"{where} R")
        if problems := camera_problems(R, K):
            raise SceneFormatError(f"{path}: {where} {problems[0]}")
        T = check_shape(require_key(c, "T", path, where, "[3] translation in metres"), (3,), path, f"{where} T")
        D = np.asarray(c.get("D", np.zeros(5)), dtype=np.float64).reshape(-1)
        E = np.eye(4)
        E[:3, :3], E[:3, 3] = R, T
        cams[name] = {"K": K, "viewmat": E, "dist": D}
    return cams


def read_models(subject_dir: Path) -> tuple[list[Path], PoseTable, np.ndarray]:
    """models/*.npz -> (files sorted, PoseTable over frame ids 0..N-1, betas [B] of the first file)."""
    files = sorted((subject_dir / "models").glob("*.npz"))
    if not files:
        raise FileNotFoundError(f"{subject_dir / 'models'}: no <idx:06d>.npz SMPL files")
    idx = [int(f.stem) if f.stem.isdigit() else None for f in files]
    steps = {b - a for a, b in pairwise(idx)} if None not in idx else set()
    if len(steps) > 1:  # frame ids are positions in this list
        a, b = next((a, b) for a, b in pairwise(idx) if b - a != min(steps))
        raise SceneFormatError(f"{subject_dir / 'models'}: the files are not evenly numbered ({a:06d}.npz is followed "
                               f"by {b:06d}.npz): frame ids are positions in the sorted list, and the pose windows "
                               "would join the frames on both sides of a gap as if consecutive")
    poses, trans, betas = [], [], None
    for i, f in enumerate(files):
        try:
            with np.load(f) as z:
                d = {k: z[k] for k in z.files}
        except Exception as e:
            raise SceneFormatError(f"{f}: not a readable .npz ({type(e).__name__}: {e})") from e
        parts = {}
        for k, n in MODEL_KEYS.items():
            parts[k] = require_key(d, k, f, "the file", f"[{n}]").reshape(-1)
            if parts[k].size != n:
                raise SceneFormatError(f"{f}: {k} has {parts[k].size} values, expected {n}")
        pose = np.concatenate([parts["root_orient"], parts["pose_body"], parts["pose_hand"]]).reshape(24, 3)
        if not (np.isfinite(pose).all() and np.isfinite(parts["trans"]).all()):
            raise SceneFormatError(f"{f}: non-finite (NaN/inf) pose or trans")
        poses.append(pose)
        trans.append(parts["trans"])
        if betas is None and "betas" in d:
            betas = np.asarray(d["betas"], dtype=np.float64).reshape(-1)
    if steps and min(steps) > 1:  # the windows count files: s files back is s * step capture frames back
        log.warning("%s: the SMPL files are every %d-th capture frame; data.window_step counts files (frame ids are "
                    "positions in the list), so a window step of s reaches s * %d capture frames back",
                    subject_dir / "models", min(steps), min(steps))
    # Every file's pose, not only the selected images' frames: the table is dense (windows exact, clamped at frame 0).
    table = PoseTable(np.arange(len(files)), np.stack(poses), np.stack(trans), source=str(subject_dir / "models"),
                      dense_every=1)
    return files, table, betas if betas is not None else np.zeros(10)


def frame_range(spec: Sequence[int] | None, n: int, what: str) -> list[int]:
    """[start, end, step] (end 0 or None = to the last frame) -> frame ids, like 3DGS-Avatar's slices."""
    if spec is None:
        return []
    if len(spec) != 3:
        raise ValueError(f"data.{what}: expected [start, end, step], got {list(spec)}")
    start, end, step = (int(x) if x is not None else 0 for x in spec)
    return list(range(n))[slice(start, end if end else None, step or 1)]


def read_zju(
    subject_dir: str | Path,
    train_views: Sequence[int] | None,
    test_views: Sequence[int] | None,
    train_frames: Sequence[int],
    novel_view_frames: Sequence[int] | None = None,
    novel_pose_frames: Sequence[int] | None = None,
) -> SceneData:
    """Splits: train = train_views x train_frames; novel_view = test_views x novel_view_frames (default: every 30th
    training frame); novel_pose = test_views x novel_pose_frames (frames outside the training range)."""
    subject_dir = Path(subject_dir)
    if not subject_dir.is_dir():
        raise FileNotFoundError(
            f"ZJU-MoCap subject folder {subject_dir} not found (set data.root to the folder holding CoreView_XXX)"
        )
    cams = read_cam_params(subject_dir)
    files, table, betas = read_models(subject_dir)
    n = len(files)
    all_views = list(cams)
    tv = [str(v) for v in train_views] if train_views is not None else all_views
    ev = [str(v) for v in test_views] if test_views is not None else [v for v in all_views if v not in tv]
    for v in tv + ev:
        if v not in cams:
            raise SceneFormatError(f"{subject_dir / 'cam_params.json'}: no camera {v!r} (have {all_views})")
    train_ids = frame_range(train_frames, n, "reader.train_frames")
    nv_ids = (frame_range(novel_view_frames, n, "reader.novel_view_frames") if novel_view_frames is not None
              else train_ids[::30])
    np_ids = frame_range(novel_pose_frames, n, "reader.novel_pose_frames")
    overlap = sorted(set(np_ids) & set(train_ids))
    if overlap:
        raise ValueError(f"data.reader.novel_pose_frames overlaps the training frames (e.g. {overlap[:5]})")

    def records(views, ids):
        out = []
        for f in ids:
            stem = files[f].stem
            for v in views:
                img, mask = subject_dir / v / f"{stem}.jpg", subject_dir / v / f"{stem}.png"
                if not img.is_file():
                    raise FileNotFoundError(f"image {img} not found (camera {v}, frame {f})")
                if not mask.is_file():
                    raise FileNotFoundError(f"mask {mask} not found (camera {v}, frame {f})")
                c = cams[v]
                out.append(ImageRecord(f, int(v), img, mask, c["K"], c["viewmat"], c["dist"], "nonzero"))
        return out

    splits = {"train": records(tv, train_ids)}
    if nv_ids and ev:
        splits["novel_view"] = records(ev, nv_ids)
    if np_ids and ev:
        splits["novel_pose"] = records(ev, np_ids)
    return SceneData(splits=splits, poses=table, source=str(subject_dir),
                     meta={"reader": "zju", "betas": betas.tolist()})


class ZJUReader:
    """`data.reader` for ZJU-MoCap in the ARAH layout: <root>/<sequence> (CoreView_XXX). The splits are the cameras
    train_views / test_views (names in cam_params.json) at the frame ranges train_frames, novel_view_frames and
    novel_pose_frames ([start, end, step], end 0 = to the last frame; novel_view_frames null: every 30th training
    frame)."""

    def __init__(self, train_frames: Sequence[int], novel_view_frames: Sequence[int] | None,
                 novel_pose_frames: Sequence[int] | None) -> None:
        self.frames = [None if f is None else list(f) for f in (train_frames, novel_view_frames, novel_pose_frames)]

    def read(self, root: str | Path, sequence: str, train_views: Sequence[int] | None,
             test_views: Sequence[int] | None, pelvis=None) -> SceneData:
        """The scene of the selected cameras and frames (poses are SMPL-convention already: `pelvis` is not used)."""
        return read_zju(Path(root) / sequence, train_views, test_views, *self.frames)
