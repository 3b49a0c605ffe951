"""A physics garment (`sheet=physics`, not in the paper): the skirt as simulated cloth, Gaussians fixed to its material.

The pose-driven garments (model/sheet.py) cannot tell two drapes at one pose apart, nor hold one texture folded at
rest and flared in a spin (docs/research/2026-12-07-converged-cloth.md). Here the garment is a cloth that a solver
moves with the body, so its state carries the motion's history, and every garment Gaussian keeps its place in the
material in every frame:

1. **Rest shape from the training masks** (`estimate_shape`): a tube of cloth from the waist (the body's extent
   around the pelvis) down to the hem, which the rest frame's visual hull shows (where its radius steps in), with the
   hem wide enough for the widest flare that the training frames' hulls show. Nothing is read from a scene's files
   but what a capture has: images, foreground masks, body poses and cameras. Skirts and dresses (a tube hanging from
   the waist) are covered; a garment whose hull shows no hem below the waist is refused, naming the frame.
2. **A solver driven by the body**: MuJoCo's flex cloth (data/synthetic/cloth.py `drive_cloth`), the waist pinned to
   the posed pelvis, the legs, hips and torso capsules whose radii come from the body model's mesh, gravity along
   the cameras' mean up. Its own mesh (`around` x `rings`, no self-collision) and every material value are the
   model's: the bending stiffness, the air drag and the cloth's length and hem width are fitted to the training
   masks by a gradient-free coordinate search (`fit`). The embedded scenes are simulated by the same solver with
   another mesh, self-collision and their own material: docs/research/2026-12-08-physics-garment.md says what
   that does and does not show.
3. **Gaussians fixed to the material**: each sits at fixed barycentric coordinates of a triangle of the cloth, a
   disc in the surface (two in-surface scales, a turn and a small shift along the normal learnt), with one albedo
   per material point for all frames, lit by its triangle's (two-sided) normal through an irradiance map over
   world normals (SH, learnt, shared).
4. **Tracking residual** (`residual: true`): on training frames a per-frame offset of every cloth vertex, held near
   the simulated shape by an as-rigid-as-possible term (losses.GarmentTracking, which the garment brings): edge
   lengths kept, offsets smooth over the mesh and over time. Frames that are not training frames render the
   simulation as it is.

New motions (novel poses, `realityavatar-animate`) are simulated forward by `drive`, from the first pose of the
motion; a blow-up ends with an error naming the frame (drive_cloth's checks), and cloth inside the body is counted.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.body.base import BodyModel
from realityavatar.geometry import matrix_to_quat
from realityavatar.render import sh_basis

NORMAL_SCALE = 1e-3  # metres: the Gaussians are discs in the cloth
NORMAL_SHIFT = 0.01  # metres: the most a Gaussian may sit off the cloth, along its normal
PELVIS, LHIP, RHIP, LKNEE, RKNEE, SPINE1, SPINE2, LANKLE, RANKLE, NECK = 0, 1, 2, 4, 5, 3, 6, 7, 8, 12
# The colliders, in drive_cloth's order (thighs, shins, hips, torso), and the joints whose body vertices size them.
SEGMENTS = ((LHIP, LKNEE, (1,)), (RHIP, RKNEE, (2,)), (LKNEE, LANKLE, (4,)), (RKNEE, RANKLE, (5,)),
            (LHIP, RHIP, (0, 1, 2)), (PELVIS, SPINE2, (0, 3, 6)))
FITTED = ("young", "drag_tau", "length_scale", "hem_scale")  # the coordinate search's parameters, in its order
INSIDE_SHARE = 0.05  # a frame whose cloth has more than this share of its vertices inside the body is reported


def tube(around: int, rings: int, waist_radius: float, hem_radius: float, length: float, seed: int, noise: float):
    """The model's cloth in its own frame (axis +z up, waist ring at z = 0): vertices [rings*around,3] ring by ring
    from the waist (the first `around` are pinned), triangles [2*around*(rings-1),3] with alternating diagonals (not
    the scenes' tube_topology), outward. A straight cone from the waist to the hem ring at `length` along the surface,
    rippled by `noise` metres (seeded; it breaks the symmetry so that the cloth can fold)."""
    s = np.linspace(0.0, 1.0, rings)[:, None]
    phi = 2 * np.pi * (np.arange(around)[None, :] + 0.5 * (np.arange(rings)[:, None] % 2)) / around  # staggered
    r = waist_radius + s * (hem_radius - waist_radius)
    drop = math.sqrt(max(length**2 - (hem_radius - waist_radius) ** 2, 1e-4))
    rng = np.random.default_rng(seed)
    r = r + noise * s * rng.standard_normal((rings, around)) * (np.arange(rings)[:, None] > 0)
    pts = np.stack([r * np.cos(phi), r * np.sin(phi), np.broadcast_to(-s * drop, r.shape)], -1).reshape(-1, 3)
    tris = []
    for j in range(rings - 1):
        for i in range(around):
            a, b = j * around + i, j * around + (i + 1) % around
            c, d = a + around, b + around
            # staggered rings: ring j+1's vertex i sits between ring j's i and i+1 on odd rows, before it on even
            tris += [[a, c, b], [b, c, d]] if j % 2 == 0 else [[a, c, d], [a, d, b]]
    tris = np.asarray(tris, np.int64)
    t = pts[tris[0]]
    n = np.cross(t[1] - t[0], t[2] - t[0])
    if n @ np.array([t.mean(0)[0], t.mean(0)[1], 0.0]) < 0:
        tris = tris[:, [0, 2, 1]]
    return pts, tris


def batched_normals(V: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals of meshes V [B,P,3] sharing faces [F,3] -> [B,P,3]."""
    tri = V[:, faces]  # [B,F,3,3]
    fn = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    vn = torch.zeros_like(V).index_add_(1, faces.reshape(-1), fn.repeat_interleave(3, dim=1))
    return F.normalize(vn, dim=-1)


class Silhouettes:
    """The training masks of some frames at low resolution, and the garment's silhouette drawn from meshes: the
    search's objective, 1 - the mean IoU of the cloth's pixels against the mask's, both outside the posed body's
    pixels (no garment mask needed). Meshes are drawn as points sampled densely on their triangles."""

    def __init__(self, dm, frames: list[int], size: int) -> None:
        ds = dm.datasets["train"]
        self.frames, self.size = list(frames), int(size)
        want = set(self.frames)
        self.items = []  # (frame, K [3,3] at `size`, viewmat [4,4], mask [size,size] bool)
        for i, rec in enumerate(ds.records):
            if rec.frame not in want:
                continue
            _, mask, K = ds._decoded(i)
            m = torch.as_tensor(np.asarray(mask, np.float32))
            H, W = m.shape
            k = max(H, W) // self.size
            m = F.avg_pool2d(m[None, None], k)[0, 0] > 0.5
            Ks = np.asarray(K, np.float64).copy()
            Ks[:2] /= k
            self.items.append((int(rec.frame), Ks, np.asarray(rec.viewmat, np.float64), m.numpy()))
        if not self.items:
            raise ValueError("sheet=physics: no training masks to fit the garment to")
        self.shape = self.items[0][3].shape

    def draw(self, pts: np.ndarray, K: np.ndarray, E: np.ndarray) -> np.ndarray:
        x = pts @ E[:3, :3].T + E[:3, 3]
        ok = x[:, 2] > 1e-3
        uv = (x[ok] @ K.T)[:, :2] / x[ok, 2:3]
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        H, W = self.shape
        keep = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        img = np.zeros((H, W), bool)
        img[v[keep], u[keep]] = True
        return img

    def loss(self, body: dict[int, np.ndarray], cloth: dict[int, np.ndarray]) -> float:
        """body, cloth: frame -> world points [n,3] -> 1 - the mean IoU of the cloth against the mask off the body."""
        ious = []
        for f, K, E, m in self.items:
            off = ~self.draw(body[f], K, E)
            d, g = self.draw(cloth[f], K, E) & off, m & off
            ious.append((d & g).sum() / max((d | g).sum(), 1))
        return 1.0 - float(np.mean(ious))


def surface_points(V: np.ndarray, tris: np.ndarray, per_tri: int) -> np.ndarray:
    """Points on every triangle of meshes V [F,P,3]: a fixed barycentric grid of ~per_tri points -> [F,n,3]."""
    k = max(1, math.ceil((math.sqrt(8 * per_tri + 1) - 1) / 2))
    w = np.array([(i / k, j / k) for i in range(k + 1) for j in range(k + 1 - i)])
    bary = np.concatenate([1 - w.sum(1, keepdims=True), w], 1)  # [m,3]
    return np.einsum("mk,fnkc->fnmc", bary, V[:, tris]).reshape(V.shape[0], -1, 3)


class PhysicsGarment(nn.Module):
    """`sheet=physics`: see the module doc. A source of Gaussians beside the free ones (model/avatar.py): the decoder
    does not move it (no points); its Gaussians come from the simulated cloth of each sample's frame, and it colours
    them itself (`lit`)."""

    num_basis = 0

    def __init__(self, body: BodyModel, around: int, rings: int, gaussians: int, material: dict, search: dict,
                 residual: bool, tracking: dict, waist_offset: float, waist_margin: float, hull_voxel: float,
                 hull_quantile: float, flare_every: int, sh_degree: int, init_opacity: float, seed: int,
                 feature_dim: int, data=None) -> None:
        super().__init__()
        if around < 8 or rings < 3 or gaussians < 1:
            raise ValueError(f"sheet (physics): expected around >= 8, rings >= 3, gaussians >= 1, got {around}, "
                             f"{rings}, {gaussians}")
        if not 0.0 < init_opacity < 1.0:
            raise ValueError(f"sheet.init_opacity: expected a value in (0,1), got {init_opacity}")
        self.around, self.rings, self.num_gaussians = int(around), int(rings), int(gaussians)
        self.material = {k: float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v
                         for k, v in dict(material).items()}
        self.search_cfg = dict(search)
        self.residual_on, self.tracking = bool(residual), {k: float(v) for k, v in dict(tracking).items()}
        self.waist_offset, self.waist_margin = float(waist_offset), float(waist_margin)
        self.hull_voxel, self.hull_quantile, self.flare_every = float(hull_voxel), float(hull_quantile), int(flare_every)
        self.seed, self.sh_degree, self.feature_dim = int(seed), int(sh_degree), int(feature_dim)
        self.state: dict = {}  # the fitted shape, material and colliders: what `drive` needs (checkpointed)
        self.layout: dict = {"profile": "physics"}
        M = self.num_gaussians
        self.register_buffer("features", torch.zeros(0, self.feature_dim), persistent=False)  # coloured by `lit`
        self.register_buffer("faces", torch.zeros(0, 3, dtype=torch.long))
        self.register_buffer("tri", torch.zeros(M, dtype=torch.long))  # each Gaussian's triangle
        self.register_buffer("bary", torch.zeros(M, 3))  # and its barycentric point there
        self.register_buffer("spacing", torch.zeros(M))  # metres between neighbouring Gaussians
        self.register_buffer("track_frames", torch.zeros(0, dtype=torch.long))  # [T] the frames simulated
        self.register_buffer("track", torch.zeros(0, 0, 3))  # [T,P,3] world cloth vertices per frame
        self.register_buffer("train_frames", torch.zeros(0, dtype=torch.long))  # frame of each training index
        self.albedo = nn.Parameter(torch.zeros(M, 3))  # sigmoid: 0.5 grey
        p = torch.tensor(init_opacity)
        self.opacity_logits = nn.Parameter(torch.full((M,), float(torch.log(p / (1 - p)))))
        self.scale_logit = nn.Parameter(torch.full((M, 2), -0.69))  # 0.1 + 1.9 sigmoid: 0.6 x the spacing
        self.angle = nn.Parameter(torch.zeros(M))
        self.shift_logit = nn.Parameter(torch.zeros(M))
        self.light = nn.Parameter(torch.zeros((self.sh_degree + 1) ** 2, 3))  # log irradiance over world normals
        self.offsets = nn.Parameter(torch.zeros(0, 0, 3), requires_grad=self.residual_on)  # [F_train,P,3]
        self.register_load_state_dict_pre_hook(self._take_sized_buffers)
        if data is not None:
            self._build(body, data)

    SIZED_BY_DATA = ("faces", "track_frames", "track", "train_frames", "offsets")

    def _take_sized_buffers(self, module, state_dict, prefix, *args) -> None:
        for name in self.SIZED_BY_DATA:
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                value = torch.zeros_like(state_dict[key])
                old = getattr(self, name)
                setattr(self, name, nn.Parameter(value, requires_grad=old.requires_grad)
                        if isinstance(old, nn.Parameter) else value)

    def get_extra_state(self) -> dict:
        return {"state": json.dumps(self.state)}

    def set_extra_state(self, extra: dict) -> None:
        self.state = json.loads(extra["state"])
        self.layout = {"profile": "physics", **{k: self.state[k] for k in ("shape", "material") if k in self.state}}

    # ------------------------------------------------------------------ building: shape, colliders, fit, track
    def _build(self, body: BodyModel, dm) -> None:
        t0 = time.perf_counter()
        ds = dm.datasets.get("train")
        if ds is None:
            raise ValueError("sheet=physics: the DataModule has no training split to fit the garment to")
        table = dm.scene.poses
        frames = [int(f) for f in table.frames]
        if frames != list(range(frames[0], frames[0] + len(frames))):
            raise ValueError(f"sheet=physics: the cloth is simulated through consecutive frames, but {table.source} "
                             f"skips frames (it holds {len(frames)} of {frames[0]}..{frames[-1]})")
        order = sorted(ds.train_frame_index.items(), key=lambda kv: kv[1])
        self.train_frames = torch.tensor([f for f, _ in order], dtype=torch.long)
        up = camera_up(ds)
        shape = estimate_shape(body, dm, up, self.waist_offset, self.waist_margin, self.hull_voxel,
                               self.hull_quantile, self.flare_every)
        self.state = {"up": up.tolist(), "shape": shape, "fps": float(dm.fps),
                      "radii": collider_radii(body, *table.get(frames[0]))}
        pose, transl = table.poses, table.transl
        train = [f for f, _ in order]
        sil = Silhouettes(dm, train[:: max(1, int(self.search_cfg["frame_every"]))], int(self.search_cfg["size"]))
        # the search simulates up to the last training frame only
        last = max(train) - frames[0] + 1
        body_pts = body_points(body, pose[:last], transl[:last])
        fit = self.fit(sil, body_pts, pose[:last], transl[:last], frames[:last], body)
        self.state["material"] = fit["material"]
        self.state["search"] = fit["record"]
        V = self.simulate(body, pose, transl)  # [T,P,3] every frame of the table, the fitted material
        self.track_frames = torch.tensor(frames, dtype=torch.long)
        self.track = torch.as_tensor(V, dtype=torch.float32)
        self._place_gaussians()
        if self.residual_on:
            self.offsets = nn.Parameter(torch.zeros(len(order), V.shape[1], 3))
        self.layout = {"profile": "physics", "shape": shape, "material": fit["material"],
                       "search_loss": fit["record"]["loss"], "seconds": round(time.perf_counter() - t0, 1)}

    def cloth(self, material: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The model's cloth at `material`'s length and hem scales (default: the fitted): vertices, triangles."""
        m = self.state["material"] if material is None else material
        s = self.state["shape"]
        return tube(self.around, self.rings, s["waist_radius"], s["hem_radius"] * m["hem_scale"],
                    s["length"] * m["length_scale"], self.seed, float(self.material["init_noise"]))

    def simulate(self, body: BodyModel, pose: torch.Tensor, transl: torch.Tensor, material: dict | None = None,
                 where: str = "sheet=physics") -> np.ndarray:
        """The cloth on the motion pose [T,24,3], transl [T,3] (the table's frames in order) -> vertices [T,P,3]."""
        from realityavatar.data.synthetic.cloth import drive_cloth

        m = {**self.material, **(self.state["material"] if material is None else material)}
        pts, tris = self.cloth(m)
        with torch.no_grad():
            A = body.canonical_transforms(pose.float(), transl.float()).double().cpu().numpy()  # [T,24,4,4]
            J = body.joints(pose.float(), transl.float()).double().cpu().numpy()  # [T,24,3]
        # the cloth's frame: +z along the body's axis at the first pose, in the pelvis's frame there
        R0 = A[0, PELVIS, :3, :3]
        up = np.asarray(self.state["up"])
        axis = J[0, NECK] - J[0, PELVIS]
        axis /= np.linalg.norm(axis)
        e1 = J[0, LHIP] - J[0, RHIP]
        e1 -= (e1 @ axis) * axis
        e1 /= np.linalg.norm(e1)
        frame = np.stack([e1, np.cross(axis, e1), axis], 1)  # world columns
        local = (pts @ frame.T + self.waist_offset * axis) @ R0  # world offsets from the pelvis, in its frame
        p = {**m, "self_collision": False}
        length = self.state["shape"]["length"] * m["length_scale"]
        return drive_cloth(local, tris, self.around, p, self.state["radii"], J, A[:, :, :3, :3], self.state["fps"],
                           limit=max(1.0, 1.5 * length + 0.5), gravity=tuple(-9.81 * up), where=where)

    def fit(self, sil: Silhouettes, body_pts: np.ndarray, pose, transl, frames: list[int], body) -> dict:
        """Coordinate search over FITTED (log scale): each parameter in turn tried a step up and down, the best kept;
        the steps halve after a round without a gain; at most search.rollouts simulations."""
        cfg = self.search_cfg
        x = {k: float(self.material[k]) for k in FITTED}
        steps = {k: float(cfg["steps"][k]) for k in FITTED}
        row = {f: i for i, f in enumerate(frames)}
        _, tris = self.cloth(x)
        tried: list[dict] = []
        seen: dict[tuple, float] = {}

        def loss(m: dict) -> float:
            key = tuple(round(math.log(m[k]), 6) for k in FITTED)
            if key in seen:
                return seen[key]
            seen[key] = val = simulated(m)
            return val

        def simulated(m: dict) -> float:
            try:
                V = self.simulate(body, pose, transl, m)
            except RuntimeError as e:  # an unstable material is a bad material, not the end of the search
                tried.append({**m, "loss": None, "error": str(e)[:120]})
                return math.inf
            cloth = surface_points(V, tris, 10)
            val = sil.loss({f: body_pts[row[f]] for f, *_ in sil.items}, {f: cloth[row[f]] for f, *_ in sil.items})
            tried.append({**{k: round(v, 5) for k, v in m.items()}, "loss": round(val, 5)})
            return val

        best, rollouts = loss(x), int(cfg["rollouts"])
        for _ in range(20):  # rounds; a candidate tried before costs no simulation
            improved = False
            for k in FITTED:
                for sign in (1, -1):
                    if len(seen) >= rollouts:
                        break
                    cand = {**x, k: x[k] * math.exp(sign * steps[k])}
                    val = loss(cand)
                    if val < best:
                        best, x, improved = val, cand, True
                        break
            if len(seen) >= rollouts:
                break
            if not improved:
                steps = {k: v / 2 for k, v in steps.items()}
        return {"material": x, "record": {"loss": best, "rollouts": len(tried), "tried": tried}}

    def _place_gaussians(self) -> None:
        from realityavatar.geometry import sample_barycentric

        pts, tris = self.cloth()
        self.faces = torch.as_tensor(tris, dtype=torch.long)
        gen = torch.Generator().manual_seed(self.seed)
        fi, bary, area = sample_barycentric(torch.as_tensor(pts), self.faces, self.num_gaussians, gen)
        self.tri.copy_(fi)
        self.bary.copy_(bary)
        self.spacing.fill_(float((area.sum() / self.num_gaussians).sqrt()))

    # ------------------------------------------------------------------ new motions
    @torch.no_grad()
    def drive(self, body: BodyModel, table) -> dict:
        """Simulate the cloth on the motion of a PoseTable (consecutive frames) with the fitted material and make it
        the track that frames are rendered from. Returns a record: frames, seconds, and `inside`: the frames where
        more than INSIDE_SHARE of the cloth's vertices are over 1 cm inside the body's colliders (cloth passed
        through the body), which it also prints. A blow-up raises RuntimeError naming the frame."""
        frames = [int(f) for f in table.frames]
        if frames != list(range(frames[0], frames[0] + len(frames))):
            raise ValueError(f"sheet=physics: {table.source} skips frames; the cloth needs a consecutive motion")
        t0 = time.perf_counter()
        V = self.simulate(body, table.poses, table.transl, where=f"sheet=physics on {table.source}")
        self.track_frames = torch.tensor(frames, dtype=torch.long, device=self.track.device)
        self.track = torch.as_tensor(V, dtype=self.track.dtype, device=self.track.device)
        J = body.joints(table.poses.float(), table.transl.float()).double().cpu().numpy()
        share = inside_share(V, J, self.state["radii"])
        inside = [f for f, s in zip(frames, share) if s > INSIDE_SHARE]
        if inside:
            print(f"sheet=physics on {table.source}: the cloth is inside the body in {len(inside)} frames "
                  f"(first {inside[:5]}; up to {100 * share.max():.0f} % of its vertices)")
        return {"frames": len(frames), "seconds": round(time.perf_counter() - t0, 2), "inside": inside}

    # ------------------------------------------------------------------ the source interface (model/avatar.py)
    @property
    def num_points(self) -> int:
        return 0  # no points for the decoder

    @property
    def lit_points(self) -> int:
        return self.num_gaussians

    def points(self):
        z = self.albedo.new_zeros(0, 3)
        return z, z, self.albedo.new_zeros(0, 4)

    def move(self, dx: torch.Tensor, h_t: torch.Tensor) -> torch.Tensor:
        return dx

    def vertices(self, frame: torch.Tensor, frame_idx: torch.Tensor) -> torch.Tensor:
        """The cloth of each sample [B,P,3]: its frame's simulation, plus its training frame's residual."""
        if self.track.shape[0] == 0:
            raise ValueError("sheet=physics: no simulated cloth (built without the training data and no checkpoint "
                             "loaded)")
        rows = frame.long().to(self.track_frames.device) - self.track_frames[0]
        bad = (rows < 0) | (rows >= len(self.track_frames))
        if bool(bad.any()):
            raise KeyError(f"sheet=physics: frame {int(frame[bad][0])} was not simulated (the cloth covers frames "
                           f"{int(self.track_frames[0])}..{int(self.track_frames[-1])}; `drive` a new motion first)")
        V = self.track[rows]
        if self.residual_on:
            k = frame_idx.long().to(V.device)
            keep = (k >= 0).to(V.dtype)[:, None, None]
            V = V + keep * self.offsets[k.clamp_min(0)]
        return V

    def splats(self, posed: dict, inputs: dict) -> dict:
        frame = inputs.get("frame")
        if frame is None:
            raise ValueError("sheet=physics: the garment is simulated per frame; deform's inputs need 'frame'")
        frame_idx = inputs.get("frame_idx", torch.full_like(frame, -1))
        V = self.vertices(frame, frame_idx).to(posed["means"].dtype)  # [B,P,3]
        B, M = V.shape[0], self.num_gaussians
        corners = self.faces[self.tri]  # [M,3]
        tri = V[:, corners]  # [B,M,3,3]
        w = self.bary.to(V)
        n = (w[None, :, :, None] * batched_normals(V, self.faces)[:, corners]).sum(2)
        n = F.normalize(n, dim=-1)
        x = (w[None, :, :, None] * tri).sum(2) + NORMAL_SHIFT * torch.tanh(self.shift_logit)[None, :, None] * n
        e = tri[:, :, 1] - tri[:, :, 0]
        t1 = F.normalize(e - (e * n).sum(-1, keepdim=True) * n, dim=-1)
        t2 = torch.linalg.cross(n, t1)
        c, s = self.angle.cos()[None, :, None], self.angle.sin()[None, :, None]
        R = torch.stack([c * t1 + s * t2, -s * t1 + c * t2, n], -1)
        s2 = self.spacing[:, None] * (0.1 + 1.9 * torch.sigmoid(self.scale_logit))
        scales = torch.cat([s2, torch.full_like(s2[:, :1], NORMAL_SCALE)], -1)[None].expand(B, M, 3)
        ref = posed["means"]
        eye = torch.eye(3, dtype=ref.dtype, device=ref.device)
        return {"means": x, "quats": matrix_to_quat(R), "scales": scales, "rot": eye.expand(B, M, 3, 3),
                "f_mt": ref.new_zeros(1, 1, posed["f_mt"].shape[-1]).expand(B, M, -1),
                "weights": ref.new_zeros(1, 1, posed["weights"].shape[-1]).expand(B, M, -1),
                "x_e": x, "garment_normals": n, "sheet_verts": V}

    def lit(self, posed: dict, cam_centre: torch.Tensor) -> torch.Tensor:
        """The garment's colours [B,M,3]: albedo x irradiance of the normal turned to the camera (two-sided cloth)."""
        M = self.num_gaussians
        x, n = posed["means"][:, -M:], posed["garment_normals"]
        facing = torch.where(((x - cam_centre[:, None]) * n).sum(-1, keepdim=True) > 0, -n, n)
        return torch.sigmoid(self.albedo)[None] * self.irradiance(facing)

    def irradiance(self, n: torch.Tensor) -> torch.Tensor:
        return torch.exp(sh_basis(self.sh_degree, n) @ self.light)

    def baked_rgb(self) -> torch.Tensor:
        """[M,3] each Gaussian's colour under the light averaged over the six axis directions (export, viewer)."""
        axes = torch.eye(3, dtype=self.light.dtype, device=self.light.device)
        e = self.irradiance(torch.cat([axes, -axes])).mean(0)
        return (torch.sigmoid(self.albedo) * e).clamp(0, 1)

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def colour_features(self, frame_idx: torch.Tensor) -> torch.Tensor:
        return self.features

    def canonical(self) -> dict:
        """The garment's Gaussians on the first simulated frame's cloth (world space: the cloth has no canonical
        pose)."""
        inputs = {"frame": self.track_frames[:1]}
        ref = {"means": self.albedo.new_zeros(1, 0, 3), "f_mt": self.albedo.new_zeros(1, 0, 1),
               "weights": self.albedo.new_zeros(1, 0, 24)}
        out = self.splats(ref, inputs)
        return {"means": out["means"][0], "quats": out["quats"][0], "scales": out["scales"][0],
                "opacities": self.opacities()}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        groups = {"garment_albedo": [self.albedo], "garment_opacity": [self.opacity_logits],
                  "garment_shape": [self.scale_logit, self.angle, self.shift_logit], "garment_light": [self.light]}
        if self.residual_on:
            groups["garment_offsets"] = [self.offsets]
        return groups

    def loss_terms(self) -> dict:
        if not self.residual_on:
            return {}
        from realityavatar.losses import GarmentTracking

        return {"garment_tracking": GarmentTracking(**self.tracking)}

    def canonicalise(self, body: BodyModel, skinning: nn.Module) -> None:
        return None

    def tracking_terms(self, V: torch.Tensor, frame_idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """The residual's regularisers for samples V [B,P,3] of training frames frame_idx [B]: the relative change of
        every edge's length from the simulated frame's, squared; the offsets' squared Laplacian over the mesh; their
        squared difference from the next training frame's."""
        k = frame_idx.long().clamp_min(0)
        sim = self.track[self.train_frames.to(k.device)[k] - self.track_frames[0]]
        e = self.edges()
        L = (V[:, e[:, 0]] - V[:, e[:, 1]]).norm(dim=-1)
        L0 = (sim[:, e[:, 0]] - sim[:, e[:, 1]]).norm(dim=-1).clamp_min(1e-6)
        d = self.offsets[k]
        nbr = torch.zeros_like(d).index_add_(1, e[:, 0], d[:, e[:, 1]]).index_add_(1, e[:, 1], d[:, e[:, 0]])
        deg = torch.zeros(d.shape[1], dtype=d.dtype, device=d.device).index_add_(
            0, e.reshape(-1), torch.ones(e.numel(), dtype=d.dtype, device=d.device)).clamp_min(1)
        lap = d - nbr / deg[None, :, None]
        nxt = self.offsets[(k + 1).clamp_max(len(self.offsets) - 1)]
        return {"stretch": ((L / L0 - 1) ** 2).mean(), "smooth": (lap**2).sum(-1).mean(),
                "temporal": ((d - nxt) ** 2).sum(-1).mean()}

    def edges(self) -> torch.Tensor:
        f = self.faces
        e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
        return torch.unique(e, dim=0)

    def extra_repr(self) -> str:
        return (f"around={self.around}, rings={self.rings}, gaussians={self.num_gaussians}, "
                f"residual={self.residual_on}")


def inside_share(V: np.ndarray, J: np.ndarray, radii: list[float], depth: float = 0.01) -> np.ndarray:
    """Per frame, the share of cloth vertices V [T,P,3] more than `depth` inside a collider (the capsules of joints
    J [T,24,3] with `radii`, SEGMENTS' order) [T]."""
    a = J[:, [s[0] for s in SEGMENTS]][:, None]  # [T,1,C,3]
    b = J[:, [s[1] for s in SEGMENTS]][:, None]
    d = b - a
    t = np.clip(np.einsum("tpci,tpci->tpc", V[:, :, None] - a, d) / np.maximum((d * d).sum(-1), 1e-12), 0, 1)
    dist = np.linalg.norm(V[:, :, None] - (a + t[..., None] * d), axis=-1)  # [T,P,C]
    return ((dist < np.asarray(radii) - depth).any(-1)).mean(1)


# ---------------------------------------------------------------------- what the masks and the body give
def camera_up(ds) -> np.ndarray:
    """World up from the training cameras: the direction most nearly perpendicular to all their image-right axes
    (+x of an OpenCV camera; a camera without roll keeps it level), turned to their mean image-up (-y)."""
    R = np.stack([np.asarray(r.viewmat, np.float64)[:3, :3] for r in ds.records])
    w, vec = np.linalg.eigh(np.einsum("ni,nj->ij", R[:, 0], R[:, 0]))
    up = vec[:, 0]
    if w[1] < 1e-3 * max(w[2], 1e-12):
        raise ValueError("sheet=physics: the training cameras all look one way, so their image axes do not fix "
                         "which way is up; the cloth needs gravity's direction")
    return up if up @ -R[:, 1].mean(0) > 0 else -up


def body_points(body: BodyModel, pose: torch.Tensor, transl: torch.Tensor, stride: int = 2) -> np.ndarray:
    """Every `stride`-th posed body vertex per frame [T,n,3] (the silhouette's body part)."""
    with torch.no_grad():
        return body.posed_vertices(pose.float(), transl.float())[:, ::stride].double().cpu().numpy()


def collider_radii(body: BodyModel, pose: torch.Tensor, transl: torch.Tensor) -> list[float]:
    """The colliders' radii from the body's mesh at one pose: per segment, the median distance from the segment of
    the body vertices skinned mostly to its joints that lie along its middle 60 %."""
    with torch.no_grad():
        v = body.posed_vertices(pose[None].float(), transl[None].float())[0].double().cpu().numpy()
        J = body.joints(pose[None].float(), transl[None].float())[0].double().cpu().numpy()
    main = body.skin_weights.argmax(-1).cpu().numpy()
    radii = []
    for a, b, joints in SEGMENTS:
        d = J[b] - J[a]
        t = (v - J[a]) @ d / max(d @ d, 1e-9)
        sel = np.isin(main, joints) & (t > 0.2) & (t < 0.8)
        if sel.sum() < 10:
            raise ValueError(f"sheet=physics: the body has too few vertices around joints {joints} to size a collider")
        dist = np.linalg.norm(v[sel] - (J[a] + t[sel, None] * d), axis=1)
        radii.append(float(np.median(dist)))
    return radii


def estimate_shape(body: BodyModel, dm, up: np.ndarray, waist_offset: float, waist_margin: float, voxel: float,
                   quantile: float, flare_every: int) -> dict:
    """The garment's size from the training masks (module doc, 1.): the waist's radius (the body's extent around
    the waist ring, + waist_margin), the hem's depth below the waist in the rest frame's visual hull (where its
    radius steps in most), and the hem's radius at the widest flare of the training frames' hulls (every
    `flare_every`-th frame). Radii are a lower quantile over 16 azimuth sectors of each sector's farthest hull voxel
    (a hull carved from a few cameras bulges between them). Returns waist_radius, length (waist to hem along the
    cloth at the widest flare), hem_radius, depth, flare_frame."""
    from realityavatar.model.hull import body_and_hull, cylindrical, hull_views, sector_radius

    ds = dm.datasets["train"]
    frames = sorted({r.frame for r in ds.records})
    rest = hull_views(dm, frames[0])
    verts, surf = body_and_hull(body, rest, voxel, what="sheet=physics")
    J = body.joints(rest.pose[None].float(), rest.transl[None].float())[0].double().cpu().numpy()
    axis = J[NECK] - J[PELVIS]
    axis /= np.linalg.norm(axis)

    waist = J[PELVIS] + waist_offset * axis
    body_c = cylindrical(verts, waist, axis)
    waist_r = sector_radius(body_c, 0.0, 0.03, 0.5) + waist_margin  # the median sector: not the arms
    hull_c = cylindrical(surf, waist, axis)
    heights = np.arange(-0.15, -1.0, -voxel)
    prof = np.array([sector_radius(hull_c, h, voxel, quantile) for h in heights])
    k = 3
    if len(prof) <= k or prof.max() <= waist_r:
        raise ValueError(f"sheet=physics: frame {rest.frame}'s visual hull shows no garment wider than the waist "
                         "below it; the physics garment is for skirts and dresses (sheet=none for tight clothing)")
    depth = float(-heights[int(np.argmax(prof[:-k] - prof[k:]))])
    best = (prof[heights > -depth].max(), rest.frame, depth)
    for f in frames[flare_every::flare_every]:
        views = hull_views(dm, f)
        Jf = body.joints(views.pose[None].float(), views.transl[None].float())[0].double().cpu().numpy()
        ax = Jf[NECK] - Jf[PELVIS]
        ax /= np.linalg.norm(ax)
        origin = Jf[PELVIS] + waist_offset * ax
        _, s = body_and_hull(body, views, 2 * voxel, what="sheet=physics")
        c = cylindrical(s, origin, ax)
        hs = np.arange(-0.1, -depth - 0.1, -2 * voxel)
        r = np.array([sector_radius(c, h, 2 * voxel, quantile) for h in hs])
        if r.max() > best[0]:
            # the hem at the widest flare: the lowest height still at 90 % of the widest radius
            low = hs[r >= 0.9 * r.max()].min()
            best = (float(r.max()), f, float(-low))
    hem_r, flare_frame, drop = best
    length = math.hypot(max(hem_r - waist_r, 0.0), drop) if flare_frame != rest.frame else depth
    return {"waist_radius": round(float(waist_r), 4), "hem_radius": round(float(max(hem_r, waist_r + 0.02)), 4),
            "length": round(float(max(length, depth)), 4), "depth": round(depth, 4), "flare_frame": int(flare_frame)}
