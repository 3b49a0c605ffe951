"""Bring your own capture: validate a simple folder format and convert it into the I3D-Human layout the readers use.

Input folder (see docs/data.md):
  cameras.json            {"<cam id, int>": {"K": [3,3], "R": [3,3], "T": [3] (world-to-camera, metres), "D": [5]?}}
  images/<cam>/<frame:06d>.png|.jpg    masks/<cam>/<frame:06d>.png (0 = background, anything else = person)
  smpl/<frame:06d>.npz|.json           {"poses": [72], "transl": [3]}  (SMPL: poses[:3] = global orientation)
                                    or {"poses": [72], "Rh": [3], "Th": [3]}  (EasyMocap placement); "betas" optional
Usage: python -m realityavatar.data.capture validate CAPTURE
       python -m realityavatar.data.capture convert CAPTURE OUT_ROOT --name NAME --train-views 0 1 2 --test-views 3
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from realityavatar.data.i3d import I3DSplitWriter
from realityavatar.data.records import camera_problems

IMAGE_EXTS = (".png", ".jpg", ".jpeg")


class CaptureError(ValueError):
    """Every problem found in a capture folder, one per line."""

    def __init__(self, folder: Path, problems: list[str]) -> None:
        self.problems = problems
        lines = "\n".join(f"  - {p}" for p in problems)
        super().__init__(f"capture {folder}: {len(problems)} problem(s):\n{lines}")


def _frames_in(d: Path, exts: Sequence[str]) -> dict[int, Path]:
    out = {}
    if d.is_dir():
        for p in sorted(d.iterdir()):
            if p.suffix.lower() in exts and p.stem.isdigit():
                out[int(p.stem)] = p
    return out


def _read_smpl(p: Path) -> dict[str, np.ndarray]:
    if p.suffix == ".npz":
        with np.load(p) as z:
            return {k: np.asarray(z[k], dtype=np.float64) for k in z.files}
    return {k: np.asarray(v, dtype=np.float64) for k, v in json.loads(p.read_text()).items()}


def scan(folder: str | Path, train_views: Sequence[int] | None = None, test_views: Sequence[int] | None = None):
    """Check everything and collect every problem. Returns (problems, cameras, frames, smpl) with what could be read."""
    from PIL import Image

    folder = Path(folder)
    problems: list[str] = []
    cams: dict[int, dict[str, np.ndarray]] = {}
    smpl: dict[int, dict[str, np.ndarray]] = {}
    if not folder.is_dir():
        return [f"folder {folder} does not exist"], cams, [], smpl
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
    for key, c in raw.items():
        where = f"{cpath} camera {key!r}"
        try:
            cam_id = int(key)
        except ValueError:
            problems.append(f"{where}: camera ids must be integers (they become view_YY)")
            continue
        ok = True
        arrs = {}
        for field, shape in (("K", (3, 3)), ("R", (3, 3)), ("T", (3,)), ("D", (5,))):
            if field not in c:
                if field != "D":
                    problems.append(f"{where}: missing {field} (expected {list(shape)})")
                    ok = False
                continue
            try:
                a = np.asarray(c[field], dtype=np.float64)
            except (TypeError, ValueError):
                problems.append(f"{where}: {field} is not numeric")
                ok = False
                continue
            if a.size != int(np.prod(shape)):
                problems.append(f"{where}: {field} has shape {list(a.shape)}, expected {list(shape)}")
                ok = False
                continue
            a = a.reshape(shape)
            if not np.isfinite(a).all():
                problems.append(f"{where}: {field} has non-finite values")
                ok = False
            arrs[field] = a
        if ok and "R" in arrs:
            # reported, the camera kept: its images are checked too (all problems at once; nothing is converted)
            problems += [f"{where}: {p}" for p in camera_problems(arrs["R"], arrs["K"])]
        if ok:
            arrs.setdefault("D", np.zeros(5))
            cams[cam_id] = arrs
    # SMPL
    smpl_files = {**_frames_in(folder / "smpl", (".json",)), **_frames_in(folder / "smpl", (".npz",))}
    if not smpl_files:
        problems.append(f"{folder / 'smpl'}: no <frame:06d>.npz/.json files")
    for f, p in sorted(smpl_files.items()):
        try:
            d = _read_smpl(p)
        except Exception as e:  # noqa: BLE001
            problems.append(f"{p}: unreadable ({type(e).__name__}: {e})")
            continue
        if "poses" not in d:
            problems.append(f"{p}: missing 'poses' ([72] axis-angle)")
            continue
        if d["poses"].size != 72:
            problems.append(f"{p}: poses has {d['poses'].size} values, expected 72")
            continue
        has_smpl, has_em = "transl" in d, "Rh" in d and "Th" in d
        if not (has_smpl or has_em):
            problems.append(f"{p}: needs 'transl' [3] (SMPL convention) or 'Rh' and 'Th' [3] (EasyMocap)")
            continue
        fields = ("poses", "transl") if has_smpl else ("poses", "Rh", "Th")
        bad = [k for k in fields if d[k].size != (72 if k == "poses" else 3)]
        if bad:
            problems.append(f"{p}: wrong sizes for {bad}")
            continue
        nonfinite = [k for k in fields if not np.isfinite(d[k]).all()]
        if nonfinite:
            problems.append(f"{p}: non-finite values (NaN/inf) in {nonfinite}")
            continue
        smpl[f] = d
    frames = sorted(smpl_files)
    # images and masks per camera
    for cam_id in sorted(cams):
        img_dir, mask_dir = folder / "images" / str(cam_id), folder / "masks" / str(cam_id)
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
        for f, ip in imgs.items():
            try:
                with Image.open(ip) as im:
                    isz = im.size
                    im.verify()
            except Exception as e:  # noqa: BLE001
                problems.append(f"{ip}: corrupt or not an image ({type(e).__name__})")
                continue
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
    img_root = folder / "images"
    if img_root.is_dir():
        stray = sorted(p.name for p in img_root.iterdir() if p.is_dir() and p.name.isdigit() and int(p.name) not in cams
                       and str(p.name) not in raw)
        if stray:
            problems.append(f"{img_root}: image folders {stray} have no camera in cameras.json")
    for what, views in (("train_views", train_views), ("test_views", test_views)):
        for v in views or []:
            if int(v) not in cams and str(v) not in raw:
                problems.append(f"{what}: camera {v} is not in cameras.json")
    if train_views is not None and not list(train_views):
        problems.append("train_views is empty")
    return problems, cams, frames, smpl


def validate(folder: str | Path, train_views=None, test_views=None) -> None:
    """Raise CaptureError listing every problem at once; return None when the capture is usable."""
    problems, *_ = scan(folder, train_views, test_views)
    if problems:
        raise CaptureError(Path(folder), problems)


def _placement(d: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(poses [72], Rh [3], Th [3]) in EasyMocap placement. SMPL input maps to Rh = 0, Th = transl exactly."""
    poses = d["poses"].reshape(72)
    if "transl" in d:
        return poses, np.zeros(3), d["transl"].reshape(3)
    return poses, d["Rh"].reshape(3), d["Th"].reshape(3)


def convert(folder: str | Path, out_root: str | Path, name: str, train_views: Sequence[int] | None = None,
            test_views: Sequence[int] | None = None, novel_pose_from: int | None = None, body=None) -> Path:
    """Write <out_root>/<name>-train, -novelview, -novelpose. Frames >= novel_pose_from go to -novelpose.

    train_views default: all cameras except test_views; test_views default: none. body: a BodyModel for the
    joints/tpose_joints fields (default: the mannequin). Returns the -train folder.
    """
    from PIL import Image

    folder, out_root = Path(folder), Path(out_root)
    problems, cams, frames, smpl = scan(folder, train_views, test_views)
    if problems:
        raise CaptureError(folder, problems)
    test_views = [int(v) for v in (test_views or [])]
    train_views = [int(v) for v in train_views] if train_views is not None else [c for c in cams if c not in test_views]
    if body is None:
        from realityavatar.body.mannequin import MannequinBody

        body = MannequinBody()
    train_frames = [f for f in frames if novel_pose_from is None or f < novel_pose_from]
    pose_frames = [f for f in frames if novel_pose_from is not None and f >= novel_pose_from]
    if not train_frames:
        raise CaptureError(folder, [f"no training frames before novel_pose_from={novel_pose_from}"])
    place = {f: _placement(smpl[f]) for f in frames}
    with torch.no_grad():
        P = torch.as_tensor(np.stack([place[f][0] for f in frames]), dtype=torch.float32).reshape(-1, 24, 3)
        joints = body.joints(P).numpy()  # [F,24,3] body-local posed joints (HumanNeRF's "joints")
    rest = body.rest_joints.detach().cpu().numpy()
    jrow = {f: i for i, f in enumerate(frames)}
    layout = {"train": (train_views, train_frames), "novelview": (test_views, train_frames),
              "novelpose": (test_views, pose_frames)}
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
                ip = _frames_in(folder / "images" / str(v), IMAGE_EXTS)[f]
                mp = folder / "masks" / str(v) / f"{f:06d}.png"
                img = np.asarray(Image.open(ip).convert("RGB"))
                m = np.asarray(Image.open(mp))
                m = (m[..., 0] if m.ndim == 3 else m) != 0
                img = img * m[..., None]  # the layout's images have a black background
                out.add(f, v, img.astype(np.uint8), (m * 255).astype(np.uint8), c["K"].astype(np.float32),
                        E.astype(np.float32), info, c["D"].astype(np.float32))
        out.close()
    return out_root / f"{name}-train"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m realityavatar.data.capture", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("validate", help="report every problem of a capture folder")
    v.add_argument("capture")
    v.add_argument("--train-views", type=int, nargs="*")
    v.add_argument("--test-views", type=int, nargs="*")
    c = sub.add_parser("convert", help="convert a capture folder into the I3D-Human layout")
    c.add_argument("capture")
    c.add_argument("out_root")
    c.add_argument("--name", required=True, help="sequence name: writes <out_root>/<name>-train etc.")
    c.add_argument("--train-views", type=int, nargs="*")
    c.add_argument("--test-views", type=int, nargs="*", default=[])
    c.add_argument("--novel-pose-from", type=int, default=None, help="frames >= this go to -novelpose")
    c.add_argument("--body", choices=("mannequin", "smpl"), default="mannequin")
    c.add_argument("--smpl-dir", default=None, help="SMPL model folder (with --body smpl)")
    a = ap.parse_args(argv)
    try:
        if a.cmd == "validate":
            validate(a.capture, a.train_views, a.test_views)
            print(f"{a.capture}: OK")
        else:
            from realityavatar.body import build_body

            body = build_body("smpl", model_dir=a.smpl_dir) if a.body == "smpl" else build_body("mannequin")
            out = convert(a.capture, a.out_root, a.name, a.train_views, a.test_views, a.novel_pose_from, body)
            print(f"wrote {out.parent}/{a.name}-train|-novelview|-novelpose; train with: realityavatar-train "
                  f"data=capture data.root={out.parent} data.sequence={a.name} body={a.body}")
    except (CaptureError, FileNotFoundError) as e:
        print(str(e), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
