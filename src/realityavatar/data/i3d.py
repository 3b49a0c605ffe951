"""Reader for the HumanNeRF-style layout of I3D-Human (Dyco) and of our synthetic scenes: <seq>-train/-novelview/-novelpose.

Each folder holds images/ and masks/ (frame_XXXXXX_view_YY.png), cameras.pkl and mesh_infos.pkl keyed by frame name,
and (in -train) canonical_joints.pkl. Poses use EasyMocap placement (Rh, Th) and are converted to the SMPL convention.
"""

from __future__ import annotations

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

FOLDERS = {"train": "train", "novel_view": "novelview", "novel_pose": "novelpose"}
# Synthetic scenes only: the pixels whose surface is the garment (the scene builder's ray hits on the cloth mesh), which
# evaluation scores on their own (metrics.garment_metrics). Never read for training: a real capture has none.
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


def read_canonical_pelvis(folder: Path) -> np.ndarray:
    """canonical_joints.pkl['joints'][0]: the rest pelvis of the body that produced the data (fallback without a body)."""
    path = folder / "canonical_joints.pkl"
    raw = load_pickle(path, "the -train folder needs canonical_joints.pkl {'joints': [24,3]}")
    return check_shape(require_key(raw, "joints", path, "the pickle", "[24,3] rest joints"), (24, 3), path, "joints")[0]


def read_split(folder: Path, split: str, pelvis: torch.Tensor) -> tuple[list[ImageRecord], PoseTable]:
    """One split folder -> image records (sorted by frame, view) and its pose table."""
    img_dir, mask_dir = folder / "images", folder / "masks"
    if not img_dir.is_dir():
        raise FileNotFoundError(f"{img_dir} not found (expected images/frame_XXXXXX_view_YY.png)")
    cams = read_cameras(folder)
    table = read_mesh_infos(folder, pelvis)
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
    return records, table


def read_i3d(root: str | Path, sequence: str, pelvis: torch.Tensor | None = None, build_hint: str = "") -> SceneData:
    """Read all splits of `sequence` under `root`. The -train folder is required; -novelview/-novelpose are optional.

    pelvis: [3] rest pelvis of the body model in use (for Rh/Th -> SMPL); None takes it from canonical_joints.pkl.
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
    splits, tables = {}, []
    for split in FOLDERS:
        folder = split_folder(root, sequence, split)
        if split != "train" and not folder.is_dir():
            continue
        records, table = read_split(folder, split, pelvis)
        splits[split] = records
        tables.append(table)
    meta = {"reader": "i3d", "pelvis": pelvis.float().tolist()}
    scene_meta = root / f"{sequence}-meta.json"  # written by the synthetic scene generator (motion events, fps)
    if scene_meta.is_file():
        import json

        try:
            meta.update({k: v for k, v in json.loads(scene_meta.read_text()).items() if k not in meta})
        except json.JSONDecodeError as e:
            raise SceneFormatError(f"{scene_meta}: not valid JSON ({e})") from e
    return SceneData(splits=splits, poses=PoseTable.union(tables), source=str(root / sequence), meta=meta)
