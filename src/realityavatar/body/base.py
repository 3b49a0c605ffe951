"""The body-model interface every body (mannequin, SMPL) implements: 24 SMPL-order joints and LBS.

Conventions (shared with the data readers and the avatar model):
- pose: [...,24,3] axis-angle, SMPL order; pose[...,0,:] is the global orientation about the pelvis joint.
- transl: [...,3] added after the rotation, as in SMPL.
- forward() returns bone transforms [...,24,4,4] that map *rest-pose* (pose = 0) body points to posed points.
- A *canonical* pose (a star/A pose with the legs apart, see `canonical_pose`) is where the avatar's
  Gaussians live; `canonical_transforms(pose, transl)` maps canonical points to posed points.
"""

from __future__ import annotations

import copy
import functools
import math

import torch
from torch import nn

from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle, rigid, transform_points

NUM_JOINTS = 24
SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)


def check_pose_shape(pose: torch.Tensor, transl: torch.Tensor | None, where: str = "pose") -> None:
    """Raise a ValueError naming the field when a pose or translation has a wrong shape (no read of the values:
    the model's forward path calls this, and on a GPU a read of a device tensor waits for the device)."""
    if pose.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"{where}: expected axis-angle pose of shape [...,24,3], got {tuple(pose.shape)}")
    if transl is not None and transl.shape[-1] != 3:
        raise ValueError(f"{where}: expected translation of shape [...,3], got {tuple(transl.shape)}")


def canonical_pose(dtype=torch.float32, leg_angle_deg: float = 30.0, arm_angle_deg: float = 0.0,
                   device: torch.device | str | None = None) -> torch.Tensor:
    """Star/A pose [24,3]: legs rotated apart about the forward (z) axis so the inner thighs separate."""
    pose = torch.zeros(NUM_JOINTS, 3, dtype=dtype, device=device)
    a = math.radians(leg_angle_deg)
    pose[1, 2] = a  # left hip
    pose[2, 2] = -a  # right hip
    if arm_angle_deg:
        b = math.radians(arm_angle_deg)
        pose[16, 2] = -b
        pose[17, 2] = b
    return pose


def rh_th_to_smpl(pose: torch.Tensor, Rh: torch.Tensor, Th: torch.Tensor, pelvis: torch.Tensor):
    """EasyMocap/HumanNeRF world placement (x_w = R(Rh) x_body + Th, pose[0] usually 0) -> SMPL (pose[0], transl).

    pose: [...,24,3]; Rh, Th: [...,3]; pelvis: [3] rest pelvis joint of the body model.
    The combined global rotation R(Rh) R(pose0) acts about the origin; SMPL rotates about the pelvis, so
    transl = Th + R(Rh) J0 - J0 makes both place every point identically.
    """
    R_h = axis_angle_to_matrix(Rh)
    R0 = R_h @ axis_angle_to_matrix(pose[..., 0, :])
    out = pose.clone()
    out[..., 0, :] = matrix_to_axis_angle(R0)
    transl = Th + (R_h @ pelvis[..., None]).squeeze(-1) - pelvis
    return out, transl


@functools.cache
def _depth_levels(parents: tuple[int, ...]) -> list[tuple[list[int], list[int]]]:
    """The joints of a kinematic tree grouped by depth (root excluded), each with its parents: [(joints, parents)]."""
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [([j for j in range(len(parents)) if depth[j] == d], [parents[j] for j in range(len(parents)) if depth[j] == d])
            for d in range(1, max(depth) + 1)]


class BodyModel(nn.Module):
    """A skinned body with 24 SMPL-order joints. Subclasses fill the buffers in __init__ via `_set_buffers`.

    Buffers: rest_vertices [V,3], faces [F,3] (long), skin_weights [V,24] (rows sum to 1),
    rest_joints [24,3]; attribute parents (tuple of 24 ints, -1 for the root).
    """

    parents: tuple[int, ...] = SMPL_PARENTS
    name: str = "body"

    def _set_buffers(self, rest_vertices, faces, skin_weights, rest_joints) -> None:
        self._canonical_inverse: dict[tuple, torch.Tensor] = {}  # canonical_transforms' constant, per device/dtype
        self.register_buffer("rest_vertices", torch.as_tensor(rest_vertices, dtype=torch.float32), persistent=False)
        self.register_buffer("faces", torch.as_tensor(faces, dtype=torch.long), persistent=False)
        w = torch.as_tensor(skin_weights, dtype=torch.float32)
        self.register_buffer("skin_weights", w / w.sum(-1, keepdim=True).clamp_min(1e-8), persistent=False)
        self.register_buffer("rest_joints", torch.as_tensor(rest_joints, dtype=torch.float32), persistent=False)

    def host_copy(self) -> BodyModel:
        """A copy on the CPU with caches of its own (the datasets pose their samples with it, in the loader's
        workers, while the model's body may live on a GPU)."""
        body = copy.deepcopy(self).to("cpu")
        body._canonical_inverse = {}
        return body

    def forward(self, pose: torch.Tensor, transl: torch.Tensor | None = None) -> torch.Tensor:
        """pose [...,24,3], transl [...,3] -> bone transforms [...,24,4,4] (rest pose -> posed)."""
        check_pose_shape(pose, transl)
        J = self.rest_joints.to(pose.dtype)  # [24,3]
        R = axis_angle_to_matrix(pose)  # [...,24,3,3]
        batch = pose.shape[:-2]
        rel_t = J.clone()
        rel_t[1:] = J[1:] - J[list(self.parents[1:])]
        local = rigid(R, rel_t.expand(batch + (NUM_JOINTS, 3)))  # [...,24,4,4]
        G = local.clone()  # [...,24,4,4] joint frames, one batched product per depth of the tree (8 for SMPL's)
        for joints, parents in _depth_levels(self.parents):
            G[..., joints, :, :] = G[..., parents, :, :] @ local[..., joints, :, :]
        # Remove the rest joint location so G maps rest-pose points, not joint-local points.
        offset = (G[..., :3, :3] @ J[..., None]).squeeze(-1)
        A = G.clone()
        A[..., :3, 3] = G[..., :3, 3] - offset
        if transl is not None:
            A[..., :3, 3] = A[..., :3, 3] + transl[..., None, :]
        return A

    def joints(self, pose: torch.Tensor, transl: torch.Tensor | None = None) -> torch.Tensor:
        """Posed joint locations [...,24,3]."""
        A = self.forward(pose, transl)
        return transform_points(A, self.rest_joints.to(pose.dtype).expand(A.shape[:-2] + (3,)))

    def lbs(self, points: torch.Tensor, weights: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
        """points [...,P,3], weights [P,24] or [...,P,24], transforms A [...,24,4,4] -> posed points [...,P,3]."""
        T = torch.einsum("...pj,...jab->...pab", weights, A)
        return transform_points(T, points)

    def posed_vertices(self, pose: torch.Tensor, transl: torch.Tensor | None = None) -> torch.Tensor:
        """Mesh vertices [...,V,3] under the pose."""
        A = self.forward(pose, transl)
        return self.lbs(self.rest_vertices.to(pose.dtype), self.skin_weights.to(pose.dtype), A)

    def canonical_pose(self) -> torch.Tensor:
        """[24,3] on the body's device and in its dtype (Lightning moves the buffers before on_fit_start)."""
        return canonical_pose(dtype=self.rest_joints.dtype, device=self.rest_joints.device)

    def canonical_vertices(self) -> torch.Tensor:
        return self.posed_vertices(self.canonical_pose())

    def canonical_transforms(self, pose: torch.Tensor, transl: torch.Tensor | None = None) -> torch.Tensor:
        """Bone transforms [...,24,4,4] mapping canonical-pose points to the posed frame."""
        key = (pose.device, pose.dtype)
        if key not in self._canonical_inverse:  # a constant: computed once per device and dtype
            self._canonical_inverse[key] = torch.linalg.inv(self.forward(self.canonical_pose().to(pose)))
        return self.forward(pose, transl) @ self._canonical_inverse[key]
