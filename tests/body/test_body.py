"""Tests of the mannequin body model: package agreement, folded weights, FK conventions, Rh/Th placement."""

import numpy as np
import pytest
import torch

from realityavatar.body import SMPL_PARENTS, MannequinBody, build_body, rh_th_to_smpl
from realityavatar.body.mannequin import fold_joint_index
from realityavatar.geometry import axis_angle_to_matrix


def mannequin_reference_vertices(pose: np.ndarray, transl: np.ndarray | None = None, kind: str = "wooden") -> np.ndarray:
    """mannequin-x's own posed vertices [V,3] for an SMPL-order pose [24,3] (pose[0] about the pelvis, like SMPL):
    the package's reference that our LBS is checked against.

    Joints 22/23 (hands) are not actuated by mannequin-x (SMPL-X has no such body joints), so pose[22:] must be zero.
    """
    from mannequin import Mannequin

    pose = np.asarray(pose, dtype=np.float32)
    if np.abs(pose[22:]).max() > 0:
        raise ValueError("mannequin_reference_vertices: pose[22:24] (hand joints) must be zero for mannequin-x")
    m = Mannequin(kind)
    p = m.rest_pose()
    p["body_pose"] = pose[1:22].copy()
    # pelvis_rotation turns about the pelvis like SMPL's global_orient; global_rotation would turn about the origin.
    p["pelvis_rotation"] = pose[0].copy()
    if transl is not None:
        p["global_translation"] = np.asarray(transl, dtype=np.float32)
    return np.asarray(m.vertices(p))


@pytest.fixture(scope="module")
def body():
    return MannequinBody()


def test_buffers_and_parents(body):
    from mannequin import Mannequin

    m = Mannequin("wooden")
    assert tuple(m.parents[:24]) == SMPL_PARENTS == body.parents
    assert body.rest_vertices.shape == (24256, 3)
    assert body.faces.shape[1] == 3 and int(body.faces.max()) < 24256
    assert body.skin_weights.shape == (24256, 24)
    assert torch.allclose(body.skin_weights.sum(-1), torch.ones(24256), atol=1e-5)
    assert (body.skin_weights >= 0).all()
    assert body.rest_joints.shape == (24, 3)


def test_finger_weights_fold_into_hands(body):
    from mannequin import Mannequin

    m = Mannequin("wooden")
    parents = m.parents
    names = m.joint_names
    for j in range(24, len(parents)):
        expect = names.index("L_Hand") if names[j].startswith("L_") else names.index("R_Hand")
        assert fold_joint_index(parents, j) == expect, names[j]
    # Vertices skinned to fingers in the package now move with the hand joints.
    fingers = (np.asarray(m._skin_joint_indices) >= 24).any(1)
    assert fingers.sum() > 100
    assert (body.skin_weights[torch.as_tensor(fingers)][:, 22:24].sum(-1) > 0).all()


def test_rest_pose_matches_package(body):
    v = body.posed_vertices(torch.zeros(24, 3))
    ref = mannequin_reference_vertices(np.zeros((24, 3)))
    assert np.abs(v.numpy() - ref).max() < 1e-5
    assert torch.allclose(body.joints(torch.zeros(24, 3)), body.rest_joints, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_lbs_matches_package_for_random_pose(body, seed):
    # Exact up to float error: fingers keep their relaxed pose, so folding them into the hands changes nothing.
    g = torch.Generator().manual_seed(seed)
    pose = torch.randn(24, 3, generator=g) * 0.35
    pose[22:] = 0  # mannequin-x does not actuate SMPL's hand joints
    transl = torch.tensor([0.3, -0.1, 0.7])
    v = body.posed_vertices(pose, transl).numpy()
    ref = mannequin_reference_vertices(pose.numpy(), transl.numpy())
    assert np.abs(v - ref).max() < 2e-3  # metres
    assert np.abs(v - ref).mean() < 1e-4
    # A wrong convention (e.g. global rotation about the origin instead of the pelvis) is far off.
    moved = mannequin_reference_vertices(pose.numpy(), transl.numpy() + 0.01)
    assert np.abs(v - moved).max() > 5e-3


def test_global_orientation_turns_about_pelvis(body):
    pose = torch.zeros(24, 3)
    pose[0, 1] = 1.2
    J = body.joints(pose)
    assert torch.allclose(J[0], body.rest_joints[0], atol=1e-6)


def test_rh_th_placement_roundtrip(body):
    # Scene writer convention: x_world = R(Rh) x_body(poses with poses[0]=0) + Th.
    g = torch.Generator().manual_seed(3)
    pose = torch.randn(24, 3, generator=g) * 0.2
    pose[0] = 0
    Rh = torch.tensor([0.1, 2.5, -0.2])
    Th = torch.tensor([0.4, 0.9, -0.3])
    x_body = body.joints(pose)
    x_world = (axis_angle_to_matrix(Rh) @ x_body[..., None]).squeeze(-1) + Th
    smpl_pose, transl = rh_th_to_smpl(pose, Rh, Th, body.rest_joints[0])
    assert torch.allclose(body.joints(smpl_pose, transl), x_world, atol=1e-5)


def test_build_body_errors():
    with pytest.raises(ValueError, match="unknown body model"):
        build_body("robot")
    with pytest.raises(ValueError, match="wooden"):
        MannequinBody(kind="convex")


def test_forward_batched_shapes(body):
    pose = torch.zeros(2, 3, 24, 3)
    A = body(pose, torch.zeros(2, 3, 3))
    assert A.shape == (2, 3, 24, 4, 4)
    assert body.posed_vertices(pose[:, 0]).shape == (2, 24256, 3)


def test_wrong_pose_shape_gives_clear_error(body):
    """The forward path checks shapes (values are checked where poses enter: tests/data/test_poses.py)."""
    from realityavatar.body.base import check_pose_shape

    with pytest.raises(ValueError, match=r"\[\.\.\.,24,3\]"):
        check_pose_shape(torch.zeros(23, 3), None)
    with pytest.raises(ValueError, match=r"translation of shape \[\.\.\.,3\]"):
        check_pose_shape(torch.zeros(24, 3), torch.zeros(2))
    with pytest.raises(ValueError, match=r"\[\.\.\.,24,3\]"):
        body(torch.zeros(23, 3))

def test_host_copy_poses_like_the_body_with_caches_of_its_own(body):
    """The datasets' copy of the body (BodyModel.host_copy): same transforms, on the CPU, its own canonical cache."""
    pose = torch.randn(2, 24, 3, generator=torch.Generator().manual_seed(3)) * 0.3
    A = body.canonical_transforms(pose)  # fills the body's cache
    copy = body.host_copy()
    assert copy is not body and copy._canonical_inverse == {} and body._canonical_inverse
    assert all(b.device.type == "cpu" for b in copy.buffers())
    torch.testing.assert_close(copy.canonical_transforms(pose), A)
    copy.rest_joints.add_(1.0)  # its buffers are its own
    assert not torch.equal(copy.rest_joints, body.rest_joints)
