"""Ground-truth images by ray casting posed body + garment meshes (trimesh + Embree): RGB, masks, Lambert shading.

Independent of the project's splat renderer on purpose. Textures are procedural and cheap: the body gets a solid
texture evaluated at the rest-pose position of each hit, the garment a pattern on its UVs.
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

LIGHT_DIR = np.array([0.35, 0.82, 0.45]) / np.linalg.norm([0.35, 0.82, 0.45])  # towards the light; world y up
AMBIENT = 0.4
DIFFUSE = 0.6
MIN_ALBEDO = 0.1  # keeps every lit pixel > 0 so the black background alone is zero (masks == silhouettes)


def camera_rays(K: np.ndarray, viewmat: np.ndarray, width: int, height: int):
    """Origins [H*W,3], unit directions [H*W,3] (world) through pixel centres, row-major."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return pixel_rays(K, viewmat, u.ravel(), v.ravel())


def pixel_rays(K: np.ndarray, viewmat: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Origins [P,3], unit directions [P,3] (world) through image points (u, v) [P] in pixels (OpenCV: the first
    pixel's centre is (0.5, 0.5))."""
    pix = np.stack([u, v, np.ones(u.size)], -1)  # [P,3]
    d_cam = pix @ np.linalg.inv(K).T
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    d = d_cam @ R  # R^T d_cam, row-wise
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = -R.T @ t
    return np.broadcast_to(origin, d.shape).copy(), d


def _hash01(ix: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random numbers in [0,1) from integer cell coordinates [...,k]."""
    h = np.uint64(seed * 2654435761 + 97)
    for c in np.moveaxis(ix.astype(np.int64), -1, 0):
        h = (h ^ c.astype(np.uint64)) * np.uint64(0x100000001B3)
        h ^= h >> np.uint64(29)
    return (h % np.uint64(1 << 24)).astype(np.float64) / float(1 << 24)


class BodyTexture:
    """Albedo for the body from its rest-pose position: part colours (shirt, trousers, skin) with stripes/checks."""

    def __init__(self, rest_vertices: np.ndarray, skin_weights: np.ndarray, seed: int = 0):
        rng = np.random.default_rng(seed + 1)
        part = np.argmax(skin_weights, 1)  # [V] dominant joint
        # Groups: 0 legs (trousers), 1 torso/upper arms (shirt), 2 head/forearms/hands (skin), 3 feet (shoes).
        group_of_joint = np.array([1, 0, 0, 1, 0, 0, 1, 3, 3, 1, 3, 3, 2, 1, 1, 2, 1, 1, 2, 2, 2, 2, 2, 2])
        self.group = group_of_joint[part]  # [V]
        self.rest = rest_vertices.astype(np.float64)
        base = np.array([[0.18, 0.22, 0.45], [0.85, 0.35, 0.2], [0.88, 0.68, 0.52], [0.25, 0.2, 0.18]])
        self.colors = np.clip(base + rng.uniform(-0.08, 0.08, base.shape), MIN_ALBEDO, 1.0)
        self.seed = seed

    def __call__(self, face_vertices: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """face_vertices [P,3] vertex ids of the hit faces, bary [P,3] -> albedo [P,3]."""
        x = np.einsum("pk,pkc->pc", bary, self.rest[face_vertices])  # rest-pose hit position
        g = self.group[face_vertices[np.arange(len(bary)), np.argmax(bary, 1)]]
        col = self.colors[g].copy()
        # Shirt: 3 cm horizontal stripes; trousers: 5 cm checks; skin: fine noise; shoes: plain.
        stripes = (np.floor(x[:, 1] / 0.03) % 2)[:, None]
        checks = ((np.floor(x[:, 0] / 0.05) + np.floor(x[:, 1] / 0.05) + np.floor(x[:, 2] / 0.05)) % 2)[:, None]
        noise = _hash01(np.floor(x / 0.02), self.seed)[:, None]
        mod = np.where(g[:, None] == 1, 0.65 + 0.35 * stripes,
                       np.where(g[:, None] == 0, 0.6 + 0.4 * checks, np.where(g[:, None] == 2, 0.85 + 0.15 * noise, 1.0)))
        return np.clip(col * mod, MIN_ALBEDO, 1.0)


class GarmentTexture:
    """Albedo for the garment from its UVs: a checkerboard of random colours with thin stripes across it."""

    def __init__(self, uv: np.ndarray, seed: int = 0, cells=(16, 24)):
        self.uv = uv.astype(np.float64)
        self.cells = np.asarray(cells, dtype=np.float64)
        self.seed = seed + 7

    def __call__(self, face_vertices: np.ndarray, bary: np.ndarray) -> np.ndarray:
        uv = np.einsum("pk,pkc->pc", bary, self.uv[face_vertices]) * self.cells
        cell = np.floor(uv)
        hue = _hash01(cell, self.seed)
        checker = (cell.sum(1) % 2)[:, None]
        col = 0.5 + 0.45 * np.cos(2 * np.pi * (hue[:, None] + np.array([0.0, 1 / 3, 2 / 3])))
        col = col * (0.55 + 0.45 * checker)
        frac = uv[:, 1] * 4 - np.floor(uv[:, 1] * 4)
        col = np.where((frac < 0.12)[:, None], np.array([0.95, 0.95, 0.9]), col)  # thin light stripes
        return np.clip(col, MIN_ALBEDO, 1.0)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    vn = np.zeros_like(vertices)
    for k in range(3):  # area-weighted
        np.add.at(vn, faces[:, k], fn)
    return vn / np.linalg.norm(vn, axis=1, keepdims=True).clip(1e-12)


def all_camera_rays(Ks: np.ndarray, viewmats: np.ndarray, width: int, height: int):
    """Origins, directions [C*H*W,3] for all cameras (fixed cameras: compute once per scene)."""
    origins, dirs = zip(*(camera_rays(Ks[c], viewmats[c], width, height) for c in range(len(Ks))))
    return np.concatenate(origins), np.concatenate(dirs)


def render_views(parts: list[tuple[np.ndarray, np.ndarray, object]], Ks: np.ndarray, viewmats: np.ndarray,
                 width: int, height: int, rays: tuple[np.ndarray, np.ndarray] | None = None,
                 ambient: float = AMBIENT, diffuse: float = DIFFUSE, supersample: int = 1):
    """Ray cast the union of mesh parts [(vertices [V,3], faces [F,3], texture)] into every camera.

    rays: optional precomputed `all_camera_rays(Ks, viewmats, width, height)`. Shading: albedo x (ambient + diffuse x
    max(0, n.LIGHT_DIR)), the light fixed in the world.
    supersample: s > 1 integrates each pixel as a camera does: s x s rays on a regular grid inside the pixel, averaged
    (misses count as the black background). Only pixels within one pixel of a centre-ray hit take them (the rest is
    background); s = 1 is one ray through each pixel centre, whose sub-pixel texture detail aliases.
    Returns rgb [C,H,W,3] uint8 (black background), mask [C,H,W] uint8 (0/255): 255 where at least half of the
    pixel is covered (s > 1), or where the centre ray hits (s = 1), and part [C,H,W] uint8: 1 + the index of the part
    whose surface is the first hit of at least half of the pixel's rays (the centre ray's, s = 1), 0 where none is
    (the evaluation's garment labels: which pixels show the cloth).
    """
    if isinstance(supersample, bool) or int(supersample) != supersample or not 1 <= supersample <= 8:
        raise ValueError(f"supersample: expected an integer 1..8 (rays per pixel side), got {supersample!r}")
    s = int(supersample)
    verts, faces, owner, offsets = [], [], [], [0]
    for i, (v, f, _) in enumerate(parts):
        faces.append(np.asarray(f) + offsets[-1])
        verts.append(np.asarray(v, dtype=np.float64))
        owner.append(np.full(len(f), i))
        offsets.append(offsets[-1] + len(v))
    V, Fc, owner = np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)
    mesh = trimesh.Trimesh(V, Fc, process=False, validate=False)
    caster = RayMeshIntersector(mesh)
    vn = _vertex_normals(V, Fc)
    C = len(Ks)
    origins, dirs = rays if rays is not None else all_camera_rays(Ks, viewmats, width, height)

    def shade(o: np.ndarray, d: np.ndarray):
        """Colour of every ray's first hit: (ray index [P], albedo x light [P,3], part index [P])."""
        tri, ray, bary = first_hits(caster, V, Fc, o, d)
        if not len(ray):
            return ray, np.zeros((0, 3)), np.zeros(0, np.int64)
        d = d[ray]
        normal = np.einsum("pk,pkc->pc", bary, vn[Fc[tri]])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True).clip(1e-12)
        normal = np.where((np.einsum("pc,pc->p", normal, d) > 0)[:, None], -normal, normal)  # two-sided cloth
        light = ambient + diffuse * np.clip(normal @ LIGHT_DIR, 0, None)
        albedo = np.zeros((len(ray), 3))
        for i, (_, f, tex) in enumerate(parts):
            sel = owner[tri] == i
            if sel.any():
                albedo[sel] = tex(np.asarray(f)[tri[sel] - _face_offset(parts, i)], bary[sel])
        return ray, albedo * light[:, None], owner[tri]

    rgb = np.zeros((C * width * height, 3))
    mask = np.zeros(C * width * height, dtype=np.uint8)
    part = np.zeros(C * width * height, dtype=np.uint8)
    ray, col, own = shade(origins, dirs)
    rgb[ray] = col
    mask[ray] = 255
    part[ray] = own + 1
    if s > 1:
        # Pixels within one pixel of a centre hit (a 3x3 dilation of the centre mask), each camera on its own.
        hit = mask.reshape(C, height, width) > 0
        pad = np.pad(hit, ((0, 0), (1, 1), (1, 1)))
        near = np.zeros_like(hit)
        for dy in range(3):
            for dx in range(3):
                near |= pad[:, dy:dy + height, dx:dx + width]
        sub = (np.arange(s) + 0.5) / s  # sub-pixel offsets from the pixel's corner
        sv, su = (a.ravel() for a in np.meshgrid(sub, sub, indexing="ij"))
        for c in range(C):
            ys, xs = np.nonzero(near[c])
            if not len(ys):
                continue
            o, d = pixel_rays(Ks[c], viewmats[c], (xs[:, None] + su[None]).ravel(), (ys[:, None] + sv[None]).ravel())
            r, col, own = shade(o, d)
            acc = np.zeros((len(ys) * s * s, 3))
            acc[r] = col
            hit_part = np.zeros(len(ys) * s * s, dtype=np.int64)  # 0: background, else 1 + part index
            hit_part[r] = own + 1
            idx = c * width * height + ys * width + xs
            rgb[idx] = acc.reshape(len(ys), s * s, 3).mean(1)
            hit_part = hit_part.reshape(len(ys), s * s)
            mask[idx] = np.where((hit_part > 0).mean(1) >= 0.5, 255, 0)
            share = np.stack([(hit_part == k + 1).mean(1) for k in range(len(parts))], 1)  # [P,parts]
            part[idx] = np.where(share.max(1) >= 0.5, share.argmax(1) + 1, 0)
    rgb8 = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    rgb8[mask > 0] = np.maximum(rgb8[mask > 0], 1)
    return rgb8.reshape(C, height, width, 3), mask.reshape(C, height, width), part.reshape(C, height, width)


def first_hits(caster, V: np.ndarray, Fc: np.ndarray, o: np.ndarray, d: np.ndarray):
    """First hit of every ray (origins o, directions d [R,3]) on the mesh (V, Fc) behind `caster`: triangle index
    [P], ray index [P] and barycentrics [P,3] of the hit (from the ray/plane intersection; Embree's own are not
    exposed by trimesh)."""
    tri, ray = caster.intersects_id(o, d, multiple_hits=False, return_locations=False)
    if not len(ray):
        return tri, ray, np.zeros((0, 3))
    tris = V[Fc[tri]]  # [P,3,3]
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    o, d = o[ray], d[ray]
    tt = np.einsum("pc,pc->p", tris[:, 0] - o, n) / np.einsum("pc,pc->p", d, n)
    loc = o + tt[:, None] * d
    bary = trimesh.triangles.points_to_barycentric(tris, loc).clip(0, 1)
    bary /= bary.sum(1, keepdims=True).clip(1e-12)
    return tri, ray, bary


def _face_offset(parts, i: int) -> int:
    return int(sum(len(p[1]) for p in parts[:i]))
