"""The default body: the skinned "wooden" mannequin of the mannequin-x package (Apache-2.0) as a 24-joint BodyModel.

Its first 24 joints are SMPL's 24 in SMPL order; finger joints fold into the hand joints (22, 23), so LBS with our
24 joints reproduces the package's own skinning exactly whenever the fingers keep their rest (relaxed) pose.
"""

from __future__ import annotations

import numpy as np

from realityavatar.body.base import NUM_JOINTS, SMPL_PARENTS, BodyModel


def fold_joint_index(parents: tuple[int, ...], joint: int, keep: int = NUM_JOINTS) -> int:
    """Nearest ancestor of `joint` (itself included) whose index is below `keep`."""
    while joint >= keep:
        joint = parents[joint]
    return joint


def mannequin_arrays(kind: str = "wooden") -> dict[str, np.ndarray]:
    """Rest vertices [V,3], faces [F,3], skin weights [V,24], rest joints [24,3] from mannequin-x.

    The rest pose is the package's pose zero (T pose, relaxed SMPL-X hand mean), so BodyModel.forward(pose=0) gives
    exactly `Mannequin.vertices(rest_pose())`.
    """
    from mannequin import Mannequin

    if kind != "wooden":
        raise ValueError(f"mannequin kind: only the skinned 'wooden' mannequin has skin weights, got {kind!r}")
    m = Mannequin(kind)
    parents = tuple(int(p) for p in m.parents)
    if parents[:NUM_JOINTS] != SMPL_PARENTS:
        raise ValueError(f"mannequin-x: first 24 parents {parents[:NUM_JOINTS]} differ from SMPL's {SMPL_PARENTS}")
    rest = m.rest_pose()
    rest_vertices = np.asarray(m.vertices(rest), dtype=np.float64)  # [V,3]
    rest_joints = np.asarray(m.joint_transforms(rest)[:NUM_JOINTS, :3, 3], dtype=np.float64)  # [24,3]
    # Package skinning: up to 4 influences per vertex over all 54 joints (private fields; the package exposes no
    # public accessor). Fold every joint >= 24 (fingers) into its nearest ancestor among the first 24.
    idx = np.asarray(m._skin_joint_indices)  # [V,4]
    w = np.asarray(m._skin_weights, dtype=np.float64)  # [V,4]
    fold = np.array([fold_joint_index(parents, j) for j in range(len(parents))])
    weights = np.zeros((rest_vertices.shape[0], NUM_JOINTS), dtype=np.float64)  # [V,24]
    np.add.at(weights, (np.arange(idx.shape[0])[:, None].repeat(idx.shape[1], 1), fold[idx]), w)
    weights /= weights.sum(1, keepdims=True)
    return {
        "rest_vertices": rest_vertices.astype(np.float32),
        "faces": np.asarray(m.faces, dtype=np.int64),
        "skin_weights": weights.astype(np.float32),
        "rest_joints": rest_joints.astype(np.float32),
    }


_CACHE: dict[str, dict[str, np.ndarray]] = {}


class MannequinBody(BodyModel):
    """mannequin-x "wooden" mannequin (24,256 vertices, y up, metres, T rest pose) behind the BodyModel interface."""

    name = "mannequin"

    def __init__(self, kind: str = "wooden") -> None:
        super().__init__()
        if kind not in _CACHE:  # building the package's identity takes ~0.3 s; reuse it across instances
            _CACHE[kind] = mannequin_arrays(kind)
        a = _CACHE[kind]
        self.kind = kind
        self._set_buffers(a["rest_vertices"], a["faces"], a["skin_weights"], a["rest_joints"])
