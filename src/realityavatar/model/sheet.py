"""A garment sheet (`sheet=skirt`): Gaussians bound to a deformable surface of revolution around the hips and legs.

The free Gaussians of the default model build a flared skirt from whatever Gaussians end up there, a few cm off the
cloth and sliding over it (docs/research/2026-11-24-spin-limits.md). The sheet gives the garment a surface instead:
a grid of (rows + 1) x cols vertices on rings about the body's vertical axis (pelvis -> neck), from a little above
the pelvis down to the garment's hem (see GarmentSheet for the layout). The motion-trend decoder moves the vertices
(the same decoder and h_t as the free Gaussians), the skinning field poses them, and every sheet Gaussian follows
its grid cell bilinearly: its position is the cell's bilinear point plus a learnt offset along the normal, its
rotation the cell's tangent frame, its scale along the two tangents stretches with the cell. A Gaussian keeps its
place in the cloth (its colour is material, not wherever it slid), the sheet has no holes as it opens, and one
covered hem pixel moves the cells around it. The sheet's Gaussians are a fixed set beside the free ones: density
control acts on the free Gaussians only.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.body.base import BodyModel
from realityavatar.geometry import matrix_to_quat
from realityavatar.model.hull import hull_views


class Stateless:
    """What a garment without state answers beside its Gaussians (model/avatar.py; model/garment.py's PhysicsGarment
    answers otherwise): the colour model colours all its Gaussians, and a new motion needs no simulation."""

    lit_points = 0  # Gaussians that colour themselves (the last ones of the avatar): none

    def lit(self, posed: dict, cam_centre: torch.Tensor) -> torch.Tensor:
        """Colours of the Gaussians that colour themselves [B,0,3]: none."""
        return posed["means"].new_zeros(posed["means"].shape[0], 0, 3)

    def baked_rgb(self) -> torch.Tensor:
        """Baked colours of the Gaussians that colour themselves [0,3]: none."""
        return self.opacities().new_zeros(0, 3)

    def drive(self, body: BodyModel, table) -> dict:
        """A garment without state needs no simulation of a new motion: nothing simulated, no frame inside the body."""
        return {"frames": 0, "inside": []}


class GarmentSheet(Stateless, nn.Module):
    """rows x cols cells, `per_cell` Gaussians each, on a surface of revolution around the hips and legs.

    profile="rest" (the config's default): the sheet is laid out in the rest frame of the training sequence (the
    first training frame, or `hull_frame`), about that frame's posed body axis, from `top_offset` above the pelvis
    down to the garment's hem, found in that frame's visual hull (its training masks) as the height where the
    hull's radius steps in most (garment -> legs). Each ring's radius is the rest body's own extent at that height
    (`radius_from="body"`: a lower quantile over azimuth of the body's farthest point, i.e. around the legs) or the
    hull's (`"hull"`), plus `margin`. `canonicalise` then takes it to canonical space through the module's own
    skinning field (a fixed point of the inverse LBS), so at the rest frame the sheet poses back onto its layout.
    Measured: a sheet that starts around the legs, inside the garment, fits far better than one at the hull's
    radius, which four views leave loose where no silhouette grazes it (docs/research/2026-11-24-garment-sheet.md).
    profile="canonical": the canonical body, from `top_offset` to the `bottom_joints` (the knees) + `bottom_offset`,
    radii from the canonical body's widest points; also what profile="rest" falls back to without views (a run
    rebuilt from its checkpoint, whose vertices then replace it).
    """

    def __init__(self, body: BodyModel, rows: int, cols: int, per_cell: int, profile: str, top_offset: float,
                 margin: float, radius_from: str, bottom_joints: tuple[int, ...], bottom_offset: float,
                 hull_frame: int | None, hull_voxel: float, hull_quantile: float, feature_dim: int,
                 init_opacity: float, normal_scale: float, seed: int, max_stretch: float, strain_free: float,
                 basis: int, cond_dim: int, feature_init_std: float, data=None) -> None:
        """data: the set-up DataModule, whose training masks profile="rest" carves its hull from; None when a run
        is rebuilt from its checkpoint (its layout buffers replace the canonical one laid out here)."""
        super().__init__()
        if rows < 1 or cols < 3 or per_cell < 1:
            raise ValueError(f"sheet: expected rows >= 1, cols >= 3, per_cell >= 1, got {rows}, {cols}, {per_cell}")
        if profile not in ("rest", "canonical"):
            raise ValueError(f"sheet.profile: expected 'rest' or 'canonical', got {profile!r}")
        if radius_from not in ("body", "hull"):
            raise ValueError(f"sheet.radius_from: expected 'body' or 'hull', got {radius_from!r}")
        if not 0.0 < init_opacity < 1.0:
            raise ValueError(f"sheet.init_opacity: expected a value in (0,1), got {init_opacity}")
        if not 0.0 <= hull_quantile <= 1.0:
            raise ValueError(f"sheet.hull_quantile: expected a value in [0,1], got {hull_quantile}")
        self.rows, self.cols, self.per_cell = int(rows), int(cols), int(per_cell)
        self.max_stretch = float(max_stretch)  # <= 0: unbounded
        if strain_free < 0:
            raise ValueError(f"sheet.strain_free must be >= 0, got {strain_free}")
        self.strain_free = float(strain_free)  # see `strain` (the loss term losses.SheetStrain)
        self.feature_dim = int(feature_dim)
        self.profile = profile
        # profile=rest keeps its layout (posed) and that frame's pose for `canonicalise`; both are checkpointed
        self.register_buffer("posed_rest", torch.zeros(0, 3))
        self.register_buffer("rest_pose", torch.zeros(0, 3))
        self.register_buffer("rest_transl", torch.zeros(3))
        self.register_buffer("canonical_done", torch.tensor(True))
        self.layout: dict = {"profile": "canonical"}
        if profile == "rest" and data is not None:
            grid = self._rest_layout(body, hull_views(data, hull_frame), float(top_offset), float(margin), radius_from, float(hull_voxel),
                                     float(hull_quantile))
        else:
            grid = self._canonical_layout(body, float(top_offset), tuple(bottom_joints), float(bottom_offset),
                                          float(margin))
        self.register_buffer("vertices", grid.reshape(-1, 3).contiguous())  # [P,3] canonical
        # every Gaussian: its cell's four corner indices and its bilinear place (a along the ring, b down the skirt)
        gen = torch.Generator().manual_seed(seed)
        j, i = torch.meshgrid(torch.arange(self.rows), torch.arange(self.cols), indexing="ij")
        j, i = j.reshape(-1).repeat_interleave(self.per_cell), i.reshape(-1).repeat_interleave(self.per_cell)
        i1 = (i + 1) % self.cols
        corners = torch.stack([j * self.cols + i, j * self.cols + i1, (j + 1) * self.cols + i,
                               (j + 1) * self.cols + i1], dim=-1)  # [M,4]: 00, 10, 01, 11
        self.register_buffer("corners", corners)
        self.register_buffer("ab", torch.rand(corners.shape[0], 2, generator=gen))
        M = corners.shape[0]
        # scales: along the tangents in units of the cell's edge (a Gaussian's share of its cell), along the normal in m
        rel_scale = 0.5 / math.sqrt(self.per_cell)
        self.log_scales = nn.Parameter(torch.tensor([math.log(rel_scale)] * 2 + [math.log(normal_scale)]).repeat(M, 1))
        self.normal_offset = nn.Parameter(torch.zeros(M))
        p = torch.tensor(init_opacity)
        self.opacity_logits = nn.Parameter(torch.full((M,), float(torch.log(p / (1 - p)))))
        self.features = nn.Parameter(torch.randn(M, self.feature_dim, generator=gen) * feature_init_std)
        # basis > 0: a garment motion basis, per-vertex canonical offsets B [K,P,3] weighted by K coefficients that
        # are a linear function of the temporal state h_t (`basis_offsets`); starts at zero offset
        self.num_basis = int(basis)
        if self.num_basis < 0:
            raise ValueError(f"sheet.basis: expected >= 0 basis shapes, got {basis}")
        if self.num_basis:
            self.basis = nn.Parameter(torch.zeros(self.num_basis, self.vertices.shape[0], 3))
            self.coeff = nn.Linear(int(cond_dim), self.num_basis)
        self.register_load_state_dict_pre_hook(self._take_layout_buffers)

    # tensors sized by the training data at build time: a module rebuilt from its checkpoint takes their shapes there
    SIZED_BY_DATA: tuple[str, ...] = ("posed_rest", "rest_pose")

    def _take_layout_buffers(self, module, state_dict, prefix, *args) -> None:
        """A module rebuilt without the training data (the rest frame's views; SlidingSheet: its frames) loads a
        checkpoint's data-sized buffers and parameters: each is replaced by zeros of the checkpoint's shape."""
        for name in self.SIZED_BY_DATA:
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                value = torch.zeros_like(state_dict[key])
                setattr(self, name, nn.Parameter(value) if isinstance(getattr(self, name), nn.Parameter) else value)

    @staticmethod
    def _frame(origin: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Two unit vectors spanning the plane normal to `axis`."""
        ref = torch.tensor([0.0, 0.0, 1.0]) if abs(float(axis[2])) < 0.9 else torch.tensor([1.0, 0.0, 0.0])
        e1 = F.normalize(torch.linalg.cross(axis, ref.to(axis)), dim=0)
        return e1, torch.linalg.cross(axis, e1)

    def _rings(self, origin, axis, heights, radii) -> torch.Tensor:
        e1, e2 = self._frame(origin, axis)
        phi = torch.arange(self.cols, dtype=origin.dtype) * (2 * math.pi / self.cols)
        ring = torch.cos(phi)[:, None] * e1 + torch.sin(phi)[:, None] * e2  # [cols,3]
        return origin + heights[:, None, None] * axis + radii[:, None, None] * ring[None]  # [R+1,C,3]

    def _canonical_layout(self, body: BodyModel, top: float, bottom_joints: tuple[int, ...], bottom_offset: float,
                          margin: float) -> torch.Tensor:
        verts = body.canonical_vertices().detach().float().cpu()  # [V,3]
        J = body.joints(body.canonical_pose()[None])[0].detach().float().cpu()  # [24,3]
        origin, axis = J[0], F.normalize(J[12] - J[0], dim=0)
        bottom = float(((J[list(bottom_joints)] - origin) @ axis).mean()) + bottom_offset
        if not bottom < top:
            raise ValueError(f"sheet: the bottom ({bottom:.3f} m along the body axis) must lie below the top ({top:.3f})")
        rel = verts - origin
        h_v = rel @ axis
        r_v = (rel - h_v[:, None] * axis).norm(dim=-1)
        heights = torch.linspace(top, bottom, self.rows + 1)
        band = max(abs(top - bottom) / self.rows, 0.02)
        radii = []
        for h in heights:
            near = (h_v - h).abs() < band
            radii.append((float(torch.quantile(r_v[near], 0.98)) if near.any() else float(r_v.median())) + margin)
        self.layout = {"profile": "canonical", "bottom": bottom, "radii": [round(x, 4) for x in radii]}
        return self._rings(origin, axis, heights, torch.tensor(radii))

    def _rest_layout(self, body: BodyModel, views, top: float, margin: float, radius_from: str, voxel: float,
                     quantile: float) -> torch.Tensor:
        """The layout in the rest frame's posed space (see the class doc), and a first guess of its canonical
        vertices by inverse LBS with the nearest body vertex's weights (`canonicalise` refines it)."""
        import numpy as np
        from scipy.spatial import cKDTree

        from realityavatar.model.hull import body_and_hull, cylindrical, sector_radius, to_canonical

        with torch.no_grad():
            pose, transl = views.pose.float(), views.transl.float()
            verts_np, surf = body_and_hull(body, views, voxel, what="sheet.profile=rest")
            J = body.joints(pose, transl).cpu().double()
            origin, axis = J[0], F.normalize(J[12] - J[0], dim=0)

            def radius(pts_c, hj: float, band: float) -> float:
                return sector_radius(pts_c, hj, band, quantile)

            hull_c = cylindrical(surf, origin, axis)
            # the hem: where the hull's radius steps in most (garment -> legs), searched 0.15-1.0 m below the top
            fine = np.arange(top - 0.15, top - 1.0, -voxel)
            prof = np.array([radius(hull_c, x, voxel) for x in fine])
            k = 3  # radii compared 3 voxels apart
            if len(prof) <= k or prof.max() <= 0:
                raise ValueError(f"sheet.profile=rest: frame {views.frame}'s hull has no garment below the top ring")
            bottom = float(fine[int(np.argmax(prof[:-k] - prof[k:]))])
            heights = torch.linspace(top, bottom, self.rows + 1, dtype=torch.float64)
            band = max(abs(top - bottom) / self.rows, voxel, 0.03)
            shape_c = hull_c if radius_from == "hull" else cylindrical(verts_np, origin, axis)
            radii = torch.tensor([radius(shape_c, float(hj), band) + margin for hj in heights], dtype=torch.float64)
            posed = self._rings(origin, axis, heights, radii).reshape(-1, 3).float()
            canon = to_canonical(body, views, posed, cKDTree(verts_np).query(posed.numpy())[1])
            self.posed_rest = posed
            self.rest_pose, self.rest_transl = pose.detach().clone(), transl.detach().clone()
            self.canonical_done = torch.tensor(False)
            self.layout = {"profile": "rest", "frame": int(views.frame), "bottom": bottom,
                           "radius_from": radius_from, "radii": [round(float(x), 4) for x in radii]}
            return canon.reshape(self.rows + 1, self.cols, 3)

    @torch.no_grad()
    def canonicalise(self, body: BodyModel, skinning: nn.Module, iterations: int = 60) -> dict | None:
        """profile=rest: canonical vertices x_c with LBS(x_c; skinning(x_c)) = the rest-frame layout, by the
        damped fixed point x_c <- (x_c + T(x_c)^-1 x_posed) / 2. Once per run (a checkpoint carries the result). Returns a record."""
        if bool(self.canonical_done) or self.posed_rest.shape[0] == 0:
            return None
        A = body.canonical_transforms(self.rest_pose.to(self.vertices), self.rest_transl.to(self.vertices))  # [24,4,4]
        target = self.posed_rest.to(self.vertices)
        x = self.vertices.clone()
        ones = torch.ones(len(x), 1, dtype=x.dtype, device=x.device)
        for _ in range(iterations):
            w = skinning(x[None])[0]  # [P,24]
            T = torch.einsum("pj,jab->pab", w, A)
            # damped: between the legs the blended weights change fast and the plain iteration can cycle
            x = x + 0.5 * ((torch.linalg.inv(T) @ torch.cat([target, ones], -1)[..., None])[:, :3, 0] - x)
        w = skinning(x[None])[0]
        T = torch.einsum("pj,jab->pab", w, A)
        resid = ((T @ torch.cat([x, ones], -1)[..., None])[:, :3, 0] - target).norm(dim=-1)
        self.vertices.copy_(x)
        self.canonical_done.fill_(True)
        return {"iterations": iterations, "residual_max_m": float(resid.max()), "residual_median_m": float(resid.median())}

    @property
    def num_points(self) -> int:
        return int(self.corners.shape[0])

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Optimizer groups: sheet_<name>, whose rates default to the free Gaussians' of the same name (module;
        the motion basis and its coefficients the decoder's)."""
        groups = {"sheet_features": [self.features], "sheet_opacity_logits": [self.opacity_logits],
                  "sheet_log_scales": [self.log_scales], "sheet_normal_offset": [self.normal_offset]}
        if self.num_basis:
            groups.update(sheet_basis=[self.basis], sheet_coeff=list(self.coeff.parameters()))
        return groups

    # ------------------------------------------------------------------ the source interface (model/avatar.py)
    def points(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The decoder moves the sheet's vertices [P,3] (zero log-scales, identity quaternions: placeholders that
        `splats` replaces)."""
        V = self.vertices
        return V, V.new_zeros(V.shape), F.pad(V.new_ones(len(V), 1), (0, 3))

    def move(self, dx: torch.Tensor, h_t: torch.Tensor) -> torch.Tensor:
        """The decoder's offsets of the vertices [B,P,3], plus the motion basis's (sheet.basis > 0)."""
        return dx + self.basis_offsets(h_t) if self.num_basis else dx

    def splats(self, posed: dict, inputs: dict) -> dict:
        """The posed vertices (entries [B,P,...]) -> the sheet's Gaussians [B,M,...], which follow their cells: position,
        tangent frame and stretch from the posed vertices (`place`), the canonical-to-posed rotation of the cell's
        first corner, the rest interpolated bilinearly. sheet_verts: the posed vertices (the strain term's input)."""
        placed = self.place(posed["means"])
        return {"means": placed["means"], "quats": placed["quats"], "scales": placed["scales"],
                "rot": posed["rot"][:, self.corners[:, 0]], "f_mt": self.interpolate(posed["f_mt"]),
                "weights": self.interpolate(posed["weights"]), "x_e": self.interpolate(posed["x_e"]),
                "sheet_verts": posed["means"]}

    def canonical(self) -> dict:
        """The sheet's Gaussians placed on its canonical vertices."""
        placed = self.place(self.vertices[None])
        return {"means": placed["means"][0], "quats": placed["quats"][0], "scales": placed["scales"][0],
                "opacities": self.opacities()}

    def basis_offsets(self, h_t: torch.Tensor) -> torch.Tensor:
        """Temporal state [B,H] -> canonical offsets of the vertices [B,P,3]: sum_k c_k(h_t) B_k. One coefficient
        vector moves every vertex, so a frame's gradient shapes the whole garment's motion (a low-rank cloth model,
        as a PCA of simulated cloth), and each basis shape is free per vertex, unlike the decoder's smooth field."""
        c = self.coeff(h_t)  # [B,K]
        return torch.einsum("bk,kpd->bpd", c, self.basis.to(c))

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def colour_features(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """The colour features every frame renders with [M,F] (SlidingSheet's depend on the frame)."""
        return self.features

    def loss_terms(self) -> dict:
        """Loss terms the sheet brings to training (build_avatar adds them to the configured ones): none."""
        return {}

    def interpolate(self, values: torch.Tensor) -> torch.Tensor:
        """Per-vertex values [B,P,D] -> each Gaussian's bilinear blend of its cell's corners [B,M,D]."""
        c = values[:, self.corners]  # [B,M,4,D]
        a, b = self.ab[:, 0:1].to(values), self.ab[:, 1:2].to(values)
        w = torch.cat([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], dim=-1)  # [M,4]
        return (c * w[None, :, :, None]).sum(2)

    def _cell_frame(self, verts: torch.Tensor):
        """Each Gaussian's tangent frame at its place in its cell (e1 along the ring, e2 down the sheet, e3 the
        normal, each [B,M,3]) and the cell's extent along e1 and e2 there [B,M,1]."""
        c = verts[:, self.corners]  # [B,M,4,3]
        a, b = self.ab[:, 0, None].to(verts), self.ab[:, 1, None].to(verts)
        t_u = (1 - b) * (c[:, :, 1] - c[:, :, 0]) + b * (c[:, :, 3] - c[:, :, 2])
        t_v = (1 - a) * (c[:, :, 2] - c[:, :, 0]) + a * (c[:, :, 3] - c[:, :, 1])
        u_len = t_u.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        e1 = t_u / u_len
        v_perp = t_v - (t_v * e1).sum(-1, keepdim=True) * e1
        v_len = v_perp.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        e2 = v_perp / v_len
        return e1, e2, torch.linalg.cross(e1, e2, dim=-1), u_len, v_len

    def _reference_layout(self) -> torch.Tensor:
        """The layout stretch is measured against [P,3]: the rest frame's (profile=rest), else the canonical one."""
        return self.posed_rest if self.posed_rest.shape[0] == self.vertices.shape[0] else self.vertices

    @torch.no_grad()
    def reference_cells(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each Gaussian's cell extent along the ring and down the sheet [1,M,1] in the layout the stretch cap is
        measured against: the rest frame's layout (profile=rest), else the canonical one. Not the canonical cells
        of a rest layout: canonicalised into the star pose, the cells between the legs span up to 37 cm, and a cap
        of 16x that bound nothing under poses that spread the legs further (docs/research/2026-11-23-stability-reports.md)."""
        return self._cell_frame(self._reference_layout()[None])[3:]

    def _column_edges(self, verts: torch.Tensor) -> torch.Tensor:
        """Lengths of the edges down the sheet (ring j to ring j + 1, every column) [B,rows,cols]."""
        G = verts.reshape(verts.shape[0], self.rows + 1, self.cols, 3)
        return (G[:, 1:] - G[:, :-1]).norm(dim=-1)

    def strain(self, verts: torch.Tensor) -> torch.Tensor:
        """Stretch down the garment beyond what cloth allows: the mean over the edges down the sheet of
        max(0, length / reference length - 1 - strain_free)^2, the reference being the rest layout's (else the
        canonical) edge. Posed vertices [B,P,3] -> a scalar. Cloth barely stretches along its length (the simulated
        skirt's edges at most 1.08x), while without this term the trained sheet stretched its columns 2.1x (median)
        at peak flare and hung its hem below the cloth's (docs/research/2026-11-24-garment-sheet.md). Around the rings the sheet is free:
        it starts around the legs, inside the garment, and must widen to follow a flare."""
        with torch.no_grad():
            L0 = self._column_edges(self._reference_layout()[None].to(verts)).clamp_min(1e-6)
        excess = (self._column_edges(verts) / L0 - 1.0 - self.strain_free).clamp_min(0.0)
        return (excess * excess).mean()

    def place(self, verts: torch.Tensor) -> dict[str, torch.Tensor]:
        """Vertex positions [B,P,3] -> the Gaussians' means [B,M,3], quats [B,M,4] (the cell's tangent frame) and
        scales [B,M,3] (stretched with the cell, at most `max_stretch` times the reference cell's, see
        `reference_cells`: a cell torn open by a pose the garment cannot follow, legs spread far apart, leaves a gap
        instead of a half-metre-long smear)."""
        e1, e2, e3, u_len, v_len = self._cell_frame(verts)
        R = torch.stack([e1, e2, e3], dim=-1)  # [B,M,3,3], columns = the frame
        means = self.interpolate(verts) + self.normal_offset[None, :, None] * e3
        if self.max_stretch > 0:
            cu, cv = (c.to(verts) for c in self.reference_cells())
            u_len = torch.minimum(u_len, self.max_stretch * cu)
            v_len = torch.minimum(v_len, self.max_stretch * cv)
        s = self.log_scales.exp()
        scales = torch.cat([s[None, :, 0:1] * u_len, s[None, :, 1:2] * v_len, s[None, :, 2:3].expand_as(u_len)], -1)
        return {"means": means, "quats": matrix_to_quat(R), "scales": scales}

    def extra_repr(self) -> str:
        return f"rows={self.rows}, cols={self.cols}, per_cell={self.per_cell}, gaussians={self.num_points}"


class NoSheet(Stateless, nn.Module):
    """No garment sheet (`sheet=none`, the default): a source with no points and no Gaussians."""

    num_points = 0
    num_basis = 0
    layout: dict = {}  # noqa: RUF012  (read-only: nothing laid out)

    def __init__(self, body: BodyModel | None = None, feature_dim: int = 0, **unused) -> None:
        super().__init__()
        self.feature_dim = int(feature_dim)
        self.register_buffer("features", torch.zeros(0, self.feature_dim), persistent=False)
        # empty points, made once (not per step)
        self.register_buffer("_empty3", torch.zeros(0, 3), persistent=False)
        self.register_buffer("_empty4", torch.zeros(0, 4), persistent=False)
        self.register_buffer("_empty", torch.zeros(0), persistent=False)

    def points(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self._empty3, self._empty3, self._empty4

    def move(self, dx: torch.Tensor, h_t: torch.Tensor) -> torch.Tensor:
        return dx

    def splats(self, posed: dict, inputs: dict) -> dict:
        return posed

    def opacities(self) -> torch.Tensor:
        return self._empty

    def colour_features(self, frame_idx: torch.Tensor) -> torch.Tensor:
        return self.features

    def loss_terms(self) -> dict:
        return {}

    def canonical(self) -> dict:
        return {"means": self._empty3, "quats": self._empty4, "scales": self._empty3, "opacities": self._empty}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {}

    def canonicalise(self, body: BodyModel, skinning: nn.Module) -> None:
        return None


class SlidingSheet(GarmentSheet):
    """`sheet=skirt_slide` (the demo's): the garment sheet whose texture slides around its rings, per training frame.

    A loose skirt turns about the body in the pelvis's frame: the demo's hem lags the spin by up to 13 degrees and
    swings after the stop, while the decoder's sheet stays locked to the pelvis, so each sheet Gaussian sees other
    material in every frame and learns their average (docs/research/2026-11-29-garment-twist-and-views.md). Here
    every training frame f has an angle per ring, slide[f, j] (radians, zero at the start): a Gaussian of row j
    renders the colour feature of the material that far back around its ring (linear interpolation between its
    row's columns), while its geometry, the decoder's offsets and the skinning stay the plain sheet's. The angles are
    learnt from the images, with a smoothness over frames and rings (losses.SheetSlideSmooth, which the sheet brings
    to training), and held at zero in the frames where the body's root did not turn within the pose window (`live`,
    from the training poses: the cloth at rest, where a free slide would fit the four cameras one by one; and the
    gauge, without which a slide common to all frames is a turn of the texture). Frames that are not training frames
    (novel poses, animation) render unslid. Measured on the demo, 3 seeds: +0.62 dB garment PSNR in the held-out
    spin (box +0.36), the other phases and novel poses within the seed spread
    (docs/research/2026-11-29-garment-motion-and-flow.md).
    Sliding the geometry instead (turning the rings) gained less in the spin and cost 0.2 dB at rest. per_cell = 1.
    """

    def __init__(self, body: BodyModel, still_deg: float, smoothness: float, data=None, **kw) -> None:
        super().__init__(body, data=data, **kw)
        if self.per_cell != 1:
            raise ValueError(f"sheet.per_cell: the sliding sheet needs one Gaussian per cell, got {self.per_cell}")
        if still_deg < 0 or smoothness <= 0:
            raise ValueError(f"sheet: expected still_deg >= 0 and smoothness > 0, got {still_deg}, {smoothness}")
        self.smoothness = float(smoothness)
        live = moving_frames(data, float(still_deg)) if data is not None else torch.zeros(0)
        self.register_buffer("live", live)  # [F] 1: the root turned within the frame's window
        self.slide = nn.Parameter(torch.zeros(len(live), self.rows + 1))

    SIZED_BY_DATA = (*GarmentSheet.SIZED_BY_DATA, "live", "slide")  # the frame count, from a checkpoint

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {**super().param_groups(), "sheet_slide": [self.slide]}

    def loss_terms(self) -> dict:
        from realityavatar.losses import SheetSlideSmooth

        return {"sheet_slide": SheetSlideSmooth(self.smoothness)}

    def angles(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """Each sample's slide per ring [B,rows+1]: zero for a frame not trained on (-1) or not `live`."""
        if len(self.live) == 0:
            raise ValueError("sheet=skirt_slide: no training frames to slide (built without the training data and no "
                             "checkpoint loaded)")
        k = frame_idx.long().to(self.slide.device).clamp(0, len(self.live) - 1)
        keep = (frame_idx.to(k.device) >= 0).to(self.slide.dtype) * self.live[k]
        return self.slide[k] * keep[:, None]

    def colour_features(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """[B,M,F]: each row's features read `angles` back around the ring (a slide of one column's width reads the
        previous column's)."""
        theta = self.angles(frame_idx)
        shift = 0.5 * (theta[:, :-1] + theta[:, 1:]) * (self.cols / (2 * math.pi))  # [B,rows] in columns
        B, F_ = theta.shape[0], self.feature_dim
        G = self.features.reshape(1, self.rows, self.cols, F_).expand(B, -1, -1, -1)
        p = torch.arange(self.cols, device=theta.device, dtype=theta.dtype) - shift[..., None]  # [B,rows,cols]
        lo = torch.floor(p)
        w = (p - lo)[..., None]
        i0 = lo.long() % self.cols
        g0 = G.gather(2, i0[..., None].expand(-1, -1, -1, F_))
        g1 = G.gather(2, ((i0 + 1) % self.cols)[..., None].expand(-1, -1, -1, F_))
        return ((1 - w) * g0 + w * g1).reshape(B, -1, F_)


@torch.no_grad()
def moving_frames(data, still_deg: float) -> torch.Tensor:
    """Per training frame (in the order of the frame indices): 1 where the root turned by more than `still_deg`
    between two consecutive entries of the frame's pose window, else 0 [F]."""
    from realityavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle

    ds = data.datasets.get("train")
    if ds is None:
        raise ValueError("sheet=skirt_slide: the DataModule has no training split to read the poses of")
    order = sorted(ds.train_frame_index.items(), key=lambda kv: kv[1])
    live = torch.zeros(len(order))
    still = math.radians(still_deg)
    for frame, k in order:
        poses, _ = ds.poses.window(frame, ds.window_len, ds.window_step)  # [T,24,3]
        R = axis_angle_to_matrix(poses[:, 0].double())  # the root's orientation per window entry
        turn = matrix_to_axis_angle(R[:-1].transpose(-1, -2) @ R[1:]).norm(dim=-1)  # [T-1] radians
        live[k] = float(bool((turn > still).any()))
    return live
