"""Writers for tiny fixture datasets in the exact on-disk layouts (I3D-Human/HumanNeRF, ZJU-MoCap ARAH) for reader tests.

Each image shows a filled disc around the projected pelvis joint; the mask is the same disc, so tests can check that a
joint projects inside its mask.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from realityavatar.body.base import SMPL_PARENTS, BodyModel, rh_th_to_smpl
from realityavatar.data.i3d import I3DSplitWriter
from realityavatar.data.synthetic.cameras import look_at as _look_at

SIZE = 48  # image width = height
FOCAL = 60.0
DISC = 5  # disc radius in pixels


class RandomBody(BodyModel):
    """24 made-up joints (SMPL tree, normal offsets of `spread` m), each wrapped in a small tetrahedron skinned 100%
    to it: FK for the readers, a mesh with area for surface sampling. The one stand-in body of the tests."""

    name = "random"

    def __init__(self, seed: int = 7, pelvis=(0.0, 0.9, 0.02), spread: float = 0.1) -> None:
        super().__init__()
        rng = np.random.default_rng(seed)
        J = np.zeros((24, 3))
        J[0] = pelvis  # off the origin by default, so the Rh/Th -> SMPL conversion matters
        for j in range(1, 24):
            J[j] = J[SMPL_PARENTS[j]] + rng.normal(0, spread, 3)
        tet = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64) * 0.03
        verts = (J[:, None, :] + tet[None]).reshape(-1, 3)
        faces = np.concatenate([np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]) + 4 * j for j in range(24)])
        self._set_buffers(verts, faces, np.repeat(np.eye(24), 4, axis=0), J)


def look_at(eye, target=(0.0, 0.9, 0.0), up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """The scene generator's look_at (OpenCV world-to-camera [4,4]), aimed at the fixture body by default."""
    return _look_at(np.asarray(eye, float), np.asarray(target, float), up)


def camera(view: int, n_views: int = 12, dist: float = 3.0):
    a = 2 * math.pi * view / n_views
    E = look_at([dist * math.sin(a), 1.0, dist * math.cos(a)])
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    return K, E


def project(K, E, X) -> np.ndarray:
    """X [3] world -> pixel [2] (gsplat/pixel-area convention is irrelevant at this tolerance)."""
    x = E[:3, :3] @ X + E[:3, 3]
    return (K @ x)[:2] / x[2]


def draw(uv, color, size: int = SIZE):
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    disc = (xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= DISC**2
    img = np.zeros((size, size, 3), np.uint8)
    img[disc] = color
    return img, (disc * 255).astype(np.uint8)


def motion(frames, seed: int = 0):
    """EasyMocap-style per-frame poses [F,72] (poses[:3] = 0), Rh [F,3], Th [F,3]."""
    rng = np.random.default_rng(seed)
    F = len(frames)
    poses = rng.normal(0, 0.2, (F, 72))
    poses[:, :3] = 0
    t = np.asarray(frames, dtype=np.float64)
    Rh = np.stack([0.1 * np.sin(t / 7), 0.3 * t / max(t.max(), 1), 0.05 * np.ones_like(t)], -1)
    Th = np.stack([0.02 * t, 0.01 * np.ones_like(t), -0.01 * t], -1)
    return poses, Rh, Th


def world_pelvis(body: BodyModel, poses, Rh, Th) -> np.ndarray:
    """World pelvis [F,3] under EasyMocap placement, computed through the body's FK after rh_th_to_smpl."""
    p, tr = rh_th_to_smpl(torch.as_tensor(poses).reshape(-1, 24, 3), torch.as_tensor(Rh), torch.as_tensor(Th),
                          body.rest_joints[0].double())
    return copy.deepcopy(body).double().joints(p, tr)[:, 0].numpy()


def write_i3d(root, sequence, body, train_frames=(0, 1, 2, 3), pose_frames=(4, 5), train_views=(0, 1),
              test_views=(2,), seed=0, distortions=None):
    """Write <root>/<sequence>-train/-novelview/-novelpose. Returns a dict with what was written."""
    root = Path(root)
    frames = sorted(set(train_frames) | set(pose_frames))
    poses, Rh, Th = motion(frames, seed)
    by_frame = {f: i for i, f in enumerate(frames)}
    pelvis_w = world_pelvis(body, poses, Rh, Th)
    layout = {"train": (train_frames, train_views), "novelview": (train_frames, test_views),
              "novelpose": (pose_frames, test_views)}
    written = {"frames": frames, "poses": poses, "Rh": Rh, "Th": Th, "pelvis_world": pelvis_w, "cameras": {}}
    for folder, (fr, views) in layout.items():
        out = I3DSplitWriter(root / f"{sequence}-{folder}", body.rest_joints.numpy() if folder == "train" else None)
        for f in fr:
            i = by_frame[f]
            info = {"poses": poses[i], "Rh": Rh[i], "Th": Th[i], "joints": np.zeros((24, 3)),
                    "tpose_joints": body.rest_joints.numpy()}
            for v in views:
                K, E = camera(v)
                written["cameras"][v] = (K, E)
                img, mask = draw(project(K, E, pelvis_w[i]), (200, (100 + 20 * v) % 256, 50))
                out.add(f, v, img, mask, K, E, info, None if distortions is None else np.asarray(distortions))
        out.close()
    return written


def write_i3d_release(root, sequence, body, n_frames=60, start=10, split_at=40, train_every=5, novel_every=10,
                      train_views=(0, 1), test_views=(2,), seed=0, frame_interval=1, frameid_pose=True):
    """Write <root>/<sequence>-train/-novelview/-novelpose as I3D-Human is released: the image folders hold every
    `train_every`-th frame of [start, split_at) (-train), every `novel_every`-th of it (-novelview) and of
    [split_at, n_frames) (-novelpose); with `frameid_pose`, each split's frameid_pose.pkl holds the whole motion in
    Dyco's format, a list whose entry k is frame k * frame_interval ({'poses': [23,3], 'Rh', 'Th'}).
    Returns the dense motion (poses [F,72], Rh, Th over frames 0..n_frames-1) and each split's frames."""
    import pickle

    root = Path(root)
    frames = list(range(n_frames))
    poses, Rh, Th = motion(frames, seed)
    pelvis_w = world_pelvis(body, poses, Rh, Th)
    layout = {"train": (list(range(start, split_at, train_every)), train_views),
              "novelview": (list(range(start, split_at, novel_every)), test_views),
              "novelpose": (list(range(split_at, n_frames, novel_every)), test_views)}
    dense = [{"poses": poses[f].reshape(24, 3)[1:].astype(np.float32), "Rh": Rh[f].astype(np.float32),
              "Th": Th[f].astype(np.float32)} for f in range(0, n_frames, frame_interval)]
    for folder, (fr, views) in layout.items():
        out = I3DSplitWriter(root / f"{sequence}-{folder}", body.rest_joints.numpy() if folder == "train" else None)
        for f in fr:
            info = {"poses": poses[f], "Rh": Rh[f], "Th": Th[f], "joints": np.zeros((24, 3)),
                    "tpose_joints": body.rest_joints.numpy()}
            for v in views:
                K, E = camera(v)
                img, mask = draw(project(K, E, pelvis_w[f]), (200, (100 + 20 * v) % 256, 50))
                out.add(f, v, img, mask, K, E, info)
        out.close()
        if frameid_pose:
            with open(root / f"{sequence}-{folder}" / "frameid_pose.pkl", "wb") as fh:
                pickle.dump(dense, fh)
    return {"poses": poses, "Rh": Rh, "Th": Th, "frames": {k: v[0] for k, v in layout.items()}}


def write_zju(root, subject="CoreView_377", body=None, n_frames=6, cams=("1", "2", "3"), seed=0, size=SIZE):
    """Write <root>/<subject> in the ARAH layout: cam_params.json, <cam>/<idx:06d>.jpg|.png, models/<idx:06d>.npz."""
    d = Path(root) / subject
    (d / "models").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    params = {"all_cam_names": list(cams)}
    root_orient = rng.normal(0, 0.2, (n_frames, 3))
    pose_body = rng.normal(0, 0.2, (n_frames, 63))
    pose_hand = rng.normal(0, 0.1, (n_frames, 6))
    trans = np.stack([np.linspace(0, 0.2, n_frames), np.full(n_frames, 0.05), np.zeros(n_frames)], -1)
    pose = np.concatenate([root_orient, pose_body, pose_hand], -1).reshape(n_frames, 24, 3)
    pelvis_w = copy.deepcopy(body).double().joints(torch.as_tensor(pose), torch.as_tensor(trans))[:, 0].numpy()
    for c in cams:
        K, E = camera(int(c))
        params[c] = {"K": K.tolist(), "D": [[0.0]] * 5, "R": E[:3, :3].tolist(), "T": E[:3, 3:].tolist()}
        (d / c).mkdir(exist_ok=True)
        for f in range(n_frames):
            img, mask = draw(project(K, E, pelvis_w[f]), (90, 180, 40), size)
            bgimg = img.copy()
            bgimg[mask == 0] = (30, 60, 90)  # ZJU images have a real background; the reader must composite it away
            Image.fromarray(bgimg).save(d / c / f"{f:06d}.jpg", quality=95)
            Image.fromarray((mask > 0).astype(np.uint8)).save(d / c / f"{f:06d}.png")  # ZJU masks are 0/1 labels
    for f in range(n_frames):
        np.savez(d / "models" / f"{f:06d}.npz", minimal_shape=np.zeros((10, 3)), betas=np.zeros((1, 10)),
                 Jtr_posed=np.zeros((24, 3)), bone_transforms=np.tile(np.eye(4), (24, 1, 1)), trans=trans[f],
                 root_orient=root_orient[f], pose_body=pose_body[f], pose_hand=pose_hand[f])
    with open(d / "cam_params.json", "w") as fh:
        json.dump(params, fh)
    return {"pose": pose, "trans": trans, "pelvis_world": pelvis_w}

def pixel_in_mask(mask: np.ndarray, uv) -> bool:
    """Whether pixel position uv [2] falls on a set pixel of mask [H,W]."""
    x, y = int(np.floor(uv[0])), int(np.floor(uv[1]))
    return 0 <= x < mask.shape[1] and 0 <= y < mask.shape[0] and bool(mask[y, x])


# Pose-file layouts of data/motion.py: how many joints `poses` holds, and the frame-rate field's name.
MOTION_LAYOUTS = ("amass_smplh", "amass_smplx", "amass_smplx_split", "smplx_split", "smpl", "smpl_24x3")


def write_motion(path: Path, layout: str = "amass_smplh", fps: float = 120.0, seconds: float = 1.0,
                 omega: float = 3.0, offset=(4.0, -3.0, 0.95)) -> dict:
    """A known motion in a Z-up world, written in one of MOTION_LAYOUTS: the root turns about +z at `omega` rad/s
    (upright: the body's y axis along world z), the left knee bends and straightens once, hand/face joints are set
    (they must not reach SMPL's joints 22-23), and the translation is `offset` plus a slow walk along x.
    Returns the body pose [F,24,3] (SMPL order, hands 22-23 zero) and trans [F,3] the file holds, float64."""
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

    F = round(seconds * fps) + 1
    t = np.arange(F) / fps
    spin = torch.zeros(F, 3, dtype=torch.float64)
    spin[:, 2] = torch.as_tensor(omega * t)
    stand = axis_angle_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))  # body y -> world z
    body = np.zeros((F, 24, 3))
    body[:, 0] = matrix_to_axis_angle(axis_angle_to_matrix(spin) @ stand).numpy()
    body[:, 4, 0] = 0.5 * (1 - np.cos(2 * np.pi * t))  # left knee
    trans = np.asarray(offset, float) + np.outer(t, [0.2, 0.0, 0.0])
    full = np.full((F, 55, 3), 0.3)  # SMPL-X: 22 body, jaw, 2 eyes, 2 x 15 finger joints
    full[:, :22] = body[:, :22]
    smplh = np.concatenate([full[:, :22], full[:, 25:]], 1)  # SMPL-H: 22 body, 2 x 15 finger joints
    beta = {"betas": np.zeros(16), "gender": np.array("female")}
    fields = {
        "amass_smplh": {"poses": smplh.reshape(F, 156), "trans": trans, "mocap_framerate": np.array(fps), **beta},
        "amass_smplx": {"poses": full.reshape(F, 165), "trans": trans, "mocap_frame_rate": np.array(fps), **beta},
        "amass_smplx_split": {"root_orient": full[:, 0], "pose_body": full[:, 1:22].reshape(F, 63),
                              "pose_hand": full[:, 25:].reshape(F, 90), "trans": trans, "mocap_frame_rate": fps, **beta},
        "smplx_split": {"global_orient": full[:, 0], "body_pose": full[:, 1:22].reshape(F, 63),
                        "jaw_pose": full[:, 22], "left_hand_pose": full[:, 25:40].reshape(F, 45), "transl": trans,
                        "fps": fps},
        "smpl": {"poses": body.reshape(F, 72), "transl": trans, "fps": fps},
        "smpl_24x3": {"poses": body, "transl": trans, "fps": fps},
    }[layout]
    np.savez(path, **fields)
    return {"pose": body, "trans": trans, "fps": fps, "omega": omega}
