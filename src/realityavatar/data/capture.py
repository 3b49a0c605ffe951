"""Bring your own capture: validate a simple folder format and convert it into the I3D-Human layout the readers use.

Input folder (see docs/data.md):
  capture.json            {"fps": 25}  the cameras' frame rate (or convert --fps)
  cameras.json            {"<cam id, int>": {"K": [3,3], "R": [3,3], "T": [3] (world-to-camera, metres), "D": [5]?}}
  images/<cam>/<frame:06d>.png|.jpg    masks/<cam>/<frame:06d>.png (0 = background, anything else = person)
  smpl/<frame:06d>.npz|.json           {"poses": [72], "transl": [3]}  (SMPL: poses[:3] = global orientation)
                                    or {"poses": [72], "Rh": [3], "Th": [3]}  (EasyMocap placement); "betas" optional
                                    or EasyMocap's own file: [{"id": 0, "poses": [[72]], "Rh": [[3]], "Th": [[3]],
                                       "shapes": [[10]]}, ...] (one entry per person)
Usage: .venv/bin/python -m realityavatar.data.capture validate CAPTURE
       .venv/bin/python -m realityavatar.data.capture convert CAPTURE OUT_ROOT --name NAME
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from realityavatar.data.i3d import I3DSplitWriter
from realityavatar.data.records import camera_problems

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
POSE_FIELDS = {"poses": 72, "transl": 3, "Rh": 3, "Th": 3}  # values each field holds, nested or flat
NOVEL_POSE_SHARE = 0.2  # convert's default: the last fifth of the frames is the novel-pose tail
BODY_HEIGHT_M = 1.7  # a person's height, for "the projected body is far larger than the image"


class CaptureError(ValueError):
    """Every problem found in a capture folder, one per line."""

    def __init__(self, folder: Path, problems: list[str]) -> None:
        self.problems = problems
        lines = "\n".join(f"  - {p}" for p in problems)
        super().__init__(f"capture {folder}: {len(problems)} problem(s):\n{lines}")


@dataclass
class Capture:
    """What `scan` found: every problem, and what could be read (cameras by id, frames, poses, fps, image sizes)."""

    problems: list[str] = field(default_factory=list)
    cams: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    frames: list[int] = field(default_factory=list)
    smpl: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    fps: float | None = None
    sizes: dict[int, tuple[int, int]] = field(default_factory=dict)  # camera -> its images' (width, height)
    split: dict = field(default_factory=dict)  # train_views, test_views, novel_pose_from; defaults named in `notes`
    notes: list[str] = field(default_factory=list)


def _frames_in(d: Path, exts: Sequence[str]) -> dict[int, Path]:
    out = {}
    if d.is_dir():
        for p in sorted(d.iterdir()):
            if p.suffix.lower() in exts and p.stem.isdigit():
                out[int(p.stem)] = p
    return out


def read_pose_file(p: Path, person: int | None = None) -> dict[str, np.ndarray]:
    """A pose file's fields as arrays: the flat form (.npz or .json) or EasyMocap's list of people (the entry whose
    `id` is `person`; None: the file's only person), its `shapes` read as `betas`. ValueError names file and field."""
    if p.suffix == ".npz":
        with np.load(p) as z:
            raw = {k: z[k] for k in z.files}
    else:
        raw = json.loads(p.read_text())
    if isinstance(raw, list):  # EasyMocap: [{"id": 0, "poses": [[...]], ...}, ...]
        if not raw or not all(isinstance(x, dict) for x in raw):
            raise ValueError(f"{p}: expected an object or EasyMocap's list of people (objects with 'id'), got "
                             f"{'an empty list' if not raw else 'a list of ' + type(raw[0]).__name__}")
        ids = [x.get("id") for x in raw]
        if person is None and len(raw) > 1:
            raise ValueError(f"{p}: {len(raw)} people (field 'id': {ids}); choose one with --person ID")
        chosen = raw if person is None else [x for x in raw if x.get("id") == person]
        if not chosen:
            raise ValueError(f"{p}: no person with 'id' {person} (the file has ids {ids})")
        raw = chosen[0]
    elif not isinstance(raw, dict):
        raise ValueError(  # noqa: TRY004 - the file's content, reported with the other problems (scan)
            f"{p}: expected an object of fields or EasyMocap's list of people, got {type(raw).__name__}")
    out = {}
    for k in (*POSE_FIELDS, "betas", "shapes"):
        if k in raw:
            try:
                out["betas" if k == "shapes" else k] = np.asarray(raw[k], dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{p}: field {k!r} is not an array of numbers") from None
    return out


def _pose_problem(p: Path, d: dict[str, np.ndarray]) -> str | None:
    """What is missing or wrong in one frame's pose fields (naming the file and the field), or None."""
    if "poses" not in d:
        return f"{p}: missing field 'poses' ([72] axis-angle; it has {sorted(d)})"
    if "transl" not in d and not ("Rh" in d and "Th" in d):
        lacks = [k for k in ("Rh", "Th") if k not in d]
        return f"{p}: missing field {' and '.join(repr(k) for k in lacks)} ([3], EasyMocap) or 'transl' ([3], SMPL)"
    fields = ("poses", "transl") if "transl" in d else ("poses", "Rh", "Th")
    bad = [f"{k} has {d[k].size} values, expected {POSE_FIELDS[k]}" for k in fields if d[k].size != POSE_FIELDS[k]]
    if bad:
        return f"{p}: {'; '.join(bad)}"
    nonfinite = [k for k in fields if not np.isfinite(d[k]).all()]
    return f"{p}: non-finite values (NaN/inf) in field(s) {nonfinite}" if nonfinite else None


def _placement(d: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(poses [72], Rh [3], Th [3]) in EasyMocap placement. SMPL input maps to Rh = 0, Th = transl exactly."""
    poses = d["poses"].reshape(72)
    if "transl" in d:
        return poses, np.zeros(3), d["transl"].reshape(3)
    return poses, d["Rh"].reshape(3), d["Th"].reshape(3)


def _roots(smpl: dict[int, dict[str, np.ndarray]], pelvis: np.ndarray) -> np.ndarray:
    """The body's root in the world per frame [F,3]: x = R(Rh) pelvis + Th (EasyMocap) or pelvis + transl (SMPL)."""
    from realityavatar.geometry import axis_angle_to_matrix

    out = [pelvis + d["transl"] if "transl" in d else
           axis_angle_to_matrix(torch.as_tensor(d["Rh"])).numpy() @ pelvis + d["Th"] for d in smpl.values()]
    return np.asarray(out).reshape(-1, 3)


def _seen(K: np.ndarray, R: np.ndarray, T: np.ndarray, size: tuple[int, int], X: np.ndarray) -> tuple[float, float]:
    """(share of the points X [F,3] in front of the camera that project within half an image of it, their median
    depth) for world-to-camera R, T."""
    x = X @ R.T + T
    z = x[:, 2]
    front = z > 1e-6
    uv = x[:, :2] / np.where(front, z, 1.0)[:, None] * K[[0, 1], [0, 1]] + K[:2, 2]
    W, H = size
    inside = front & (uv[:, 0] > -W / 2) & (uv[:, 0] < 1.5 * W) & (uv[:, 1] > -H / 2) & (uv[:, 1] < 1.5 * H)
    return float(inside.mean()), float(np.median(z[front])) if front.any() else float("nan")


def view_problems(where: str, K: np.ndarray, R: np.ndarray, T: np.ndarray, size: tuple[int, int],
                  roots: np.ndarray) -> list[str]:
    """A camera that cannot see the body as calibrated: intrinsics of another resolution (the principal point far
    from the images' centre, or a body far larger than the image) and extrinsics the wrong way round (the root
    projects into the image in most frames only with R, T inverted)."""
    W, H = size
    c = K[:2, 2]
    if abs(c[0] - W / 2) > W / 4 or abs(c[1] - H / 2) > H / 4:
        s = W / (2 * c[0]) if c[0] > 0 else float("nan")
        return [(f"{where}: K's principal point ({c[0]:.0f}, {c[1]:.0f}) is far from the centre ({W / 2:.0f}, "
                 f"{H / 2:.0f}) of its {W}x{H} images: intrinsics of another resolution? (scale fx, fy, cx, cy by "
                 f"the images' size over the calibration's, about {s:.3g} here)")]
    if not len(roots):
        return []
    share, depth = _seen(K, R, T, size, roots)
    if share > 0.5:
        span = K[1, 1] * BODY_HEIGHT_M / depth
        if span > 2 * H:  # a full-body capture frames the whole body
            return [(f"{where}: a {BODY_HEIGHT_M} m body {depth:.2f} m away spans {span:.0f} px with K's fy = "
                     f"{K[1, 1]:.0f}, in images {H} px high: intrinsics of another resolution?")]
        return []
    inv, _ = _seen(K, R.T, -R.T @ T, size, roots)
    if inv > 0.5:
        return [(f"{where}: R, T look camera-to-world: the body's root projects into the image in {share:.0%} of the "
                 f"frames as given, in {inv:.0%} with R, T inverted; give world-to-camera (R^T, -R^T T)")]
    return [(f"{where}: the body's root (from smpl/) projects into the image in only {share:.0%} of the frames "
             f"(either way round): check R, T (world-to-camera, metres), K, and that smpl/ is in the same world")]


def _split(cap: Capture, train_views, test_views, novel_pose_from) -> None:
    """The cameras and frames of each split, convert's defaults filled in and named in cap.notes; a split that would
    come out empty is a problem naming the flag."""
    cams, frames, p = sorted(cap.cams), cap.frames, cap.problems
    for what, views in (("--train-views", train_views), ("--test-views", test_views)):
        if views is not None and not list(views):
            p.append(f"{what} is empty: every split needs a camera")
        p += [f"{what}: camera {v} is not in cameras.json (it has {cams})" for v in views or [] if int(v) not in cams]
    if test_views is None and len(cams) >= 2:
        test_views = [cams[-1]]
        cap.notes.append(f"--test-views not given: camera {cams[-1]} is held out (novel view, novel pose)")
    elif test_views is None and cams:
        p.append(f"--test-views: one camera ({cams[0]}) leaves none to hold out; give --test-views and --train-views")
    test_views = [int(v) for v in test_views or []]
    if train_views is None:
        train_views = [c for c in cams if c not in test_views]
        if test_views and cams:
            cap.notes.append(f"--train-views not given: cameras {train_views} (all but the held-out)")
    train_views = [int(v) for v in train_views]
    if novel_pose_from is None and len(frames) >= 2:
        k = max(1, round(NOVEL_POSE_SHARE * len(frames)))
        novel_pose_from = frames[-k]
        cap.notes.append(f"--novel-pose-from not given: frames {novel_pose_from}..{frames[-1]} (the last {k} of "
                         f"{len(frames)}) are the novel poses")
    elif novel_pose_from is None and frames:
        p.append("--novel-pose-from: one frame leaves none for the novel poses; a capture needs two frames or more")
    elif frames:
        if not any(f < novel_pose_from for f in frames):
            p.append(f"--novel-pose-from {novel_pose_from}: no training frame before it (frames {frames[0]}..)")
        if not any(f >= novel_pose_from for f in frames):
            p.append(f"--novel-pose-from {novel_pose_from}: no frame at or after it (the last is {frames[-1]}): "
                     "the novel poses would be empty")
    if cams and not set(train_views) - set(test_views):
        p.append(f"--train-views: no training camera; cameras {cams} are all held out (--test-views {test_views})")
    cap.split = {"train_views": train_views, "test_views": test_views, "novel_pose_from": novel_pose_from}


def _read_fps(folder: Path, fps: float | None, p: list[str]) -> float | None:
    """The capture's frame rate: capture.json's "fps", or `fps` (--fps); neither, or the two disagreeing, a problem."""
    path = folder / "capture.json"
    found = None
    if path.is_file():
        try:
            found = json.loads(path.read_text()).get("fps")
        except (json.JSONDecodeError, AttributeError) as e:
            p.append(f"{path}: expected an object like {{\"fps\": 25}} ({e})")
            return fps
        if found is not None and not (isinstance(found, (int, float)) and not isinstance(found, bool) and found > 0):
            p.append(f"{path}: field 'fps' = {found!r}, expected the frames per second (a number > 0)")
            found = None
        elif found is None and fps is None:
            p.append(f"{path}: missing field 'fps' (the cameras' frames per second, e.g. {{\"fps\": 25}})")
    elif fps is None:
        p.append(f"{path} is missing: it gives the cameras' frame rate, {{\"fps\": 25}} (or convert --fps 25); "
                 "nothing assumes one")
    if fps is not None and found is not None and abs(float(fps) - float(found)) > 1e-6:
        p.append(f"--fps {fps:g} differs from {path}'s fps {found:g}")
    return float(fps if fps is not None else found) if (fps is not None or found is not None) else None


def scan(folder: str | Path, train_views: Sequence[int] | None = None, test_views: Sequence[int] | None = None,
         novel_pose_from: int | None = None, fps: float | None = None, person: int | None = None,
         pelvis: np.ndarray | None = None) -> Capture:
    """Check everything and collect every problem. `pelvis`: the body's rest pelvis [3] (the root the camera check
    projects; None: the origin of the body's frame, within ~0.3 m of it for SMPL and the mannequin)."""
    from PIL import Image

    folder = Path(folder)
    cap = Capture()
    problems = cap.problems
    if not folder.is_dir():
        problems.append(f"folder {folder} does not exist")
        return cap
    cap.fps = _read_fps(folder, fps, problems)
    # cameras
    cpath = folder / "cameras.json"
    raw = {}
    if not cpath.is_file():
        problems.append(f"{cpath} is missing")
    else:
        try:
            raw = json.loads(cpath.read_text())
        except json.JSONDecodeError as e:
            problems.append(f"{cpath}: not valid JSON ({e})")
    names: dict[int, str] = {}  # camera id -> its key in cameras.json (the folder name)
    for key, c in raw.items():
        where = f"{cpath} camera {key!r}"
        try:
            cam_id = int(key)
        except ValueError:
            problems.append(f"{where}: camera ids must be integers (they become view_YY)")
            continue
        ok = True
        arrs = {}
        for fld, shape in (("K", (3, 3)), ("R", (3, 3)), ("T", (3,)), ("D", (5,))):
            if fld not in c:
                if fld != "D":
                    problems.append(f"{where}: missing {fld} (expected {list(shape)})")
                    ok = False
                continue
            try:
                a = np.asarray(c[fld], dtype=np.float64)
            except (TypeError, ValueError):
                problems.append(f"{where}: {fld} is not numeric")
                ok = False
                continue
            if a.size != int(np.prod(shape)):
                problems.append(f"{where}: {fld} has shape {list(a.shape)}, expected {list(shape)}")
                ok = False
                continue
            a = a.reshape(shape)
            if not np.isfinite(a).all():
                problems.append(f"{where}: {fld} has non-finite values")
                ok = False
            arrs[fld] = a
        if ok and "R" in arrs:
            # reported, the camera kept: its images are checked too (all problems at once; nothing is converted)
            problems += [f"{where}: {p}" for p in camera_problems(arrs["R"], arrs["K"])]
        if ok:
            arrs.setdefault("D", np.zeros(5))
            cap.cams[cam_id], names[cam_id] = arrs, key
    # poses
    smpl_files = {**_frames_in(folder / "smpl", (".json",)), **_frames_in(folder / "smpl", (".npz",))}
    if not smpl_files:
        problems.append(f"{folder / 'smpl'}: no <frame:06d>.npz/.json files")
    for f, p in sorted(smpl_files.items()):
        try:
            d = read_pose_file(p, person)
        except ValueError as e:  # names the file and the field
            problems.append(str(e))
            continue
        except Exception as e:  # noqa: BLE001
            problems.append(f"{p}: unreadable ({type(e).__name__}: {e})")
            continue
        why = _pose_problem(p, d)
        if why:
            problems.append(why)
        else:
            cap.smpl[f] = d
    cap.frames = frames = sorted(smpl_files)
    roots = _roots(cap.smpl, np.zeros(3) if pelvis is None else np.asarray(pelvis, np.float64))
    # images and masks per camera
    img_root = folder / "images"
    found = sorted(p.name for p in img_root.iterdir() if p.is_dir()) if img_root.is_dir() else []
    no_folder = [c for c in sorted(cap.cams) if names[c] not in found]
    if no_folder:
        problems.append(f"{img_root}: no folder for camera(s) {[names[c] for c in no_folder]} of {cpath.name}; the "
                        f"folders found are {found}: name each images/ and masks/ folder as its camera's key")
    elif stray := [n for n in found if n not in raw]:
        problems.append(f"{img_root}: folders {stray} have no camera in {cpath.name} (its keys: {list(raw)})")
    for cam_id in sorted(set(cap.cams) - set(no_folder)):
        img_dir, mask_dir = img_root / names[cam_id], folder / "masks" / names[cam_id]
        imgs, masks = _frames_in(img_dir, IMAGE_EXTS), _frames_in(mask_dir, (".png",))
        if not imgs:
            problems.append(f"{img_dir}: no images for camera {cam_id}")
            continue
        missing = sorted(set(frames) - set(imgs))
        if missing:
            problems.append(f"{img_dir}: missing images for frames {missing[:20]}{' ...' if len(missing) > 20 else ''}")
        extra = sorted(set(imgs) - set(frames))
        if extra:
            problems.append(f"{img_dir}: frames {extra[:20]} have images but no smpl/<frame>.npz|.json")
        no_mask = sorted(set(imgs) - set(masks))
        if no_mask:
            problems.append(f"{mask_dir}: missing masks for frames {no_mask[:20]}")
        if len(imgs) != len(masks):
            problems.append(f"camera {cam_id}: {len(imgs)} images but {len(masks)} masks")
        by_size: dict[tuple[int, int], list[Path]] = {}
        for f, ip in imgs.items():
            try:
                with Image.open(ip) as im:
                    isz = im.size
                    im.verify()
            except Exception as e:  # noqa: BLE001
                problems.append(f"{ip}: corrupt or not an image ({type(e).__name__})")
                continue
            by_size.setdefault(isz, []).append(ip)
            mp = masks.get(f)
            if mp is None:
                continue
            try:
                with Image.open(mp) as im:
                    msz = im.size
            except Exception as e:  # noqa: BLE001
                problems.append(f"{mp}: corrupt or not an image ({type(e).__name__})")
                continue
            if msz != isz:
                problems.append(f"{mp}: size {msz} differs from image {ip.name} size {isz}")
        if not by_size:
            continue
        size = max(by_size, key=lambda s: len(by_size[s]))
        cap.sizes[cam_id] = size
        for s, odd in by_size.items():
            if s != size:
                problems.append(f"{', '.join(str(q) for q in odd[:5])}{' ...' if len(odd) > 5 else ''}: {s[0]}x{s[1]}, "
                                f"but camera {cam_id}'s other {len(by_size[size])} images are {size[0]}x{size[1]} "
                                "(one size per camera)")
        c = cap.cams[cam_id]
        if not camera_problems(c["R"], c["K"]):
            problems += view_problems(f"{cpath} camera {names[cam_id]!r}", c["K"], c["R"], c["T"], size, roots)
    _split(cap, train_views, test_views, novel_pose_from)
    return cap


def summary(cap: Capture) -> str:
    """validate's last lines: cameras, frames per split, image size, fps, the poses' frame range."""
    s, frames = cap.split, cap.frames
    npf = s.get("novel_pose_from")
    train = [f for f in frames if npf is None or f < npf]
    sizes = sorted({f"{w}x{h}" for w, h in cap.sizes.values()})
    return "\n".join([
        f"cameras {sorted(cap.cams)}: train {s.get('train_views')}, held out {s.get('test_views')}",
        (f"frames: train {len(train)}, novel view {len(train)} x {len(s.get('test_views') or [])} cameras, "
         f"novel pose {len(frames) - len(train)} x {len(s.get('test_views') or [])} cameras"),
        f"images {', '.join(sizes)}; fps {cap.fps:g}; poses of frames {frames[0]}..{frames[-1]} ({len(frames)} files)",
        *cap.notes])


def validate(folder: str | Path, train_views=None, test_views=None, novel_pose_from=None, fps=None,
             person=None) -> Capture:
    """Raise CaptureError listing every problem at once; return what was read when the capture is usable."""
    cap = scan(folder, train_views, test_views, novel_pose_from, fps, person)
    if cap.problems:
        raise CaptureError(Path(folder), cap.problems)
    return cap


def convert(folder: str | Path, out_root: str | Path, name: str, train_views: Sequence[int] | None = None,
            test_views: Sequence[int] | None = None, novel_pose_from: int | None = None, body=None,
            fps: float | None = None, person: int | None = None, smpl_dir: str | None = None) -> Path:
    """Write <out_root>/<name>-train, -novelview, -novelpose and <name>-meta.json (fps, split), and <name>-betas.npz
    when the poses carry betas. Frames >= novel_pose_from go to -novelpose. Defaults (named on stdout): test_views
    the last camera, train_views the others, novel_pose_from the last fifth of the frames. body: a BodyModel, or
    "mannequin" / "smpl" (with smpl_dir; built with the capture's betas) for the joints fields. Nothing is written
    unless every split can be trained. Returns the -train folder."""
    from PIL import Image

    from realityavatar.body import build_body

    folder, out_root = Path(folder), Path(out_root)
    body = build_body("mannequin") if body is None or body == "mannequin" else body
    pelvis = None if isinstance(body, str) else body.rest_joints[0].detach().cpu().double().numpy()
    cap = scan(folder, train_views, test_views, novel_pose_from, fps, person, pelvis)
    if cap.problems:
        raise CaptureError(folder, cap.problems)
    for note in cap.notes:
        print(f"convert: {note}")
    frames, smpl, cams = cap.frames, cap.smpl, cap.cams
    train_views, test_views, npf = (cap.split[k] for k in ("train_views", "test_views", "novel_pose_from"))
    betas = [smpl[f]["betas"] for f in frames if "betas" in smpl[f]]
    betas = np.mean(np.stack(betas), 0) if betas and len({b.size for b in betas}) == 1 else None
    if isinstance(body, str):  # "smpl": shaped by the capture's betas, as training will be (body.betas=<file>)
        body = build_body("smpl", model_dir=smpl_dir, betas=None if betas is None else betas.tolist())
    train_frames, pose_frames = [f for f in frames if f < npf], [f for f in frames if f >= npf]
    place = {f: _placement(smpl[f]) for f in frames}
    with torch.no_grad():
        P = torch.as_tensor(np.stack([place[f][0] for f in frames]), dtype=torch.float32).reshape(-1, 24, 3)
        joints = body.joints(P).numpy()  # [F,24,3] body-local posed joints (HumanNeRF's "joints")
    rest = body.rest_joints.detach().cpu().numpy()
    jrow = {f: i for i, f in enumerate(frames)}
    layout = {"train": (train_views, train_frames), "novelview": (test_views, train_frames),
              "novelpose": (test_views, pose_frames)}
    names = {int(k): k for k in json.loads((folder / "cameras.json").read_text())}
    for suffix, (views, fr) in layout.items():
        out = I3DSplitWriter(out_root / f"{name}-{suffix}", rest if suffix == "train" else None)
        for f in fr:
            poses, Rh, Th = place[f]
            info = {"poses": poses.astype(np.float32), "Rh": Rh.astype(np.float32), "Th": Th.astype(np.float32),
                    "joints": joints[jrow[f]], "tpose_joints": rest}
            for v in views:
                c = cams[v]
                E = np.eye(4)
                E[:3, :3], E[:3, 3] = c["R"], c["T"]
                ip = _frames_in(folder / "images" / names[v], IMAGE_EXTS)[f]
                mp = folder / "masks" / names[v] / f"{f:06d}.png"
                img = np.asarray(Image.open(ip).convert("RGB"))
                m = np.asarray(Image.open(mp))
                m = (m[..., 0] if m.ndim == 3 else m) != 0
                img = img * m[..., None]  # the layout's images have a black background
                out.add(f, v, img.astype(np.uint8), (m * 255).astype(np.uint8), c["K"].astype(np.float32),
                        E.astype(np.float32), info, c["D"].astype(np.float32))
        out.close()
    if betas is not None:
        np.savez(out_root / f"{name}-betas.npz", betas=betas)
    meta = {"fps": cap.fps, "capture": {"source": str(folder.resolve()), **cap.split,
                                        "frames": [frames[0], frames[-1]], "person": person}}
    (out_root / f"{name}-meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return out_root / f"{name}-train"


def train_command(out_root: Path, name: str, body: str, smpl_dir: str | None) -> str:
    """The training command for a converted capture, as it runs from here (this environment's realityavatar-train)."""
    exe = Path(sys.executable).parent / "realityavatar-train"
    cmd = [str(exe) if exe.is_file() else "realityavatar-train", "data=capture", f"data.root={out_root.resolve()}",
           f"data.sequence={name}", f"body={body}"]
    if body == "smpl":
        cmd += [f"body.model_dir={smpl_dir}"] if smpl_dir else []
        betas = out_root / f"{name}-betas.npz"
        cmd += [f"body.betas={betas.resolve()}"] if betas.is_file() else []
    return " ".join(cmd)


class _Defaults(argparse.ArgumentDefaultsHelpFormatter):
    """--help with every default: a value's as argparse writes it, a rule's (default None) in the help text."""

    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=".venv/bin/python -m realityavatar.data.capture",
                                 description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    fmt = _Defaults
    v = sub.add_parser("validate", help="report every problem of a capture folder, then a summary", formatter_class=fmt)
    c = sub.add_parser("convert", help="convert a capture folder into the I3D-Human layout", formatter_class=fmt)
    for p in (v, c):
        p.add_argument("capture")
        if p is c:
            p.add_argument("out_root")
            p.add_argument("--name", required=True, help="sequence name: writes <out_root>/<name>-train etc.")
        p.add_argument("--train-views", type=int, nargs="*", help="training cameras (default: all but the held-out)")
        p.add_argument("--test-views", type=int, nargs="*", help="held-out cameras (default: the last camera)")
        p.add_argument("--novel-pose-from", type=int, help=f"frames >= this are the novel poses (default: "
                       f"the last {NOVEL_POSE_SHARE:g} of the frames, at least one)")
        p.add_argument("--fps", type=float, help="the cameras' frame rate (default: capture.json's fps)")
        p.add_argument("--person", type=int, help="EasyMocap pose files: the person's 'id' (default: the file's only person)")
    c.add_argument("--body", choices=("mannequin", "smpl"), default="mannequin",
                   help="mannequin: no SMPL files needed; smpl: your SMPL model files (--smpl-dir)")
    c.add_argument("--smpl-dir", default=None, help="SMPL model folder (with --body smpl; default: $SMPL_DIR)")
    a = ap.parse_args(argv)
    split = (a.train_views, a.test_views, a.novel_pose_from)
    try:
        if a.cmd == "validate":
            cap = validate(a.capture, *split, a.fps, a.person)
            print(f"{a.capture}: OK\n{summary(cap)}")
        else:
            out = convert(a.capture, a.out_root, a.name, *split, a.body, a.fps, a.person, a.smpl_dir)
            print(f"wrote {out.parent}/{a.name}-train|-novelview|-novelpose|-meta.json; train with:\n"
                  f"{train_command(out.parent, a.name, a.body, a.smpl_dir)}")
    except (CaptureError, FileNotFoundError) as e:
        print(str(e), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
