"""The avatar's forward pass, the one path that training, evaluation, export, the viewer and the benchmarks call:

    sources (canonical Gaussians, garment sheet) -> pose encoder -> temporal -> motion-trend decoder -> skinning (LBS)
    -> colour (x world-fixed light) -> splats

A *source* is a set of canonical points that the decoder and skinning move, and the Gaussians they become once posed
(model/gaussians.py CanonicalGaussians: each point is a Gaussian; model/sheet.py GarmentSheet: the points are a
garment surface's vertices and its Gaussians follow their cells; NoSheet: no points). Every source answers:

    points()             canonical means [P,3], log-scales [P,3], quaternions [P,4] of the points the decoder moves
    move(dx, h_t)        the decoder's offsets of its points [B,P,3], plus the source's own (the sheet's motion basis)
    splats(posed)        its posed points (means, quats, scales, rot, f_mt, weights, x_e: [B,P,...]) -> its Gaussians
    opacities()          [M] opacities of its Gaussians
    features             [M,F] colour features of its Gaussians
    colour_features(i)   the features a training frame's samples (indices i [B], -1: not a training frame) render
                         with: `features`, or [B,M,F] for a sheet whose texture slides per frame (SlidingSheet)
    canonical()          its Gaussians in canonical space: means, quats, scales [M,...], opacities [M]
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.body.base import BodyModel
from realityavatar.geometry import camera_centres
from realityavatar.model.deform import apply_deformation
from realityavatar.model.encoders import pose_features
from realityavatar.model.skinning import lbs_gaussians
from realityavatar.render import rasterize
from realityavatar.runtime import constant

# Per-point entries of a posed dict, split between the sources and joined again in source order.
PER_POINT = ("means", "quats", "scales", "rot", "f_mt", "weights", "x_e")
POSE_INPUTS = ("pose_features", "bone_transforms")  # pose_inputs' keys: what deform reads of a batch
FRAME_INPUTS = ("frame", "frame_idx")  # and, where a batch has them, its frames (sheet=physics: the cloth's frame)
# The view directions `Avatar.baked` averages a Gaussian's colour over.
AXES = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))


@torch.no_grad()
def pose_inputs(body: BodyModel, poses: torch.Tensor, transl: torch.Tensor) -> dict[str, torch.Tensor]:
    """The part of the forward pass that depends on the poses alone (no parameters, no gradient), from a pose window
    poses [B,T,24,3], transl [B,T,3]: `pose_features` [B,T,D] (the encoder's input) and `bone_transforms`
    [B,24,4,4] (the body's canonical-to-posed transforms of the current, last frame). The dataset computes them for
    every sample (on the host, in the loader's workers), so a training step on a GPU launches none of the ~110
    operations they take; `Avatar.pose_inputs` computes them for poses from anywhere else (animation, export)."""
    return {"pose_features": pose_features(poses, transl),  # POSE_INPUTS
            "bone_transforms": body.canonical_transforms(poses[:, -1], transl[:, -1])}


def join(parts: list[torch.Tensor], dim: int = 0) -> torch.Tensor:
    """Concatenate the non-empty parts along `dim` (one part: itself, no copy)."""
    parts = [p for p in parts if p.shape[dim]]
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim)


def cut(x: torch.Tensor, sizes: list[int], dim: int) -> list[torch.Tensor]:
    """`join`'s inverse: x split into parts of `sizes` along `dim`. With one non-empty part it is x itself and the
    others are empty views, so the backward has no split to undo (a split's backward fills the empty parts' gradients
    with zeros and concatenates: a dozen operations per step with sheet=none)."""
    if sum(1 for n in sizes if n) != 1:
        return list(x.split(sizes, dim))
    return [x if n else x.narrow(dim, 0, 0) for n in sizes]


@dataclass
class Schedule:
    """The step-dependent switches of the model (the loss terms carry their own, e.g. loss.skinning.switch)."""

    deform_start: int
    skin_pretrain_steps: int  # skinning=mlp: fit the field to the body's weights before the first step
    deform_anneal: int  # the decoder's frequency bands open linearly over steps deform_start .. + this (0: all)

    @classmethod
    def from_config(cls, schedule: dict) -> Schedule:
        """The config's schedule block (other keys there, e.g. skin_switch, reach loss terms by interpolation); a
        missing key is an error naming it."""
        missing = [f.name for f in fields(cls) if f.name not in schedule]
        if missing:
            raise KeyError(f"schedule: missing {', '.join(missing)} (conf/train.yaml's schedule block)")
        return cls(**{f.name: schedule[f.name] for f in fields(cls)})

    def deform_on(self, step: int) -> bool:
        return step >= self.deform_start

    def deform_window(self, step: int | None) -> float:
        """How far the decoder's coarse-to-fine window is open at `step` (None: a finished run): 0 .. 1."""
        if step is None or self.deform_anneal <= 0:
            return 1.0
        return min(1.0, max(0.0, (step - self.deform_start) / self.deform_anneal))


class Avatar(nn.Module):
    """Canonical Gaussians (+ garment sheet) -> pose encoder -> temporal -> motion-trend decoder -> skinning -> colour.

    Holds the model's components; AvatarModule (model/module.py) adds training and evaluation around it.
    """

    def __init__(self, body: BodyModel, gaussians: nn.Module, encoder: nn.Module, temporal: nn.Module,
                 deformer: nn.Module, skinning: nn.Module, color: nn.Module, shading: nn.Module, sheet: nn.Module,
                 render: dict) -> None:
        super().__init__()
        self.body = body
        self.gaussians = gaussians
        self.encoder = encoder
        self.temporal = temporal
        self.deformer = deformer
        self.skinning = skinning
        self.color = color
        self.shading = shading
        self.sheet = sheet  # sheet=skirt: Gaussians bound to a deformable garment surface, after the free ones
        self.render_cfg = dict(render)
        self.background = list(self.render_cfg.pop("background", [0.0, 0.0, 0.0]))
        self.register_buffer("background_rgb", torch.tensor(self.background, dtype=torch.float32), persistent=False)
        # The decoder's normalisation box follows the initial canonical Gaussians (not those of its first forward at
        # deform_start, which have moved and been densified); a loaded checkpoint replaces it with the trained box.
        if not bool(deformer.bounds_fitted):
            deformer.fit_bounds(gaussians.means.detach())

    @property
    def sources(self) -> tuple[nn.Module, ...]:
        return (self.gaussians, self.sheet)

    def pose_inputs(self, poses: torch.Tensor, transl: torch.Tensor) -> dict[str, torch.Tensor]:
        """`pose_inputs` of a pose window poses [B,T,24,3], transl [B,T,3] with this avatar's body: deform's input."""
        return pose_inputs(self.body, poses, transl)

    def deform(self, inputs: dict, deform: bool = True) -> dict:
        """The posed Gaussians of the current (last) frame of every source, from `pose_inputs` (a batch has them:
        the dataset computes them; other poses: `self.deform(self.pose_inputs(poses, transl))`).
        Geometry does not depend on the frame index (only the colour's per-frame latent does, see `shade`).
        deform=False: the canonical warm-up before schedule.deform_start (decoder skipped, identity offsets).

        Returns dict: means [B,N,3], quats [B,N,4], scales [B,N,3], opacities [N], rot [B,N,3,3] (canonical-to-posed
        rotation per Gaussian, for canonical view directions), f_mt [B,N,F], weights [B,N,24], x_e [B,N,3], B.
        """
        features, A = inputs["pose_features"], inputs["bone_transforms"]  # [B,T,D], [B,24,4,4]
        B = features.shape[0]
        h_t = self.temporal(self.encoder(features))  # [B,H]
        # every source's points ride through one decoder, skinning and LBS pass
        points = [s.points() for s in self.sources]
        sizes = [p[0].shape[0] for p in points]
        means, log_scales, quats = (join([p[i] for p in points]) for i in range(3))
        if deform:
            out = self.deformer(means, h_t)
            out["dx"] = join([s.move(dx, h_t) for s, dx in zip(self.sources, cut(out["dx"], sizes, 1))], 1)
        else:
            out = identity_deformation(B, means, self.deformer.feature_dim)
        x_e, log_s_e, q_e = apply_deformation(means, log_scales, quats, out)  # [B,N,3],[B,N,3],[B,N,4]
        w = self.skinning(self.skinning.query(means, x_e))  # [B,N,24] at x_e or x_c (skinning.query)
        means_o, quats_o, rot = lbs_gaussians(x_e, q_e, w, A)
        posed = {"means": means_o, "quats": quats_o, "scales": torch.exp(log_s_e), "rot": rot, "f_mt": out["f_mt"],
                 "weights": w, "x_e": x_e}
        chunks = {k: cut(v, sizes, 1) for k, v in posed.items()}
        per_source = [s.splats({k: c[i] for k, c in chunks.items()}, inputs) for i, s in enumerate(self.sources)]
        posed = {k: v for part in per_source for k, v in part.items() if k not in PER_POINT}  # e.g. sheet_verts
        for k in PER_POINT:
            first = per_source[0][k]
            posed[k] = join([first] + [part[k].to(first) for part in per_source[1:]], 1)
        posed["opacities"] = self.opacities()
        posed["B"] = B
        return posed

    def opacities(self) -> torch.Tensor:
        """[N] opacities of every rendered Gaussian: the free ones, then the garment sheet's."""
        first = self.gaussians.opacities()
        return join([first] + [s.opacities().to(first) for s in self.sources[1:]])

    def all_features(self) -> torch.Tensor:
        """Colour features of every rendered Gaussian: the free ones, then the garment sheet's [N(+M),F]."""
        first = self.gaussians.features
        return join([first] + [s.features.to(first) for s in self.sources[1:]])

    def frame_features(self, frame_idx: torch.Tensor) -> torch.Tensor:
        """`all_features` as the samples of training frames `frame_idx` [B] render them: [N(+M),F], or [B,N+M,F] when
        the sheet's features depend on the frame (SlidingSheet)."""
        free, sheet = self.gaussians.features, self.sheet.colour_features(frame_idx)
        if sheet.ndim == 2:
            return join([free, sheet.to(free)])
        return torch.cat([free[None].expand(sheet.shape[0], -1, -1), sheet.to(free)], 1)

    def canonical_gaussians(self) -> dict:
        """Every rendered Gaussian in canonical space (the free ones, then the sheet's placed on its canonical
        vertices): means [N,3], quats [N,4], scales [N,3], opacities [N]."""
        parts = [s.canonical() for s in self.sources]
        return {k: join([parts[0][k]] + [p[k].to(parts[0][k]) for p in parts[1:]]) for k in parts[0]}

    def shade(self, posed: dict, viewmats: torch.Tensor, frame_idx: torch.Tensor) -> torch.Tensor:
        """View-dependent colour of every Gaussian for each sample's camera: [B,N,3]."""
        cam_centre = camera_centres(viewmats)  # [B,3]
        # The Gaussians the colour model colours: all but the last `lit_points` (sheet=physics colours its own).
        n = posed["means"].shape[1] - self.sheet.lit_points
        # The camera-to-Gaussian vector, canonicalised (each Gaussian's blended skinning rotation undone); the colour
        # model's SH basis normalises it (normalising before a rotation as well would only add operations).
        rot, x_e = posed["rot"][:, :n], posed["x_e"][:, :n]
        d_c = (rot.transpose(-1, -2) @ (posed["means"][:, :n] - cam_centre[:, None, :])[..., None]).squeeze(-1)
        rgb = self.color(self.frame_features(frame_idx), d_c, posed["f_mt"][:, :n], frame_idx)
        rgb = self.shading.apply(rgb, x_e, rot)  # x world-fixed light (shading=none: as it is)
        return join([rgb, self.sheet.lit(posed, cam_centre).to(rgb)], 1)

    def splat(self, posed: dict, b: int, rgb: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, W: int, H: int,
              check_finite: bool = True):
        """Rasterize sample b of `posed` from C cameras (viewmat [C,4,4], K [C,3,3]; colours rgb [N,3] or [C,N,3])
        over the run's background: one rasterizer call. check_finite: name a non-finite input (reads the device)."""
        bg = self.background_rgb.to(rgb)[None].expand(viewmat.shape[0], -1)
        return rasterize(posed["means"][b], posed["quats"][b], posed["scales"][b], posed["opacities"], rgb,
                         viewmat, K, W, H, backgrounds=bg, check_finite=check_finite, **self.render_cfg)

    def render_batch(self, batch: dict, deform: bool = True, check_finite: bool = True, supersample: int = 1):
        """Render every sample of a batch from its own camera. Returns rgb [B,H,W,3], alpha [B,H,W,1], metas, posed.
        check_finite: the rasterizer's input checks (they read the device).
        supersample k (evaluation, eval.supersample): each image rendered at k times its width and height and averaged
        over k x k pixels, for a model evaluated below the resolution it was trained at. Rendered there directly, its
        sub-pixel Gaussians are widened by the rasterizer's 2D filter (eps2d, 0.3 px^2): a 256 px model lost 2.6 dB at
        128 px and 7.2 dB at 64 px (docs/gpu.md)."""
        viewmats, Ks = batch["viewmat"], batch["K"]
        W, H = int(batch["width"][0]), int(batch["height"][0])  # host ints in training (on_before_batch_transfer)
        if supersample > 1:  # pixel centres at +0.5: f and c scale with the image
            Ks = Ks * constant((supersample, supersample, 1.0), Ks)[:, None]
            W, H = W * supersample, H * supersample
        V = batch.get("views_per_frame", 1)  # data.views_per_step: V cameras of each frame, one pass of the networks
        inputs = {k: batch[k][::V] for k in (*POSE_INPUTS, *FRAME_INPUTS) if k in batch}
        posed = views_of(self.deform(inputs, deform=deform), V)
        rgb = self.shade(posed, viewmats, batch["frame_idx"])  # [B,N,3]
        images, alphas, metas = [], [], []
        for b in range(0, posed["B"], V):  # one rasterizer call per frame, for its V cameras
            img, alpha, meta = self.splat(posed, b, rgb[b : b + V], viewmats[b : b + V], Ks[b : b + V], W, H,
                                          check_finite)
            images.append(img)
            alphas.append(alpha)
            metas.append(meta)
        image, alpha = torch.cat(images), torch.cat(alphas)
        if supersample > 1:
            image, alpha = (F.avg_pool2d(x.permute(0, 3, 1, 2), supersample).permute(0, 2, 3, 1)
                            for x in (image, alpha))
        return image, alpha, metas, posed

    def posed(self, poses: torch.Tensor, transl: torch.Tensor, frame: int | None = None) -> dict:
        """`deform` of one pose window poses [T,24,3], transl [T,3] from anywhere (moved to the avatar's device and
        dtype): the posed Gaussians of its last frame, B=1. frame: that frame's id in the motion the garment was
        driven on (sheet=physics: `drive`; the others ignore it)."""
        dev, dt = self.gaussians.means.device, self.gaussians.means.dtype
        inputs = self.pose_inputs(poses[None].to(dev, dt), transl[None].to(dev, dt))
        if frame is not None:
            inputs["frame"] = torch.tensor([int(frame)], device=dev)
        return self.deform(inputs)

    def drive(self, table) -> dict:
        """Simulate a garment that has state (sheet=physics) on the motion of a PoseTable before its frames are
        rendered with `posed(..., frame=f)`; the other garments need nothing. Returns the garment's record (frames
        simulated, `inside`: frames with cloth inside the body)."""
        return self.sheet.drive(self.body, table)

    @torch.no_grad()
    def render_view(self, posed: dict, viewmat: torch.Tensor, K: torch.Tensor, W: int, H: int) -> torch.Tensor:
        """Sample 0 of `posed` seen by one camera viewmat [4,4], K [3,3] (moved to the avatar's device and dtype)
        without a training frame's colour latent (frame -1): an animation frame [H,W,3]."""
        dev, dt = self.gaussians.means.device, self.gaussians.means.dtype
        vm = viewmat[None].to(dev, dt)
        rgb = self.shade(posed, vm, torch.full((1,), -1, dtype=torch.long, device=dev))[0]
        return self.splat(posed, 0, rgb, vm, K[None].to(dev, dt), W, H)[0][0]

    @torch.no_grad()
    def baked(self, poses: torch.Tensor | None = None, transl: torch.Tensor | None = None,
              frame: int | None = None) -> dict:
        """Every rendered Gaussian with its colour baked, as export writes it and the viewer streams it: canonical
        (poses None) or posed by one pose window poses [T,24,3], transl [T,3]. Returns means [N,3], quats [N,4] wxyz,
        scales [N,3] (linear), opacities [N], and either rgb [N,3] in [0,1] or sh [N,K,3].

        `shade`'s colour without a camera: averaged over the six axis-aligned view directions, then lit
        (shading=irradiance: the light of that pose; canonical: the rest orientation). The SH colour model in
        canonical space keeps its coefficients instead (lit, `shading.apply_sh`). frame: as `posed`'s."""
        dev, dt = self.gaussians.means.device, self.gaussians.means.dtype
        frame_idx = torch.full((1,), -1, dtype=torch.long, device=dev)
        feats = self.all_features()  # the free Gaussians, then a garment sheet's (sheet=skirt)
        if poses is None:
            out = self.canonical_gaussians()
            N = out["means"].shape[0]
            rot = torch.eye(3, device=dev, dtype=dt).expand(N, 3, 3)[None]
            f_mt = feats.new_zeros(1, N, self.deformer.feature_dim)  # canonical: no motion-trend feature
            x_e = out["means"][None]
        else:
            posed = self.posed(poses, transl, frame)
            out = {k: posed[k][0] for k in ("means", "quats", "scales")} | {"opacities": posed["opacities"]}
            rot, f_mt, x_e, N = posed["rot"], posed["f_mt"], posed["x_e"], posed["means"].shape[1]
        sh_coeffs = getattr(self.color, "sh_coefficients", None)
        if callable(sh_coeffs) and poses is None and not self.sheet.lit_points:
            out["sh"] = self.shading.apply_sh(sh_coeffs(feats), x_e)  # lit by the rest orientation's light
            return out
        N = N - self.sheet.lit_points  # the colour model's Gaussians (sheet=physics: its own colours follow)
        rot, f_mt, x_e = rot[:, :N], f_mt[:, :N], x_e[:, :N]
        # One direction at a time: a [6,N,hidden] batch is slower on the CPU at 35k Gaussians (cache), not faster.
        rgb = 0
        for d in torch.tensor(AXES, dtype=dt, device=dev):
            d_c = (rot.transpose(-1, -2) @ d[:, None]).squeeze(-1)  # canonical view direction per Gaussian [1,N,3]
            rgb = rgb + self.color(feats, F.normalize(d_c.expand(1, N, 3), dim=-1), f_mt, frame_idx)[0]
        out["rgb"] = self.shading.apply((rgb / len(AXES))[None], x_e, rot)[0].clamp(0, 1)  # x world-fixed light
        out["rgb"] = join([out["rgb"], self.sheet.baked_rgb().to(out["rgb"])])
        return out


    def num_parameters(self) -> int:
        """Learnable parameters of the avatar: Gaussians and every network (the body model has none); the encoder
        counts the entries it trains (its part split holds the input layer's off-block entries at zero)."""
        mine = {id(p) for p in self.encoder.parameters()}
        rest = sum(p.numel() for p in self.parameters() if p.requires_grad and id(p) not in mine)
        return int(rest + self.encoder.num_parameters())

def views_of(posed: dict, V: int) -> dict:
    """The posed Gaussians of F frames [F,...] -> those of their V cameras each [F*V,...] (views, no copy for F=1)."""
    if V == 1:
        return posed
    out = dict(posed, B=posed["B"] * V)
    for k in (*PER_POINT, "sheet_verts", "garment_normals"):
        if k in posed:
            x = posed[k]
            out[k] = x[:, None].expand(x.shape[0], V, *x.shape[1:]).reshape(x.shape[0] * V, *x.shape[1:])
    return out


def identity_deformation(B: int, means: torch.Tensor, feature_dim: int) -> dict:
    """Decoder output that leaves the canonical Gaussians unchanged: dx, ds [B,N,3], dq [B,N,4], f_mt [B,N,F]."""
    N = means.shape[0]
    zeros = means.new_zeros(B, N, 3)
    dq = means.new_zeros(B, N, 4)
    dq[..., 0] = 1.0
    return {"dx": zeros, "ds": zeros, "dq": dq, "f_mt": means.new_zeros(B, N, feature_dim)}
