"""Latentbone pose encoder: per-body-part pose features (+ clothes latent Z_c) -> per-frame pose feature f_p."""

from __future__ import annotations

import torch
from torch import nn

from realityavatar.body.base import check_pose_shape
from realityavatar.geometry import axis_angle_to_matrix

# SMPL joint indices of the paper's four parts.
LEFT_ARM = (13, 16, 18, 20, 22)
RIGHT_ARM = (14, 17, 19, 21, 23)
LEGS = (1, 2, 4, 5, 7, 8, 10, 11)
TORSO = (3, 6, 9, 12, 15)
PART_NAMES = ("left_arm", "right_arm", "legs", "torso")
# Feature sizes: 6 per joint (6D rotation); legs + hip-to-hip rotation; torso + root orientation (6) + translation (3).
PART_DIMS = {"left_arm": 6 * 5, "right_arm": 6 * 5, "legs": 6 * 8 + 6, "torso": 6 * 5 + 6 + 3}


def _rot6d(R: torch.Tensor) -> torch.Tensor:
    """R [...,3,3] -> first two columns minus the identity's, [...,6] (zero for the identity)."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)[:, :2]
    return (R[..., :, :2] - eye).flatten(-2)


def pose_features(poses: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """poses [B,T,24,3] axis-angle (last frame = current), transl [B,T,3] -> [B,T,sum(PART_DIMS)]: the four parts'
    features side by side in PART_NAMES order (`split_parts` cuts them apart).

    The global orientation and translation of every window frame are expressed in the current frame's root
    frame (R_root(t)^T R_root(t_k), R_root(t)^T (transl_k - transl_t)): invariant to absolute heading and
    position, but carrying spin and velocity history (a spin that stops abruptly changes only these).
    No parameters and no gradient: the dataset computes it for every sample (model/avatar.py pose_inputs).
    """
    check_pose_shape(poses, transl, "pose_features")
    if poses.ndim != 4 or transl.shape != poses.shape[:2] + (3,):
        raise ValueError(
            f"pose_features: expected poses [B,T,24,3] and transl [B,T,3], got {tuple(poses.shape)}, {tuple(transl.shape)}"
        )
    R = axis_angle_to_matrix(poses)  # [B,T,24,3,3]
    six = _rot6d(R)  # [B,T,24,6]
    R_root_t = R[:, -1:, 0]  # [B,1,3,3]
    rel_orient = _rot6d(R_root_t.transpose(-1, -2) @ R[:, :, 0])  # [B,T,6]
    rel_transl = (R_root_t.transpose(-1, -2) @ (transl - transl[:, -1:])[..., None]).squeeze(-1)  # [B,T,3]
    hips = _rot6d(R[:, :, 1].transpose(-1, -2) @ R[:, :, 2])  # [B,T,6] right hip in the left hip's frame
    B, T = poses.shape[:2]
    return torch.cat([six[:, :, list(LEFT_ARM)].reshape(B, T, -1), six[:, :, list(RIGHT_ARM)].reshape(B, T, -1),
                      six[:, :, list(LEGS)].reshape(B, T, -1), hips,
                      six[:, :, list(TORSO)].reshape(B, T, -1), rel_orient, rel_transl], -1)


def split_parts(features: torch.Tensor) -> dict[str, torch.Tensor]:
    """[...,sum(PART_DIMS)] -> {part: [...,PART_DIMS[part]]} (views)."""
    return dict(zip(PART_NAMES, features.split([PART_DIMS[p] for p in PART_NAMES], -1)))


def _mlp(in_dim: int, hidden_dim: int, out_dim: int, num_layers: int) -> nn.Sequential:
    """num_layers Linear layers (num_layers-1 hidden, SiLU) ending in a plain Linear."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(num_layers - 1):
        layers += [nn.Linear(d, hidden_dim), nn.SiLU()]
        d = hidden_dim
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class LatentBoneEncoder(nn.Module):
    """The paper's latentbone encoder F_le({p_lm, p_rm, p_lg, p_to}; Z_c) applied to every frame of the window.

    part_split=True: each part's features ⊕ Z_c go through their own single Linear+SiLU (part_dim outputs);
    the four outputs are concatenated into a shallow MLP. part_split=False: all features ⊕ Z_c go through one
    Linear+SiLU of width 4*part_dim into the same MLP. clothes_latent_dim=0 removes Z_c.
    Note: with one avatar per model Z_c is a learned constant, i.e. it acts as extra bias in the input layers.
    """

    def __init__(
        self,
        part_split: bool = True,
        clothes_latent_dim: int = 16,
        part_dim: int = 32,
        hidden_dim: int = 128,
        out_dim: int = 128,
        num_layers: int = 2,
        latent_init_std: float = 0.1,
    ) -> None:
        super().__init__()
        dims = PART_DIMS
        if num_layers < 1:
            raise ValueError(f"encoder.num_layers: expected >= 1, got {num_layers}")
        self.part_split = part_split
        self.clothes_latent_dim = clothes_latent_dim
        self.out_dim = out_dim
        if clothes_latent_dim > 0:
            self.z_c = nn.Parameter(torch.randn(clothes_latent_dim) * latent_init_std)
        else:
            self.register_parameter("z_c", None)
        if part_split:
            self.part_layers = nn.ModuleDict(
                {p: nn.Sequential(nn.Linear(dims[p] + clothes_latent_dim, part_dim), nn.SiLU())
                 for p in PART_NAMES}
            )
        else:
            total = sum(dims.values())
            self.input_layer = nn.Sequential(nn.Linear(total + clothes_latent_dim, 4 * part_dim), nn.SiLU())
        self.mlp = _mlp(4 * part_dim, hidden_dim, out_dim, num_layers)

    def _with_latent(self, x: torch.Tensor) -> torch.Tensor:
        if self.z_c is None:
            return x
        return torch.cat([x, self.z_c.expand(x.shape[:-1] + (-1,))], -1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features [B,T,sum(PART_DIMS)] (`pose_features`) -> f_p [B,T,out_dim]."""
        if self.part_split:
            parts = split_parts(features)
            h = torch.cat([self.part_layers[p](self._with_latent(parts[p])) for p in PART_NAMES], -1)
        else:
            h = self.input_layer(self._with_latent(features))
        return self.mlp(h)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"encoder": list(self.parameters())}
