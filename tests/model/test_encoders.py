"""Pose encoder: heading-invariant pose features, the latent-bone encoder's ablation options."""

from __future__ import annotations

import pytest
import torch

from realityavatar.geometry import (
    axis_angle_to_matrix,
)
from realityavatar.model.encoders import PART_DIMS, LatentBoneEncoder, pose_features, split_parts
from tests.helpers import assert_all_grads, random_poses


def test_pose_features_invariant_to_heading_but_not_to_spin():
    poses, transl = random_poses()
    feats = split_parts(pose_features(poses, transl))
    assert {k: v.shape[-1] for k, v in feats.items()} == PART_DIMS
    # rotate and shift the whole window about the world origin: root orientation and translation change, features not
    R0 = axis_angle_to_matrix(torch.tensor([0.0, 1.3, 0.0]))
    from realityavatar.geometry import matrix_to_axis_angle

    p2 = poses.clone()
    p2[:, :, 0] = matrix_to_axis_angle(R0 @ axis_angle_to_matrix(poses[:, :, 0]))
    t2 = (R0 @ transl[..., None]).squeeze(-1) + torch.tensor([1.0, 0.0, -2.0])
    feats2 = split_parts(pose_features(p2, t2))
    for k in feats:
        assert torch.allclose(feats[k], feats2[k], atol=1e-5), k
    # a different spin history (only past root orientations differ) changes the torso features
    p3 = poses.clone()
    p3[:, 0, 0] += torch.tensor([0.0, 0.8, 0.0])
    feats3 = split_parts(pose_features(p3, transl))
    assert not torch.allclose(feats3["torso"], feats["torso"])
    assert torch.allclose(feats3["left_arm"], feats["left_arm"])
    # the current frame's own root terms are zero (relative to itself)
    assert torch.allclose(feats["torso"][:, -1, 30:], torch.zeros(2, 9), atol=1e-6)


def test_pose_features_rejects_a_wrong_shape():
    """Shapes are checked in the forward path; values (NaN) where poses enter, on the host (test_body, test_module)."""
    poses, transl = random_poses()
    with pytest.raises(ValueError, match=r"pose_features: expected axis-angle pose of shape \[\.\.\.,24,3\]"):
        pose_features(poses[..., :23, :], transl)


@pytest.mark.parametrize("split,zc", [(True, 16), (False, 16), (True, 0)])
def test_latentbone_encoder_options(split, zc):
    enc = LatentBoneEncoder(part_split=split, clothes_latent_dim=zc, out_dim=64)
    poses, transl = random_poses()
    f = enc(pose_features(poses, transl))
    assert f.shape == (2, 5, 64) and enc.out_dim == 64
    f.square().sum().backward()
    assert_all_grads(enc)
    names = dict(enc.named_parameters())
    if zc == 0:
        assert enc.z_c is None and not any("z_c" in n for n in names)
    else:
        assert enc.z_c.shape == (zc,)
    if split:
        assert set(enc.part_layers) == {"left_arm", "right_arm", "legs", "torso"}
        assert enc.part_layers["legs"][0].in_features == PART_DIMS["legs"] + zc
    else:
        assert not hasattr(enc, "part_layers")
        assert enc.input_layer[0].in_features == sum(PART_DIMS.values()) + zc
