"""Motion files (AMASS/SMPL-H, SMPL-X, SMPL [F,72]/[F,24,3]) read into a PoseTable at the run's frame rate, turned
upright into the dataset's world and placed where the training subject stood: the one reader of animate, view, export."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from realityavatar.body.base import NUM_JOINTS, rh_th_to_smpl
from realityavatar.data.poses import PoseTable
from realityavatar.geometry import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_slerp,
    quat_to_axis_angle,
)

RATE_FIELDS = ("mocap_framerate", "mocap_frame_rate", "fps")  # AMASS SMPL-H, AMASS SMPL-X, ours
TRANSL_FIELDS = ("trans", "transl")  # AMASS, SMPL-X / ours
SPLIT_FIELDS = (("global_orient", "body_pose"), ("root_orient", "pose_body"))  # SMPL-X parameters, AMASS SMPL-X
POSE_LAYOUTS = {24: "SMPL", 52: "SMPL-H (AMASS)", 55: "SMPL-X"}  # joints in 'poses'; the first 22 are SMPL's
POSES_EXPECTED = "[F,24,3] or [F,72] (SMPL), [F,156] (SMPL-H, AMASS) or [F,165] (SMPL-X)"
UP = {"y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
PLACES = ("subject", "keep")
SNAP_DEG = 15.0  # a mean body axis this close to a world axis is that axis
HEAD = 15


@dataclass(frozen=True)
class Stage:
    """The run's world and time, from its training poses: up [3] (unit), the ground's height along it, centre [3]
    (the training subject's mean pelvis) and fps (the frame rate the run was trained at)."""

    up: np.ndarray
    ground: float
    centre: np.ndarray
    fps: float

    @classmethod
    def of(cls, dm, body) -> Stage:
        """From a set-up DataModule (its training poses and data.fps) and the run's body model."""
        recorded = dm.scene.meta.get("fps")  # synthetic scenes record theirs
        fps = dm.fps if dm.fps is not None else recorded
        if fps is None:
            raise ValueError(f"{dm.scene.source}: the run's config has no data.fps (the frame rate its poses were "
                             "captured at; configs written before it existed): give data.fps=<frames per second>")
        if recorded is not None and abs(float(recorded) - fps) > 1e-6:
            raise ValueError(f"data.fps={fps:g} but the scene {dm.scene.source} was built at {recorded:g} fps "
                             "(its -meta.json): set data.fps to the scene's rate")
        _, poses, transl = dm.pose_sequence("train")
        joints = posed_joints(body, poses, transl)  # [F,24,3]
        up = snap(np.mean(joints[:, HEAD] - joints[:, 0], 0))
        return cls(up, float((joints @ up).min()), joints[:, 0].mean(0), float(fps))


def posed_joints(body, poses: torch.Tensor, transl: torch.Tensor) -> np.ndarray:
    """Joints [F,24,3] (float64, CPU) of poses [F,24,3], transl [F,3] on the body's device."""
    dev = body.rest_joints.device
    return body.joints(poses.to(dev, torch.float64), transl.to(dev, torch.float64)).cpu().numpy()


def snap(v: np.ndarray) -> np.ndarray:
    """Unit vector of v, or the signed world axis it is within SNAP_DEG of."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    axis = np.zeros(3)
    axis[np.abs(v).argmax()] = np.sign(v[np.abs(v).argmax()])
    return axis if v @ axis > np.cos(np.radians(SNAP_DEG)) else v


def turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3,3] taking unit vector a to unit vector b (a half turn about a perpendicular if opposite)."""
    axis, c = np.cross(a, b), float(np.clip(a @ b, -1, 1))
    if np.linalg.norm(axis) < 1e-9:
        axis = np.cross(a, np.eye(3)[np.abs(a).argmin()]) if c < 0 else a
    aa = axis / np.linalg.norm(axis) * np.arccos(c)
    return axis_angle_to_matrix(torch.from_numpy(aa)).numpy()


def resample(poses: torch.Tensor, transl: torch.Tensor, fps: float, to_fps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """poses [F,24,3], transl [F,3] sampled at `fps` -> the same motion at `to_fps` (slerp of every joint rotation,
    linear translation), from the first frame to the last sample at or before the last frame's time."""
    F = len(poses)
    t = np.arange(int(np.floor((F - 1) * to_fps / fps + 1e-9)) + 1) * (fps / to_fps)  # source positions [G]
    i0 = torch.as_tensor(np.minimum(np.floor(t + 1e-9).astype(np.int64), F - 1))
    i1 = (i0 + 1).clamp(max=F - 1)
    w = torch.as_tensor(t, dtype=poses.dtype) - i0.to(poses.dtype)  # [G]
    q = matrix_to_quat(axis_angle_to_matrix(poses))  # [F,24,4]
    pose = quat_to_axis_angle(quat_slerp(q[i0], q[i1], w[:, None].expand(-1, NUM_JOINTS)))
    return pose, transl[i0] + w[:, None] * (transl[i1] - transl[i0])


def read_pose_file(path: Path, body, fps: float | None = None) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The file's SMPL-order poses [F,24,3], SMPL transl [F,3] (float64, the file's world) and frame rate (`fps`
    given here overrides the file's field). Errors name the file and the field."""
    if not path.is_file():
        raise FileNotFoundError(f"pose file {path} not found")
    try:
        z = np.load(path)
        names = list(z.keys())
    except Exception as e:  # noqa: BLE001 - a pickle, a truncated zip, another format
        raise ValueError(f"{path}: not a readable .npz pose file ({type(e).__name__}: {e})") from None
    with z:
        def field(key: str, widths: tuple[int, ...], frames: int | None = None, want: str = "") -> np.ndarray:
            a = np.asarray(z[key], np.float64)
            F = len(a) if a.ndim else 0
            if F == 0 or a.size // F not in widths or (frames is not None and F != frames):
                want = want or " or ".join(f"[{frames or 'F'},{w}]" for w in widths)
                raise ValueError(f"{path}: field {key!r} must be {want}, got {a.shape}"
                                 + (" (no frames)" if F == 0 else ""))
            a = a.reshape(F, -1)
            bad = ~np.isfinite(a).all(1)
            if bad.any():
                raise ValueError(f"{path}: field {key!r} has non-finite values (NaN/inf) at frames "
                                 f"{np.flatnonzero(bad)[:10].tolist()}")
            return a

        split = next((k for k in SPLIT_FIELDS if k[0] in z and k[1] in z), None)
        if "poses" in z:
            p = field("poses", tuple(3 * j for j in POSE_LAYOUTS), want=POSES_EXPECTED)
            p = p.reshape(len(p), -1, 3)
        elif split:
            root = field(split[0], (3,))
            p = np.concatenate([root, field(split[1], (63, 69), len(root))], 1).reshape(len(root), -1, 3)
        else:
            raise KeyError(f"{path}: no pose field: expected 'poses' {POSES_EXPECTED}, or 'global_orient' + "
                           f"'body_pose' (SMPL-X), or 'root_orient' + 'pose_body'; fields present: {names}")
        F = len(p)
        poses = np.zeros((F, NUM_JOINTS, 3))
        keep = NUM_JOINTS if p.shape[1] == NUM_JOINTS else 22  # SMPL-H/-X hands are not SMPL's hand joints 22-23
        poses[:, :keep] = p[:, :keep]
        tkey = next((k for k in TRANSL_FIELDS if k in z), None)
        transl = field(tkey, (3,), F) if tkey else np.zeros((F, 3))
        if ("Rh" in z) != ("Th" in z):
            raise ValueError(f"{path}: fields 'Rh' and 'Th' come together (EasyMocap placement); only "
                             f"{'Rh' if 'Rh' in z else 'Th'} is present")
        P, T = torch.from_numpy(poses), torch.from_numpy(transl)
        if "Rh" in z:
            P, T = rh_th_to_smpl(P, torch.from_numpy(field("Rh", (3,), F)),
                                 torch.from_numpy(field("Th", (3,), F)) + T, body.rest_joints[0].cpu().double())
        if fps is None:
            rkey = next((k for k in RATE_FIELDS if k in z), None)
            if rkey is None:
                raise ValueError(f"{path}: no frame rate: the file has none of the fields {list(RATE_FIELDS)}; "
                                 "give it on the command line (fps=<frames per second>)")
            rate = np.asarray(z[rkey], np.float64)
            fps = float(rate.reshape(-1)[0]) if rate.size == 1 else float("nan")
            where = f"field {rkey!r}"
        else:
            where = "fps="
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"{path}: {where} must be one frame rate > 0 (frames per second), got {fps}")
    return P, T, float(fps)


def load_motion(path: str | Path, body, stage: Stage, fps: float | None = None, up: str = "auto",
                place: str = "subject") -> PoseTable:
    """A pose file as the run sees it: resampled from its frame rate (its field, or `fps`) to stage.fps, turned so
    that its up axis (`up`: y, z, or auto = the body's mean head-above-pelvis axis) is the dataset's, and with
    place=subject moved so its mean pelvis stands on the dataset's ground where the training subject stood
    (place=keep: the file's coordinates, only turned)."""
    path = Path(path)
    if up not in (*UP, "auto"):
        raise ValueError(f"up={up!r}: expected one of {[*UP, 'auto']} (the file's up axis; AMASS is z)")
    if place not in PLACES:
        raise ValueError(f"place={place!r}: expected one of {list(PLACES)}")
    poses, transl, rate = read_pose_file(path, body, fps)
    poses, transl = resample(poses, transl, rate, stage.fps)
    joints = posed_joints(body, poses, transl)  # [G,24,3] in the file's world
    file_up = snap(np.mean(joints[:, HEAD] - joints[:, 0], 0)) if up == "auto" else np.asarray(UP[up])
    R = turn(file_up, stage.up)
    # x' = R x for every posed point: the root turns by R and SMPL's transl (applied after the rotation about the
    # pelvis J0) becomes R (J0 + t) - J0.
    J0 = body.rest_joints[0].cpu().double()
    Rt = torch.from_numpy(R)
    poses[:, 0] = matrix_to_axis_angle(Rt @ axis_angle_to_matrix(poses[:, 0]))
    transl = (J0 + transl) @ Rt.T - J0
    if place == "subject":
        joints = joints @ R.T
        pelvis = joints[:, 0].mean(0)
        flat = stage.centre - pelvis - ((stage.centre - pelvis) @ stage.up) * stage.up
        transl = transl + torch.from_numpy(flat + (stage.ground - (joints @ stage.up).min()) * stage.up)
    return PoseTable.from_sequence(poses.float(), transl.float())
