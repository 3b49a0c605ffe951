"""Visual hull of one frame carved from the training masks (the garment sheet's rest layout, sheet.profile=rest)."""

from __future__ import annotations

import numpy as np
import torch


class HullViews:
    """The training cameras of one frame: masks [C] bool [H,W], K [C,3,3], viewmats [C,4,4] (world-to-camera),
    and that frame's body pose [24,3] / translation [3] (SMPL convention, as the DataModule's PoseTable holds).
    A plain class, not a dataclass: hydra's instantiate would turn a dataclass argument into a config node."""

    def __init__(self, masks, Ks, viewmats, pose, transl, frame) -> None:
        self.masks, self.Ks, self.viewmats = masks, Ks, viewmats
        self.pose, self.transl, self.frame = pose, transl, frame


def hull_views(dm, frame: int | None = None) -> HullViews:
    """The training-split masks of `frame` (default: the first training frame, the rest pose of a sequence)."""
    ds = dm.datasets.get("train")
    if ds is None:
        raise ValueError("sheet.profile=rest: the DataModule has no training split to carve a visual hull from")
    frames = sorted({r.frame for r in ds.records})
    frame = frames[0] if frame is None else int(frame)
    idx = [i for i, r in enumerate(ds.records) if r.frame == frame]
    if len(idx) < 2:
        raise ValueError(f"sheet.hull_frame={frame}: need >= 2 training cameras at that frame, found {len(idx)}")
    masks, Ks, E = [], [], []
    for i in idx:
        _, mask, K = ds._decoded(i)
        masks.append(np.asarray(mask, bool))
        Ks.append(np.asarray(K, np.float64))
        E.append(np.asarray(ds.records[i].viewmat, np.float64))
    poses, transl = dm.scene.poses.window(frame, 1, 0)
    return HullViews(masks, np.stack(Ks), np.stack(E), poses[-1], transl[-1], frame)


def carve(views: HullViews, lo: np.ndarray, hi: np.ndarray, voxel: float) -> np.ndarray:
    """Voxel centres [P,3] on the surface of the visual hull inside the box [lo, hi].

    A voxel is occupied when its centre projects inside the mask of every camera (outside an image counts as
    outside); a surface voxel is occupied with at least one free 6-neighbour.
    """
    axes = [np.arange(lo[a] + voxel / 2, hi[a], voxel) for a in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1)  # [I,J,K,3]
    pts = X.reshape(-1, 3)
    occ = np.ones(len(pts), bool)
    from realityavatar.losses import project_points

    for mask, K, E in zip(views.masks, views.Ks, views.viewmats):
        uv, z = project_points(torch.from_numpy(pts), torch.from_numpy(E), torch.from_numpy(K))
        u, v, z = uv[:, 0].round().long().numpy(), uv[:, 1].round().long().numpy(), z.numpy()
        H, W = mask.shape
        ok = (z > 1e-3) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        inside = np.zeros(len(pts), bool)
        inside[ok] = mask[v[ok], u[ok]]
        occ &= inside
    grid = occ.reshape(X.shape[:3])
    pad = np.pad(grid, 1, constant_values=False)
    interior = grid.copy()
    for a in range(3):
        for s in (-1, 1):
            interior &= np.roll(pad, s, axis=a)[1:-1, 1:-1, 1:-1]
    return X[grid & ~interior]


def body_and_hull(body, views: HullViews, voxel: float, margin: float = 0.45,
                  what: str = "sheet.profile=rest") -> tuple[np.ndarray, np.ndarray]:
    """The views' frame: its posed body vertices [V,3] and the surface voxels of its visual hull inside the body's
    box widened by `margin` (0.05 m up and down) [P,3], both float64; an empty hull raises, naming `what`."""
    pose, transl = views.pose.float(), views.transl.float()
    verts = body.posed_vertices(pose, transl).cpu().numpy().astype(np.float64)  # [V,3]
    lo = verts.min(0) - np.array([margin, 0.05, margin])
    hi = verts.max(0) + np.array([margin, 0.05, margin])
    surf = carve(views, lo, hi, voxel)
    if len(surf) == 0:
        raise ValueError(f"{what}: the visual hull of frame {views.frame} is empty; check the masks "
                         "and cameras of the training split")
    return verts, surf


def cylindrical(pts, origin, axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points [n,3] about the line through `origin` along the unit `axis` -> (height h [n], radius r [n], azimuth
    [n]), the azimuth from e1 = axis x z (x where the axis is near z) towards e2 = axis x e1."""
    pts, origin, axis = (np.asarray(x, np.float64) for x in (pts, origin, axis))
    e1 = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rel = pts - origin
    h = rel @ axis
    return h, np.linalg.norm(rel - h[:, None] * axis, axis=1), np.arctan2(rel @ e2, rel @ e1)


def sector_radius(cyl: tuple, height: float, band: float, quantile: float, reach: float = 0.8) -> float:
    """Points in cylindrical coordinates cyl = (height h [n], radius r [n], azimuth [n]) -> the radius at `height`:
    the `quantile` over 16 azimuth sectors of each sector's farthest point within `band` of it (and within `reach`
    of the axis); 0 where no point is. A hull carved from a few cameras bulges between them: a lower quantile reads
    the garment's radius rather than the bulges'."""
    h, r, az = (np.asarray(x) for x in cyl)
    bins = np.linspace(-np.pi, np.pi, 17)
    sel = (np.abs(h - height) < band) & (r < reach)
    sector = np.digitize(az[sel], bins[1:-1])
    far = [float(r[sel][sector == k].max()) for k in range(16) if (sector == k).any()]
    return float(np.quantile(far, quantile)) if far else 0.0


def to_canonical(body, views: HullViews, x: torch.Tensor, nearest) -> torch.Tensor:
    """Points x [n,3] posed in the views' frame -> canonical space [n,3], by inverse LBS with the weights of each
    point's nearest body vertex (indices `nearest` [n])."""
    A = body.canonical_transforms(views.pose.float(), views.transl.float())  # [24,4,4] canonical -> posed
    w = body.skin_weights.cpu()[torch.as_tensor(nearest)]  # [n,24]
    T = torch.einsum("nj,jab->nab", w, A.cpu())  # [n,4,4]
    xh = torch.cat([x, torch.ones(len(x), 1)], -1)[..., None]
    return (torch.linalg.inv(T) @ xh)[:, :3, 0]
