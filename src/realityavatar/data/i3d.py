"""Reader for the HumanNeRF-style layout of I3D-Human (Dyco) and of our synthetic scenes: <seq>-train/-novelview/-novelpose.

Each folder holds images/ and masks/ (frame_XXXXXX_view_YY.png), cameras.pkl and mesh_infos.pkl keyed by frame name,
(in -train) canonical_joints.pkl, and in a release frameid_pose.pkl: the motion's poses for every frame from 0 (the
image folders are subsampled), which the pose windows read. Poses use EasyMocap placement (Rh, Th) and are converted
to the SMPL convention.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import torch

from realityavatar.body.base import rh_th_to_smpl
from realityavatar.data.poses import PoseTable
from realityavatar.data.records import (
    ImageRecord,
    SceneData,
    SceneFormatError,
    check_shape,
    extrinsics_problem,
    intrinsics_problem,
    load_pickle,
    require_key,
)

log = logging.getLogger(__name__)

FOLDERS = {"train": "train", "novel_view": "novelview", "novel_pose": "novelpose"}
# The dense poses of a split (Dyco's and SeqAvatar's layout): a list whose entry k is frame k * frame_interval,
# {'poses': [23,3] (joints 1..23; the root's rotation is Rh) or [72], 'Rh': [3], 'Th': [3]}.
FRAMEID_POSE = "frameid_pose.pkl"
# Synthetic scenes only: the pixels whose surface is the garment (the scene builder's ray hits on the cloth mesh), which
# evaluation scores on their own (metrics.image_metrics). Never read for training: a real capture has none.
GARMENT_FOLDER = "garment_masks"
FRAME_NAME = re.compile(r"^frame_(\d+)(?:_view_(\d+))?$")


def parse_frame_name(name: str, where: str = "") -> tuple[int, int]:
    """'frame_000123_view_04' -> (123, 4); 'frame_000123' -> (123, 0) (single-camera HumanNeRF data)."""
    m = FRAME_NAME.match(name)
    if not m:
        raise SceneFormatError(f"{where}: name {name!r} is not frame_XXXXXX_view_YY")
    return int(m.group(1)), int(m.group(2) or 0)


def frame_name(frame: int, view: int) -> str:
    return f"frame_{frame:06d}_view_{view:02d}"


class I3DSplitWriter:
    """Writes one split folder of this layout (the inverse of the reader below): images/ and masks/ as PNG,
    cameras.pkl and mesh_infos.pkl keyed by frame name, canonical_joints.pkl when `canonical_joints` is given."""

    def __init__(self, folder: Path, canonical_joints: np.ndarray | None = None, png_compress_level: int = 6,
                 pickle_protocol: int | None = None) -> None:
        self.folder = Path(folder)
        (self.folder / "images").mkdir(parents=True, exist_ok=True)
        (self.folder / "masks").mkdir(parents=True, exist_ok=True)
        self.canonical_joints = canonical_joints
        self.png_compress_level, self.pickle_protocol = int(png_compress_level), pickle_protocol
        self.cameras: dict = {}
        self.infos: dict = {}

    def add(self, frame: int, view: int, image: np.ndarray, mask: np.ndarray, K: np.ndarray, viewmat: np.ndarray,
            info: dict, distortions: np.ndarray | None = None, garment: np.ndarray | None = None) -> str:
        """image uint8 [H,W,3], mask uint8 [H,W] (0 / 255), K [3,3], viewmat [4,4] world-to-camera, info: the
        frame's {poses, Rh, Th, joints, tpose_joints}; garment uint8 [H,W] (0 / 255), the pixels that show the
        garment, into garment_masks/. Returns the frame name."""
        from PIL import Image

        name = frame_name(frame, view)
        if garment is not None:
            (self.folder / GARMENT_FOLDER).mkdir(exist_ok=True)
            Image.fromarray(garment).save(self.folder / GARMENT_FOLDER / f"{name}.png", format="PNG",
                                          compress_level=self.png_compress_level)
        # PIL writes no timestamps into PNGs: the same arrays give the same bytes (scene caches rely on it).
        Image.fromarray(image).save(self.folder / "images" / f"{name}.png", format="PNG",
                                    compress_level=self.png_compress_level)
        Image.fromarray(mask).save(self.folder / "masks" / f"{name}.png", format="PNG",
                                   compress_level=self.png_compress_level)
        self.cameras[name] = {"intrinsics": K, "extrinsics": viewmat,
                              "distortions": np.zeros(5, np.float32) if distortions is None else distortions}
        self.infos[name] = info
        return name

    def close(self) -> Path:
        import pickle

        for fname, obj in (("cameras.pkl", self.cameras), ("mesh_infos.pkl", self.infos)):
            with open(self.folder / fname, "wb") as fh:
                pickle.dump(obj, fh, protocol=self.pickle_protocol)
        if self.canonical_joints is not None:
            with open(self.folder / "canonical_joints.pkl", "wb") as fh:
                pickle.dump({"joints": self.canonical_joints}, fh, protocol=self.pickle_protocol)
        return self.folder


def frameid_pose_entries(infos: dict[int, dict]) -> list[dict]:
    """{frame: {poses [72], Rh, Th, ...}} covering frames 0..F-1 -> frameid_pose.pkl's list in Dyco's format
    ({'poses': [23,3] joints 1..23, 'Rh': [3], 'Th': [3]}, float32). The root's rotation must be in Rh (poses[:3]
    zero, as HumanNeRF-style fits and our scenes write it): [23,3] has no room for it."""
    frames = sorted(infos)
    if frames != list(range(len(frames))):
        gap = next(f for i, f in enumerate(frames) if f != i)
        raise ValueError(f"frameid_pose: the poses must cover frames 0..{frames[-1]} without a gap (frame {gap} "
                         "follows a missing one)")
    out = []
    for f in frames:
        pose = np.asarray(infos[f]["poses"], np.float32).reshape(24, 3)
        if np.abs(pose[0]).max() > 0:
            raise ValueError(f"frameid_pose: frame {f} has a non-zero root rotation in poses[:3]; Dyco's [23,3] "
                             "entries keep it in Rh only")
        out.append({"poses": pose[1:].copy(), "Rh": np.asarray(infos[f]["Rh"], np.float32).reshape(3),
                    "Th": np.asarray(infos[f]["Th"], np.float32).reshape(3)})
    return out


def write_release(source: str | Path, dest_root: str | Path, train_every: int = 5, novel_every: int = 5,
                  frameid_pose: bool = True) -> Path:
    """A built scene `<root>/<name>` (every frame in its image folders) rewritten as I3D-Human is released, under
    `<dest_root>/<name>`: -train keeps every `train_every`-th training frame, -novelview and -novelpose every
    `novel_every`-th frame of their ranges (I3D-Human: training every 5th frame of 100 fps, held-out sets every 30th
    or 50th; Dyco issues #1, #2), each with the cameras.pkl / mesh_infos.pkl entries of its images, and (with
    `frameid_pose`) every split's frameid_pose.pkl holding the whole motion's poses. Files are hard links where the
    file system allows (copies otherwise). Returns the new prefix."""
    import json
    import os
    import pickle
    import shutil

    for k, v in (("train_every", train_every), ("novel_every", novel_every)):
        if isinstance(v, bool) or int(v) != v or v < 1:
            raise ValueError(f"{k}: expected a whole number >= 1, got {v!r}")
    source, dest_root = Path(source), Path(dest_root)
    meta_path = source.with_name(f"{source.name}-meta.json")
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path} not found: write_release takes a scene built by realityavatar-make-scene")
    meta = json.loads(meta_path.read_text())
    dest = dest_root / source.name
    if dest.resolve() == source.resolve():
        raise ValueError(f"write_release: the release would overwrite its source {source}")
    (t0, t1), (p0, p1) = meta["frames"]["train"], meta["frames"]["novel_pose"]
    keep = {"train": set(range(t0, t1, int(train_every))), "novel_view": set(range(t0, t1, int(novel_every))),
            "novel_pose": set(range(p0, p1, int(novel_every)))}
    infos: dict[int, dict] = {}
    for split in FOLDERS:
        src = split_folder(source.parent, source.name, split)
        for name, info in load_pickle(src / "mesh_infos.pkl", "the built scene's poses").items():
            infos.setdefault(parse_frame_name(name, str(src))[0], info)
    entries = frameid_pose_entries(infos) if frameid_pose else None
    dest_root.mkdir(parents=True, exist_ok=True)
    for split in FOLDERS:
        src, out = split_folder(source.parent, source.name, split), split_folder(dest_root, source.name, split)
        if out.exists():
            shutil.rmtree(out)
        names = sorted(p.stem for p in (src / "images").glob("*.png")
                       if parse_frame_name(p.stem, str(src))[0] in keep[split])
        for sub in ("images", "masks", GARMENT_FOLDER):
            if not (src / sub).is_dir():
                continue
            (out / sub).mkdir(parents=True)
            for n in names:
                try:
                    os.link(src / sub / f"{n}.png", out / sub / f"{n}.png")
                except OSError:
                    shutil.copy2(src / sub / f"{n}.png", out / sub / f"{n}.png")
        for fname in ("cameras.pkl", "mesh_infos.pkl"):
            table = load_pickle(src / fname, "the built scene's split file")
            with open(out / fname, "wb") as fh:
                pickle.dump({n: table[n] for n in names}, fh, protocol=4)
        if (src / "canonical_joints.pkl").is_file():
            shutil.copy2(src / "canonical_joints.pkl", out / "canonical_joints.pkl")
        if entries is not None:
            with open(out / FRAMEID_POSE, "wb") as fh:
                pickle.dump(entries, fh, protocol=4)
    garment = source.with_name(f"{source.name}-garment.npz")
    if garment.is_file():
        shutil.copy2(garment, dest.with_name(garment.name))
    meta["release"] = {"source": str(source), "train_every": int(train_every), "novel_every": int(novel_every),
                       "frameid_pose": bool(frameid_pose)}
    dest.with_name(meta_path.name).write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return dest


def split_folder(root: Path, sequence: str, split: str) -> Path:
    return Path(root) / f"{sequence}-{FOLDERS[split]}"


def read_cameras(folder: Path) -> dict[str, dict[str, np.ndarray]]:
    """cameras.pkl -> {frame_name: {"K": [3,3], "viewmat": [4,4], "dist": [5] | None}} with shapes checked."""
    path = folder / "cameras.pkl"
    raw = load_pickle(path, "every split folder needs cameras.pkl {frame_name: {intrinsics, extrinsics, distortions}}")
    if not isinstance(raw, dict) or not raw:
        raise SceneFormatError(f"{path}: expected a non-empty dict keyed by frame name, got {type(raw).__name__}")
    out = {}
    for name, cam in raw.items():
        where = f"entry {name!r}"
        K = check_shape(require_key(cam, "intrinsics", path, where, "[3,3] pixel intrinsics"), (3, 3), path,
                        f"{where}['intrinsics']")
        E = check_shape(require_key(cam, "extrinsics", path, where, "[4,4] world-to-camera"), (4, 4), path,
                        f"{where}['extrinsics']")
        if why := extrinsics_problem(E):
            raise SceneFormatError(f"{path}: {where}['extrinsics'] {why}: expected a rigid world-to-camera transform")
        if why := intrinsics_problem(K):
            raise SceneFormatError(f"{path}: {where}['intrinsics'] {why}")
        dist = None
        if isinstance(cam, dict) and cam.get("distortions") is not None:
            dist = np.asarray(cam["distortions"], dtype=np.float64).reshape(-1)
            if not np.isfinite(dist).all():
                raise SceneFormatError(f"{path}: {where}['distortions'] has non-finite values")
        out[str(name)] = {"K": K, "viewmat": E, "dist": dist}
    return out


def read_mesh_infos(folder: Path, pelvis: torch.Tensor) -> PoseTable:
    """mesh_infos.pkl -> PoseTable in the SMPL convention (pose[0] about the pelvis, transl), via rh_th_to_smpl.

    Keys may be per image (frame_XXXXXX_view_YY, as in I3D-Human) or per frame. A frame's entries must agree: one
    SMPL fit per frame in world coordinates, shared by every camera (entries that differ, e.g. fits in each camera's
    coordinates, are refused rather than one of them taken).
    """
    path = folder / "mesh_infos.pkl"
    raw = load_pickle(path, "every split folder needs mesh_infos.pkl {frame_name: {poses, Rh, Th, joints, tpose_joints}}")
    if not isinstance(raw, dict) or not raw:
        raise SceneFormatError(f"{path}: expected a non-empty dict keyed by frame name, got {type(raw).__name__}")
    frames, poses, Rh, Th = [], [], [], []
    first: dict[int, tuple[str, np.ndarray]] = {}  # frame -> (its first entry's name, poses ⊕ Rh ⊕ Th)
    bad_frames = set()
    for name, info in raw.items():
        frame, _ = parse_frame_name(str(name), str(path))
        where = f"entry {name!r}"
        p = require_key(info, "poses", path, where, "[72] axis-angle SMPL pose")
        rh = require_key(info, "Rh", path, where, "[3] global rotation (axis-angle)")
        th = require_key(info, "Th", path, where, "[3] global translation")
        if p.size != 72 or rh.size != 3 or th.size != 3:
            raise SceneFormatError(
                f"{path}: {where} has poses {p.shape}, Rh {rh.shape}, Th {th.shape}; expected [72], [3], [3]"
            )
        row = np.concatenate([np.ravel(p), np.ravel(rh), np.ravel(th)]).astype(np.float64)
        if not np.isfinite(row).all():
            bad_frames.add(frame)  # checked on every entry: a per-view duplicate may be the broken one
        if frame in first:
            name0, row0 = first[frame]
            diff = np.abs(row - row0)
            if frame not in bad_frames and diff.max() > 1e-4:
                field = ("poses", "Rh", "Th")[int(np.searchsorted([72, 75], diff.argmax(), side="right"))]
                raise SceneFormatError(
                    f"{path}: entries {name0!r} and {name!r} give frame {frame} different {field} (by up to "
                    f"{diff.max():.3g}); the reader takes one SMPL fit per frame, in world coordinates, shared by "
                    "every camera")
            continue
        first[frame] = (str(name), row)
        frames.append(frame)
        poses.append(p.reshape(24, 3))
        Rh.append(rh.reshape(3))
        Th.append(th.reshape(3))
    if bad_frames:
        raise SceneFormatError(f"{path}: non-finite (NaN/inf) poses/Rh/Th at frames {sorted(bad_frames)[:10]}")
    poses_t = torch.as_tensor(np.stack(poses))  # [F,24,3] float64
    Rh_t, Th_t = torch.as_tensor(np.stack(Rh)), torch.as_tensor(np.stack(Th))  # [F,3]
    pose_smpl, transl = rh_th_to_smpl(poses_t, Rh_t, Th_t, pelvis.to(torch.float64))
    return PoseTable(frames, pose_smpl.float(), transl.float(), source=str(path))


def read_frameid_pose(folder: Path, pelvis: torch.Tensor, frame_interval: int = 1) -> PoseTable | None:
    """frameid_pose.pkl -> a dense PoseTable (entry k at frame k * frame_interval) in the SMPL convention, converted
    like mesh_infos.pkl (a [23,3] `poses` is joints 1..23 under a zero root: Rh holds the global rotation, as
    SeqAvatar's reader builds it); None when the folder has none."""
    path = folder / FRAMEID_POSE
    if not path.is_file():
        return None
    raw = load_pickle(path, "a list indexed by frame / frame_interval of {poses, Rh, Th}")
    if isinstance(raw, dict) and raw and all(isinstance(k, (int, np.integer)) for k in raw):
        if sorted(raw) != list(range(len(raw))):
            raise SceneFormatError(f"{path}: a dict keyed by integers must hold entries 0..{len(raw) - 1} (entry k is "
                                   f"frame k * frame_interval), got keys {sorted(raw)[:5]}...")
        raw = [raw[k] for k in range(len(raw))]
    if not isinstance(raw, (list, tuple)) or not raw:
        raise SceneFormatError(f"{path}: expected a non-empty list of {{poses, Rh, Th}} indexed by frame / "
                               f"frame_interval, got {type(raw).__name__}")
    poses = np.zeros((len(raw), 24, 3))
    Rh, Th = np.zeros((len(raw), 3)), np.zeros((len(raw), 3))
    for k, entry in enumerate(raw):
        where = f"entry {k} (frame {k * frame_interval})"
        p = require_key(entry, "poses", path, where, "[23,3] joints 1..23 or [72] axis-angle SMPL pose")
        rh = require_key(entry, "Rh", path, where, "[3] global rotation (axis-angle)")
        th = require_key(entry, "Th", path, where, "[3] global translation")
        if p.size not in (69, 72) or rh.size != 3 or th.size != 3:
            raise SceneFormatError(f"{path}: {where} has poses {p.shape}, Rh {rh.shape}, Th {th.shape}; expected "
                                   "[23,3] or [72], [3], [3]")
        poses[k, 24 - p.size // 3:] = np.reshape(p, (-1, 3))
        Rh[k], Th[k] = np.ravel(rh), np.ravel(th)
    bad = ~(np.isfinite(poses).all((1, 2)) & np.isfinite(Rh).all(1) & np.isfinite(Th).all(1))
    if bad.any():
        raise SceneFormatError(f"{path}: non-finite (NaN/inf) poses/Rh/Th at entries {np.flatnonzero(bad)[:10].tolist()}")
    pose_smpl, transl = rh_th_to_smpl(torch.as_tensor(poses), torch.as_tensor(Rh), torch.as_tensor(Th),
                                      pelvis.to(torch.float64))
    frames = np.arange(len(raw)) * int(frame_interval)
    return PoseTable(frames, pose_smpl.float(), transl.float(), source=str(path), dense_every=frame_interval)


def read_canonical_pelvis(folder: Path) -> np.ndarray:
    """canonical_joints.pkl['joints'][0]: the rest pelvis of the body that produced the data (fallback without a body)."""
    path = folder / "canonical_joints.pkl"
    raw = load_pickle(path, "the -train folder needs canonical_joints.pkl {'joints': [24,3]}")
    return check_shape(require_key(raw, "joints", path, "the pickle", "[24,3] rest joints"), (24, 3), path, "joints")[0]


def read_split(folder: Path, split: str, pelvis: torch.Tensor,
               frame_interval: int = 1) -> tuple[list[ImageRecord], PoseTable, PoseTable | None]:
    """One split folder -> image records (sorted by frame, view), its images' pose table (mesh_infos.pkl) and its
    dense pose table (frameid_pose.pkl; None without one)."""
    img_dir, mask_dir = folder / "images", folder / "masks"
    if not img_dir.is_dir():
        raise FileNotFoundError(f"{img_dir} not found (expected images/frame_XXXXXX_view_YY.png)")
    cams = read_cameras(folder)
    table = read_mesh_infos(folder, pelvis)
    dense = read_frameid_pose(folder, pelvis, frame_interval)
    records = []
    for img in sorted(img_dir.glob("*.png")) + sorted(img_dir.glob("*.jpg")):
        frame, view = parse_frame_name(img.stem, str(img_dir))
        cam = cams.get(img.stem)
        if cam is None:
            cam = cams.get(f"frame_{frame:06d}")  # single-camera HumanNeRF data keys cameras per frame
        if cam is None:
            raise SceneFormatError(f"{folder / 'cameras.pkl'}: no entry {img.stem!r} for image {img}")
        if frame not in table:
            raise SceneFormatError(f"{folder / 'mesh_infos.pkl'}: no entry for frame {frame} (image {img})")
        mask = mask_dir / f"{img.stem}.png"
        if not mask.is_file():
            raise FileNotFoundError(f"mask {mask} not found for image {img}")
        garment = folder / GARMENT_FOLDER / f"{img.stem}.png"
        if (folder / GARMENT_FOLDER).is_dir() and not garment.is_file():
            raise FileNotFoundError(f"garment label {garment} not found for image {img} (every image of a split with "
                                    f"{GARMENT_FOLDER}/ needs one)")
        records.append(ImageRecord(frame, view, img, mask, cam["K"], cam["viewmat"], cam["dist"], "threshold",
                                   garment if garment.is_file() else None))
    if not records:
        raise SceneFormatError(f"{img_dir}: no images (expected frame_XXXXXX_view_YY.png)")
    orphans = sorted({m.stem for m in mask_dir.glob("*.png")} - {r.image_path.stem for r in records})
    if orphans:  # an image lost in a copy or download: its frame and view would be left out without a word
        raise FileNotFoundError(f"{img_dir}: no image for the mask(s) {', '.join(o + '.png' for o in orphans[:5])}"
                                f"{f' and {len(orphans) - 5} more' if len(orphans) > 5 else ''} in {mask_dir}")
    records.sort(key=lambda r: (r.frame, r.view))
    return records, table, dense


def read_i3d(root: str | Path, sequence: str, pelvis: torch.Tensor | None = None, build_hint: str = "",
             frame_interval: int = 1) -> SceneData:
    """Read all splits of `sequence` under `root`. The -train folder is required; -novelview/-novelpose are optional.

    pelvis: [3] rest pelvis of the body model in use (for Rh/Th -> SMPL); None takes it from canonical_joints.pkl.
    frame_interval: frames between frameid_pose.pkl's entries (Dyco's `frame_interval`: 1 for ID1_x, 3 for ID2_x
    and ID3_x). With every split's frameid_pose.pkl the pose windows are exact (PoseTable.dense_every); without
    any, they take the latest image frame at or before each target, which the reader warns about. I3DReader checks
    frame_interval.
    """
    root = Path(root)
    train = split_folder(root, sequence, "train")
    if not train.is_dir():
        hint = f"; {build_hint}" if build_hint else ""
        raise FileNotFoundError(f"scene folder {train} not found{hint}")
    if pelvis is None:
        pelvis = torch.as_tensor(read_canonical_pelvis(train))
    else:
        pelvis = torch.as_tensor(pelvis, dtype=torch.float64).reshape(3)
    splits, tables, lacking = {}, [], []
    for split in FOLDERS:
        folder = split_folder(root, sequence, split)
        if split != "train" and not folder.is_dir():
            continue
        records, table, dense = read_split(folder, split, pelvis, int(frame_interval))
        splits[split] = records
        tables += [table] if dense is None else [table, dense]
        if dense is None:
            lacking.append(folder.name)
    exact = len(lacking) < len(splits)
    poses = PoseTable.union(tables)
    every_frame = not exact and np.array_equal(poses.frames, np.arange(len(poses)))  # images of every frame from 0
    if every_frame:
        meta_windows = "exact (the image folders hold every frame from 0)"
    elif exact:
        meta_windows = f"exact ({FRAMEID_POSE}, frame_interval {int(frame_interval)})"
    else:
        meta_windows = "approximate (no frameid_pose.pkl: latest image frame at or before each target)"
    if lacking and not exact and not every_frame:
        log.warning("%s: no %s in %s: the pose windows are approximate, each target taking the latest image frame at "
                    "or before it (up to a subsampling step off; every target before the first frame takes that "
                    "frame), not the exact pose", root / sequence, FRAMEID_POSE, ", ".join(lacking))
    elif lacking and exact:
        log.warning("%s: no %s in %s: their windows read the other splits' files (a frame those do not cover is an "
                    "error)", root / sequence, FRAMEID_POSE, ", ".join(lacking))
    meta = {"reader": "i3d", "pelvis": pelvis.float().tolist(), "pose_windows": meta_windows}
    scene_meta = root / f"{sequence}-meta.json"  # written by the synthetic scene generator (motion events, fps)
    if scene_meta.is_file():
        import json

        try:
            meta.update({k: v for k, v in json.loads(scene_meta.read_text()).items() if k not in meta})
        except json.JSONDecodeError as e:
            raise SceneFormatError(f"{scene_meta}: not valid JSON ({e})") from e
    return SceneData(splits=splits, poses=poses, source=str(root / sequence), meta=meta)


class I3DReader:
    """`data.reader` for this layout: I3D-Human, our synthetic scenes and converted captures. It reads
    <root>/<sequence>-train|-novelview|-novelpose and keeps the cameras `train_views` (of -train) and `test_views` (of
    -novelview/-novelpose) name; None keeps every camera. frame_interval: frames between frameid_pose.pkl's entries
    (Dyco's `frame_interval`: 1 for ID1_x, 3 for ID2_x and ID3_x)."""

    HINT = ("I3D-Human: download it (Dyco's layout, docs/data.md) and set I3D_ROOT or data.root; an embedded scene: "
            "build it with `realityavatar-make-scene` or set data.build_preset (ci|demo|full); otherwise check "
            "data.root and data.sequence")

    def __init__(self, frame_interval: int) -> None:
        if isinstance(frame_interval, bool) or not isinstance(frame_interval, int) or frame_interval < 1:
            raise ValueError(f"data.reader.frame_interval: expected a whole number >= 1 (frames between "
                             f"{FRAMEID_POSE}'s entries; Dyco's frame_interval), got {frame_interval!r}")
        self.frame_interval = frame_interval

    def read(self, root: str | Path, sequence: str, train_views: list[int] | None, test_views: list[int] | None,
             pelvis: torch.Tensor | None) -> SceneData:
        """The scene with the images of the selected cameras (pelvis: as read_i3d's)."""
        scene = read_i3d(root, sequence, pelvis, build_hint=self.HINT, frame_interval=self.frame_interval)
        splits = {}
        for key, wanted, names in (("train_views", train_views, ["train"]),
                                   ("test_views", test_views, [s for s in scene.splits if s != "train"])):
            have = sorted({r.view for s in names for r in scene.splits[s]})
            missing = sorted(set(wanted or []) - set(have))
            if missing:
                raise ValueError(f"data.{key}: camera(s) {missing} not in {scene.source}'s {', '.join(names)} "
                                 f"images (cameras {have})")
            for s in names:
                splits[s] = [r for r in scene.splits[s] if wanted is None or r.view in wanted]
        if not splits["train"]:
            raise ValueError(f"{scene.source}: no training images left after selecting views {train_views} "
                             f"(available {scene.views('train')})")
        return SceneData(splits=splits, poses=scene.poses, source=scene.source, meta=scene.meta)
