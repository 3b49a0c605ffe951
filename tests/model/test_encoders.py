"""Pose encoder: heading-invariant pose features, the latent-bone encoder's ablation options."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import (
    axis_angle_to_matrix,
)
from realityavatar.model.encoders import (
    PART_DIMS,
    PART_NAMES,
    LatentBoneEncoder,
    NoClothesLatentEncoder,
    WholePoseEncoder,
    pose_features,
)
from tests.helpers import assert_all_grads, random_poses
from tests.model.configured import component


def split_parts(features: torch.Tensor) -> dict[str, torch.Tensor]:
    """[...,sum(PART_DIMS)] -> {part: [...,PART_DIMS[part]]}: pose_features cut into its parts."""
    return dict(zip(PART_NAMES, features.split([PART_DIMS[p] for p in PART_NAMES], -1)))


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


@pytest.mark.parametrize("option,cls,zc", [("latentbone", LatentBoneEncoder, 16), ("no_split", WholePoseEncoder, 16),
                                           ("no_zc", NoClothesLatentEncoder, 0)])
def test_encoder_variants(option, cls, zc):
    """Each of the paper's encoder ablations is its own class, picked by conf/encoder/<option>.yaml; no_split's input
    layer sees every feature, the others' part i only its own features (and Z_c)."""
    enc = component("encoder", option, "encoder.out_dim=64")
    assert type(enc) is cls
    poses, transl = random_poses()
    features = pose_features(poses, transl)
    f = enc(features)
    assert f.shape == (2, 5, 64) and enc.out_dim == 64
    f.square().sum().backward()
    assert_all_grads(enc) if zc else assert_all_grads(nn.ModuleList([enc.input_layer, enc.mlp]))
    assert enc.z_c.shape == (zc,)  # no Z_c: no entries, the same path
    with torch.no_grad():  # a training step: the split must hold after updates, not only as initialised
        for q in enc.parameters():
            q -= 0.1 * q.grad
    # the legs' features reach the torso's rows of the input layer only without the split
    legs = sum(PART_DIMS[p] for p in PART_NAMES[:2])
    torso_rows = slice(3 * enc.part_dim, 4 * enc.part_dim)
    moved = features.clone()
    moved[..., legs] += 1.0
    changed = (enc.parts(moved) - enc.parts(features))[..., torso_rows].abs().max()
    assert (changed > 0) == (cls is WholePoseEncoder), float(changed)


def test_part_split_is_the_papers_four_layers_and_loads_their_checkpoints():
    """The masked input layer computes what four Linear+SiLU layers on (part features ⊕ Z_c) computed, and a state dict
    in that layout (`part_layers.<part>.0.*`, runs before the layers became one) loads into it."""
    torch.manual_seed(0)
    enc = component("encoder", "latentbone")
    features = pose_features(*random_poses())
    first, z, total = enc.input_layer[0], enc.z_c, sum(PART_DIMS.values())
    old, start, outs = {}, 0, []
    for i, (p, x) in enumerate(split_parts(features).items()):
        rows = slice(i * enc.part_dim, (i + 1) * enc.part_dim)
        w = torch.cat([first.weight[rows, start : start + PART_DIMS[p]], first.weight[rows, total:]], 1)
        old[f"part_layers.{p}.0.weight"], old[f"part_layers.{p}.0.bias"] = w.detach(), first.bias[rows].detach()
        outs.append(F.silu(F.linear(torch.cat([x, z.expand(x.shape[:-1] + (-1,))], -1), w, first.bias[rows])))
        start += PART_DIMS[p]
    assert torch.allclose(enc.parts(features), torch.cat(outs, -1), atol=1e-6)
    four_layers = sum(v.numel() for v in old.values())
    assert enc.num_parameters() == sum(q.numel() for q in enc.parameters()) - first.weight.numel() - first.bias.numel() + four_layers
    state = {k: v for k, v in enc.state_dict().items() if not k.startswith("input_layer")} | old
    loaded = component("encoder", "latentbone")
    loaded.load_state_dict(state)
    assert torch.allclose(loaded(features), enc(features), atol=1e-6)
