"""Latentbone pose encoder: per-body-part pose features (+ clothes latent Z_c) -> per-frame pose feature f_p."""

from __future__ import annotations

import torch
import torch.nn.functional as F
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
    features side by side in PART_NAMES order, PART_DIMS wide each.

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


def _mlp(in_dim: int, hidden_dim: int, out_dim: int, num_layers: int) -> nn.Sequential:
    """num_layers Linear layers (num_layers-1 hidden, SiLU) ending in a plain Linear."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(num_layers - 1):
        layers += [nn.Linear(d, hidden_dim), nn.SiLU()]
        d = hidden_dim
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def _from_parts(parts: list[tuple[torch.Tensor, torch.Tensor]], latent_dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Four part layers in PART_NAMES order, each (weight [part_dim, PART_DIMS[p] + latent_dim], bias [part_dim]) on
    (its part's features ⊕ Z_c) -> the one input layer's block-diagonal weight [4*part_dim, sum(PART_DIMS) +
    latent_dim] (part i: rows i*part_dim.., its features' columns and Z_c's, the last latent_dim) and bias."""
    part_dim, total = parts[0][0].shape[0], sum(PART_DIMS.values())
    weight = parts[0][0].new_zeros(len(parts) * part_dim, total + latent_dim)
    bias = parts[0][1].new_zeros(len(parts) * part_dim)
    start = 0
    for i, (p, (w, b)) in enumerate(zip(PART_NAMES, parts)):
        rows, n = slice(i * part_dim, (i + 1) * part_dim), PART_DIMS[p]
        weight[rows, start : start + n], weight[rows, total:], bias[rows] = w[:, :n], w[:, n:], b
        start += n
    return weight, bias


class LatentBoneEncoder(nn.Module):
    """The paper's latentbone encoder F_le({p_lm, p_rm, p_lg, p_to}; Z_c) applied to every frame of the window
    (`encoder=latentbone`): each part's features ⊕ Z_c go through their own Linear+SiLU (part_dim outputs), the four
    outputs concatenated into a shallow MLP. The four part layers are one input layer (`input_layer`) whose weight
    is masked block diagonal (`part_mask`: each part's rows see its own features and Z_c), initialised as four
    separate layers would be: one matmul instead of four layers (a step had ~30 operations more with them). Note:
    with one avatar per model Z_c is a learned constant, i.e. extra bias in the input layer.
    The paper's ablations are the subclasses: `WholePoseEncoder` (no part split), `NoClothesLatentEncoder` (no Z_c).
    """

    def __init__(self, clothes_latent_dim: int, part_dim: int, hidden_dim: int, out_dim: int, num_layers: int,
                 latent_init_std: float) -> None:
        super().__init__()
        if num_layers < 1:
            raise ValueError(f"encoder.num_layers: expected >= 1, got {num_layers}")
        self.clothes_latent_dim = clothes_latent_dim
        self.part_dim = part_dim
        self.out_dim = out_dim
        self.z_c = nn.Parameter(torch.randn(clothes_latent_dim) * latent_init_std)
        size = (sum(PART_DIMS.values()) + clothes_latent_dim, 4 * part_dim)
        first, mask = self._input_layer(size)
        self.input_layer = nn.Sequential(first, nn.SiLU())
        self.register_buffer("part_mask", mask, persistent=False)
        self.mlp = _mlp(4 * part_dim, hidden_dim, out_dim, num_layers)

    def _input_layer(self, size: tuple[int, int]) -> tuple[nn.Linear, torch.Tensor]:
        """The input layer (in, out = size) and its weight's mask: block diagonal, drawn part by part."""
        # the blocks are drawn below (the full layer's own initialisation would draw other numbers)
        first = torch.nn.utils.skip_init(nn.Linear, *size)
        dims = [PART_DIMS[p] + self.clothes_latent_dim for p in PART_NAMES]
        # nn.Linear's own initialisation for each part's fan-in, drawn in part order
        layers = [nn.Linear(d, self.part_dim) for d in dims]
        with torch.no_grad():
            weight, bias = _from_parts([(m.weight, m.bias) for m in layers], self.clothes_latent_dim)
            first.weight.copy_(weight)
            first.bias.copy_(bias)
        ones = [(torch.ones(self.part_dim, d), torch.ones(self.part_dim)) for d in dims]
        return first, _from_parts(ones, self.clothes_latent_dim)[0]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Checkpoints written before the part layers became one masked layer: their four layers' blocks.
        old = [f"{prefix}part_layers.{p}.0." for p in PART_NAMES]
        if old[0] + "weight" in state_dict:
            parts = [(state_dict.pop(k + "weight"), state_dict.pop(k + "bias")) for k in old]
            weight, bias = _from_parts(parts, self.clothes_latent_dim)
            state_dict[prefix + "input_layer.0.weight"], state_dict[prefix + "input_layer.0.bias"] = weight, bias
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def parts(self, features: torch.Tensor) -> torch.Tensor:
        """features [B,T,sum(PART_DIMS)] -> the input layer's output [B,T,4*part_dim] (part i's features reach rows
        i*part_dim..(i+1)*part_dim only, where the mask is block diagonal)."""
        x = torch.cat([features, self.z_c.expand(features.shape[:-1] + (-1,))], -1)
        first = self.input_layer[0]
        return self.input_layer[1](F.linear(x, first.weight * self.part_mask, first.bias))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features [B,T,sum(PART_DIMS)] (`pose_features`) -> f_p [B,T,out_dim]."""
        return self.mlp(self.parts(features))

    def num_parameters(self) -> int:
        """Trained entries: every parameter's, less the input layer's entries that the part mask holds at zero."""
        return sum(p.numel() for p in self.parameters()) - int((self.part_mask == 0).sum())

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"encoder": list(self.parameters())}


class WholePoseEncoder(LatentBoneEncoder):
    """Ablation "w/o part segmentation" (`encoder=no_split`): all features ⊕ Z_c through one Linear+SiLU of width
    4*part_dim (nn.Linear's own initialisation, an all-ones mask) into the same MLP."""

    def _input_layer(self, size: tuple[int, int]) -> tuple[nn.Linear, torch.Tensor]:
        return nn.Linear(*size), torch.ones(size[::-1])


class NoClothesLatentEncoder(LatentBoneEncoder):
    """Ablation "w/o latent code Z_c" (`encoder=no_zc`): the part split without the clothes latent (Z_c has no
    entries, so the input is the pose features alone)."""

    def __init__(self, part_dim: int, hidden_dim: int, out_dim: int, num_layers: int) -> None:
        super().__init__(0, part_dim, hidden_dim, out_dim, num_layers, 0.0)
