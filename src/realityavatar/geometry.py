"""Rotation and rigid-transform helpers shared by the body model, the avatar model and the renderer.

Quaternions are (w, x, y, z), like gsplat. Axis-angle vectors follow SMPL (angle = norm, axis = direction).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from realityavatar.runtime import Table, constant


class _Unit(torch.autograd.Function):
    """x / max(|x|, eps) along the last axis, with its backward written out: (g - y (g.y)) / |x|, five tensor
    operations where autograd's chain through F.normalize (norm, clamp, division) takes about ten."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, eps: float) -> torch.Tensor:
        n = torch.linalg.vector_norm(x, dim=-1, keepdim=True).clamp_min(eps)
        y = x / n
        ctx.save_for_backward(y, n)
        return y

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        y, n = ctx.saved_tensors
        return (g - y * (g * y).sum(-1, keepdim=True)) / n, None


def unit(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """F.normalize(x, dim=-1) (the same values) with a shorter backward: for the per-Gaussian directions and
    quaternions of the training step."""
    return _Unit.apply(x, eps)


def skew(v: torch.Tensor) -> torch.Tensor:
    """v [...,3] -> the cross-product matrix [v]x [...,3,3] (one matmul with a constant map)."""
    return (v @ constant(_SKEW, v)).unflatten(-1, (3, 3))


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """aa: [...,3] -> [...,3,3] (Rodrigues, stable and differentiable near zero)."""
    theta2 = (aa * aa).sum(-1, keepdim=True)  # [...,1]
    theta = torch.sqrt(theta2.clamp_min(1e-24))
    small = theta2 < 1e-8
    # Taylor series near zero keeps gradients finite.
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    k = skew(aa)  # [...,3,3] cross-product matrix [aa]x
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


# Constant maps that turn the component formulas below into one or two tensor operations each: every operation is a
# kernel launch on a GPU (and a node of the backward), so a formula written per component costs tens of launches.
_SKEW = torch.zeros(3, 9)  # aa [3] -> [aa]x flattened: [[0,-z,y],[z,0,-x],[-y,x,0]]
for _i, _r, _c, _s in ((0, 2, 1, 1), (0, 1, 2, -1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 1, 0, 1), (2, 0, 1, -1)):
    _SKEW[_i, 3 * _r + _c] = _s
_HAMILTON = torch.zeros(4, 4, 4)  # (a*b)_k = sum_ij a_i b_j H[i,j,k], wxyz
for _i, _j, _k, _s in ((0, 0, 0, 1), (1, 1, 0, -1), (2, 2, 0, -1), (3, 3, 0, -1),
                       (0, 1, 1, 1), (1, 0, 1, 1), (2, 3, 1, 1), (3, 2, 1, -1),
                       (0, 2, 2, 1), (1, 3, 2, -1), (2, 0, 2, 1), (3, 1, 2, 1),
                       (0, 3, 3, 1), (1, 2, 3, 1), (2, 1, 3, -1), (3, 0, 3, 1)):
    _HAMILTON[_i, _j, _k] = _s
_HAMILTON_FLAT = _HAMILTON.flatten(1)  # [4,16]
# matrix_to_quat's candidates: row i of [4,4] is 4 q_i q (wxyz), linear in R's entries m_rc (at 3r+c) plus a constant.
_CANDIDATES_0 = torch.zeros(16)
_CANDIDATES = torch.zeros(9, 16)
_DIAG = ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))  # 4 q_i^2 = 1 + s0 m00 + s1 m11 + s2 m22
_OFF = {(0, 1): ((2, 1, 1), (1, 2, -1)), (0, 2): ((0, 2, 1), (2, 0, -1)), (0, 3): ((1, 0, 1), (0, 1, -1)),
        (1, 2): ((1, 0, 1), (0, 1, 1)), (1, 3): ((0, 2, 1), (2, 0, 1)), (2, 3): ((2, 1, 1), (1, 2, 1))}
for _i, _signs in enumerate(_DIAG):
    _CANDIDATES_0[5 * _i] = 1.0
    for _d, _s in enumerate(_signs):
        _CANDIDATES[4 * _d, 5 * _i] = _s
for (_i, _j), _terms in _OFF.items():
    for _r, _c, _s in _terms:
        _CANDIDATES[3 * _r + _c, 4 * _i + _j] = _CANDIDATES[3 * _r + _c, 4 * _j + _i] = _s
_QUAT_TO_MATRIX = torch.zeros(16, 9)  # q q^T flattened (q_i q_j at 4i+j) -> R - I flattened, for unit wxyz q
for _row, _terms in enumerate((
        ((2, 2, -2), (3, 3, -2)), ((1, 2, 2), (0, 3, -2)), ((1, 3, 2), (0, 2, 2)),
        ((1, 2, 2), (0, 3, 2)), ((1, 1, -2), (3, 3, -2)), ((2, 3, 2), (0, 1, -2)),
        ((1, 3, 2), (0, 2, -2)), ((2, 3, 2), (0, 1, 2)), ((1, 1, -2), (2, 2, -2)))):
    for _i, _j, _s in _terms:
        _QUAT_TO_MATRIX[4 * _i + _j, _row] = _s
_SKEW, _HAMILTON_FLAT, _CANDIDATES_0, _CANDIDATES, _QUAT_TO_MATRIX = (
    Table(t) for t in (_SKEW, _HAMILTON_FLAT, _CANDIDATES_0, _CANDIDATES, _QUAT_TO_MATRIX))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """R: [...,3,3] -> unit quaternion [...,4] (wxyz, w >= 0)."""
    # pytorch3d's four candidates (row i = 4 q_i q, computed from R as one linear map: _CANDIDATES), the
    # best-conditioned one (largest q_i^2, the diagonal) kept and normalised: that removes the scale 4 q_i, so the
    # candidates need no division by it (pytorch3d's; norm >= 2 for the kept row of a rotation).
    flat = R.reshape(-1, 9)
    cands = torch.addmm(constant(_CANDIDATES_0, R), flat, constant(_CANDIDATES, R)).reshape(R.shape[:-2] + (4, 4))  # [...,4,4]
    # [...] the largest 4 q_i^2 (argmax over the strided diagonal view takes 7x as long as over a copy of it)
    idx = torch.diagonal(cands, dim1=-2, dim2=-1).contiguous().argmax(-1)
    q = unit(torch.gather(cands, -2, idx[..., None, None].expand(idx.shape + (1, 4))).squeeze(-2))
    # w >= 0; the signs as device constants, not new tensors per call (a where(cond, -q, q) would add a backward)
    return q * torch.where(q[..., :1] < 0, constant((-1.0,), q), constant((1.0,), q))


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """q: [...,4] wxyz (normalised here) -> [...,3,3]."""
    q = unit(q)
    outer = (q[..., :, None] * q[..., None, :]).flatten(-2)  # [...,16]
    eye = torch.eye(3, dtype=q.dtype, device=q.device).flatten()
    return torch.addmm(eye, outer.reshape(-1, 16), constant(_QUAT_TO_MATRIX, q)).reshape(q.shape[:-1] + (3, 3))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a*b of wxyz quaternions [...,4] (rotation b first, then a)."""
    left = (a @ constant(_HAMILTON_FLAT, a)).unflatten(-1, (4, 4))  # [...,4,4]: (a*b)_k = sum_j left[j,k] b_j
    return (left * b[..., :, None]).sum(-2)


def quat_slerp(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of unit wxyz quaternions a, b [...,4] at w [...] (0: a, 1: b), along the shorter arc."""
    dot = (a * b).sum(-1, keepdim=True)
    b = torch.where(dot < 0, -b, b)
    theta = torch.acos(dot.abs().clamp(max=1.0))  # [...,1]
    w = w[..., None]
    sin = torch.sin(theta)
    near = sin < 1e-6  # (almost) the same rotation: linear weights
    wa = torch.where(near, 1 - w, torch.sin((1 - w) * theta) / sin.clamp_min(1e-6))
    wb = torch.where(near, w, torch.sin(w * theta) / sin.clamp_min(1e-6))
    return F.normalize(wa * a + wb * b, dim=-1)


def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Unit wxyz quaternion [...,4] -> axis-angle [...,3] (angle in [0, pi])."""
    q = torch.where(q[..., :1] < 0, -q, q)
    xyz = q[..., 1:]
    s = xyz.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    scale = torch.where(s > 1e-8, angle / s.clamp_min(1e-12), 2.0 / q[..., :1].clamp_min(1e-12))
    return xyz * scale


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """R: [...,3,3] -> axis-angle [...,3] (angle in [0, pi])."""
    return quat_to_axis_angle(matrix_to_quat(R))


def rigid(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """R: [...,3,3], t: [...,3] -> homogeneous [...,4,4]."""
    T = torch.zeros(R.shape[:-2] + (4, 4), dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def transform_points(T: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """T: [...,4,4], x: [...,3] -> [...,3]."""
    return (T[..., :3, :3] @ x[..., None]).squeeze(-1) + T[..., :3, 3]


def camera_centres(viewmats: torch.Tensor) -> torch.Tensor:
    """World-to-camera [...,4,4] -> camera centres in world space [...,3] (C = -Rᵀ t)."""
    R, t = viewmats[..., :3, :3], viewmats[..., :3, 3:]
    return -(R.transpose(-1, -2) @ t).squeeze(-1)


def sample_barycentric(
    vertices: torch.Tensor, faces: torch.Tensor, n: int, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Area-weighted uniform sample points on a triangle mesh, as faces and barycentrics.

    vertices [V,3], faces [F,3] (CPU; the areas are computed in the vertices' dtype) -> face index [n], barycentrics
    [n,3] (float32) and every face's area [F]. Draws from `generator`: the faces, then two uniforms per point.
    """
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"sample_surface: faces must be [F,3], got {tuple(faces.shape)}")
    tri = vertices[faces]  # [F,3,3]
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1) / 2
    if not torch.isfinite(area).all() or area.sum() <= 0:
        raise ValueError("sample_surface: mesh has no positive area")
    face_idx = torch.multinomial(area, n, replacement=True, generator=generator)  # [n]
    r = torch.rand(n, 2, generator=generator)
    # sqrt trick: uniform over the triangle.
    s = r[:, 0].sqrt()
    return face_idx, torch.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], -1), area


def kd_tree(points):
    """scipy's cKDTree over points [P,D] (numpy) with sliding-midpoint splits and node boxes not shrunk to the data
    (balanced_tree, compact_nodes off): the same nearest points as scipy's default tree up to ties (of equally near
    points, e.g. a Gaussian and its clone, either tree may return another), built faster, and queried far
    faster away from the points (the default's boxes hug a body surface's samples, so a voxel 30 cm from the body
    searches most of the tree): 2.2 s against 15.5 s for the mannequin's 171k grid voxels over 200k surface samples,
    2.7 against 4.3 ms for a silhouette's 10k projected centres and 1,024 pixels (one CPU thread)."""
    from scipy.spatial import cKDTree

    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def sample_surface(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    weights: torch.Tensor | None,
    n: int,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Area-weighted uniform samples on a triangle mesh.

    vertices [V,3], faces [F,3], weights [V,K] or None -> points [n,3], barycentric-interpolated weights [n,K] (or None).
    Deterministic for a given generator (sampling runs on the CPU generator; results take the mesh's device and dtype).
    """
    dev = vertices.device
    v = vertices.detach().cpu().float()
    f = faces.cpu().long()
    face_idx, bary, _ = sample_barycentric(v, f, n, generator)
    fi = f[face_idx]  # [n,3]
    points = (bary[:, :, None] * v[fi]).sum(1)
    w = None
    if weights is not None:
        w = (bary[:, :, None] * weights.detach().cpu().float()[fi]).sum(1)  # [n,K]
        w = w.to(device=dev, dtype=weights.dtype)
    return points.to(device=dev, dtype=vertices.dtype), w
