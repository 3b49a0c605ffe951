"""The LightningModule: wires the built components along the data path, trains with density control, evaluates."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.body.base import BodyModel
from realityavatar.geometry import camera_centres, sample_surface
from realityavatar.model.deform import apply_deformation
from realityavatar.model.gaussians import CODE_NAME, PARAM_NAMES
from realityavatar.model.shading import NoShading, deformed_normals
from realityavatar.model.skinning import lbs_gaussians
from realityavatar.render import rasterize

# Per-Gaussian parameter groups; component groups use the component's name.
GAUSSIAN_GROUPS = PARAM_NAMES + (CODE_NAME,)
COMPONENTS = ("encoder", "temporal", "deformer", "skinning", "color", "shading")


@dataclass
class Schedule:
    """Every step-dependent switch of a run, in one place."""

    deform_start: int = 0
    skin_switch: int = 0  # the skinning-loss weight drops from loss.lambda_skin_start to lambda_skin_end here
    skin_pretrain_steps: int = 0  # fit the skinning field to the body's weights before the first step
    deform_anneal: int = 0  # the decoder's frequency bands open linearly over steps deform_start .. + this (0: all)

    def deform_on(self, step: int) -> bool:
        return step >= self.deform_start

    def deform_window(self, step: int) -> float:
        """How far the decoder's coarse-to-fine window is open at `step` (None: a finished run): 0 .. 1."""
        if step is None or self.deform_anneal <= 0:
            return 1.0
        return min(1.0, max(0.0, (step - self.deform_start) / self.deform_anneal))

    def skin_decayed(self, step: int) -> bool:
        return step >= self.skin_switch


class AvatarModule(pl.LightningModule):
    """Canonical Gaussians -> pose encoder -> temporal -> motion-trend decoder -> skinning -> colour -> splats."""

    def __init__(
        self,
        body: BodyModel,
        gaussians: nn.Module,
        encoder: nn.Module,
        temporal: nn.Module,
        deformer: nn.Module,
        skinning: nn.Module,
        color: nn.Module,
        density: Any,
        loss: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        lr: dict,
        final_factor: dict,
        render: dict,
        schedule: Schedule | dict | None = None,
        grad_clip: float | None = None,
        max_steps: int = 1000,
        scene_extent: float = 1.0,
        skin_samples: int = 1024,
        lpips: nn.Module | None = None,
        silhouette: nn.Module | None = None,
        shading: nn.Module | None = None,
        flow: nn.Module | None = None,
        sheet: nn.Module | None = None,
        posefit: nn.Module | None = None,
    ):
        super().__init__()
        self.automatic_optimization = False  # density control edits parameters between optimizer steps
        self.body = body
        self.gaussians = gaussians
        self.encoder = encoder
        self.temporal = temporal
        self.deformer = deformer
        self.skinning = skinning
        self.color = color
        self.shading = shading if shading is not None else NoShading()
        self.density = density
        self.loss_fn = loss
        self.silhouette = silhouette
        self.flow = flow if flow is not None and float(getattr(flow, "weight", 0.0)) > 0 else None
        self.sheet = sheet  # sheet=skirt: Gaussians bound to a deformable garment surface, after the free ones
        # posefit=silhouette: extra pose-path steps on other frames' silhouettes after each image step (model/posefit.py)
        self.posefit = posefit if posefit is not None and int(getattr(posefit, "passes", 0)) > 0 else None
        self.optimizer_factory = optimizer
        self.lr = dict(lr)
        self.final_factor = dict(final_factor)
        self.render_cfg = dict(render)
        self.background = list(self.render_cfg.pop("background", [0.0, 0.0, 0.0]))
        self.schedule = schedule if isinstance(schedule, Schedule) else Schedule(**(schedule or {}))
        self.grad_clip = grad_clip
        self.max_steps = max(int(max_steps), 1)
        self.scene_extent = float(scene_extent)
        self.skin_samples = int(skin_samples)
        self.lpips = lpips
        self.lpips_status = "computed" if lpips is not None else "not computed"  # build_module sets the reason
        self.test_records: list[dict] = []
        self._surface = None
        # Facts needed to rebuild the run from its checkpoint (num_train_frames, scene_extent, ...).
        self.run_info: dict = {"scene_extent": self.scene_extent}
        # Frozen networks from weight files (LPIPS, the perceptual loss's VGG19) stay out of the checkpoint, so a run
        # trained with or without them loads strictly into a module built with or without them.
        self._register_state_dict_hook(_drop_frozen_networks)
        self.register_load_state_dict_post_hook(_ignore_frozen_networks)
        # The decoder's normalisation box follows the initial canonical Gaussians (not those of its first forward at
        # deform_start, which have moved and been densified); a loaded checkpoint replaces it with the trained box.
        if hasattr(deformer, "fit_bounds") and not bool(getattr(deformer, "bounds_fitted", 1)):
            deformer.fit_bounds(gaussians.means.detach())
        codes_g, codes_d = int(getattr(gaussians, "deform_code_dim", 0)), int(getattr(deformer, "gaussian_code_dim", 0))
        if codes_g != codes_d:
            raise ValueError(f"gaussians.deform_code_dim ({codes_g}) and deformer.gaussian_code_dim ({codes_d}) must "
                             "agree: the decoder reads the Gaussians' codes")
        if getattr(gaussians, "normal_residual", False) and not hasattr(self.shading, "normals"):
            raise ValueError(f"gaussians.normal_residual=true: its residuals are added to the light's normal, which "
                             f"{type(self.shading).__name__} does not have; use shading=irradiance")
        if hasattr(deformer, "set_axis"):
            # offsets=cylindrical turn about the canonical body's vertical axis: through the pelvis, towards the neck
            # (a checkpoint's buffers replace it with the same values).
            J = body.joints(body.canonical_pose()[None])[0].detach()  # [24,3]
            deformer.set_axis(J[0], J[12] - J[0])

    def set_progress(self, step: int | None) -> None:
        """Put the step-dependent state of the networks where training step `step` has it (None: a finished run):
        the decoder's coarse-to-fine window (schedule.deform_anneal). Called every training step, and by `load_run`
        with the checkpoint's step, so a checkpoint saved mid-anneal renders as it trained."""
        if hasattr(self.deformer, "set_window"):
            self.deformer.set_window(self.schedule.deform_window(step))

    # ------------------------------------------------------------------ forward
    def deform(self, poses: torch.Tensor, transl: torch.Tensor, deform: bool = True,
               frame_idx: torch.Tensor | None = None):
        """poses [B,T,24,3], transl [B,T,3] -> posed Gaussians of the current (last) frame. Geometry does not depend
        on the frame index (only the colour's per-frame latent does, see `shade`) unless the decoder has per-frame
        codes (deformer.frame_code_dim > 0, a diagnostic): then frame_idx [B] picks them (None: the mean code).

        Returns dict: means [B,N,3], quats [B,N,4], scales [B,N,3], opacities [N], rot [B,N,3,3]
        (canonical-to-posed rotation per Gaussian, for canonical view directions) and the decoder output.
        """
        g = self.gaussians
        B = poses.shape[0]
        f_p = self.encoder(poses, transl)  # [B,T,D]
        h_t = self.temporal(f_p)  # [B,H]
        means, log_scales, quats, codes = g.means, g.log_scales, g.quats, getattr(g, "deform_codes", None)
        N = g.num_points
        if self.sheet is not None:
            # the sheet's vertices ride along the free Gaussians through one decoder, skinning and LBS pass
            V = self.sheet.vertices.to(means)
            means = torch.cat([means, V])
            log_scales = torch.cat([log_scales, V.new_zeros(V.shape)])
            quats = torch.cat([quats, F.pad(V.new_ones(len(V), 1), (0, 3))])
            codes = None if codes is None else torch.cat([codes, codes.new_zeros(len(V), codes.shape[1])])
        # Canonical warm-up: before deform_start the decoder is skipped and the offsets are the identity.
        # frame_idx and the Gaussians' codes reach the decoder's per-frame / per-Gaussian codes when it has them
        out = (self.deformer(means, h_t, frame_idx, codes=codes) if deform
               else identity_deformation(B, means, self.deformer.feature_dim))
        n_c = self._shading_normals(means, out, h_t, frame_idx, codes, deform)
        if self.sheet is not None and self.sheet.num_basis and deform:  # the sheet's motion basis (sheet.basis)
            out = {**out, "dx": torch.cat([out["dx"][:, :N], out["dx"][:, N:] + self.sheet.basis_offsets(h_t)], 1)}
        x_e, log_s_e, q_e = apply_deformation(means, log_scales, quats, out)  # [B,N,3],[B,N,3],[B,N,4]
        # skinning.query_at: the weights at the deformed canonical position (default) or at the undeformed one
        at_rest = getattr(self.skinning, "query_at", "deformed") == "canonical"
        w = self.skinning(means[None].expand(B, -1, -1) if at_rest else x_e)  # [B,N,24]
        A = self.body.canonical_transforms(poses[:, -1], transl[:, -1])  # [B,24,4,4]
        means_o, quats_o, rot = lbs_gaussians(x_e, q_e, w, A)
        posed = {
            "means": means_o,
            "quats": quats_o,
            "scales": torch.exp(log_s_e),
            "opacities": g.opacities(),
            "rot": rot,
            "f_mt": out.get("f_mt"),
            "weights": w,
            "x_e": x_e,
            "n_c": n_c,
            "B": B,
        }
        if self.sheet is not None:
            posed = self._sheet_gaussians(posed, N)
        return posed

    def deform_points(self, poses: torch.Tensor, transl: torch.Tensor, free_idx: torch.Tensor) -> torch.Tensor:
        """Posed centres [B,S(+P),3] of the free Gaussians free_idx [S], then the garment sheet's P vertices: the
        geometry path of `deform` (decoder offsets, the sheet's motion basis, skinning) without rotations, scales,
        shading or the sheet's Gaussians, for posefit=silhouette."""
        g = self.gaussians
        h_t = self.temporal(self.encoder(poses, transl))  # [B,H]
        means = g.means[free_idx]
        codes = getattr(g, "deform_codes", None)
        codes = None if codes is None else codes[free_idx]
        S = means.shape[0]
        if self.sheet is not None:
            V = self.sheet.vertices.to(means)
            means = torch.cat([means, V])
            codes = None if codes is None else torch.cat([codes, codes.new_zeros(len(V), codes.shape[1])])
        dx = self.deformer(means, h_t, None, codes=codes)["dx"]  # [B,S+P,3]
        if self.sheet is not None and self.sheet.num_basis:
            dx = torch.cat([dx[:, :S], dx[:, S:] + self.sheet.basis_offsets(h_t)], 1)
        x_e = means + dx
        at_rest = getattr(self.skinning, "query_at", "deformed") == "canonical"
        w = self.skinning(means[None].expand(x_e.shape[0], -1, -1) if at_rest else x_e)  # [B,S+P,24]
        A = self.body.canonical_transforms(poses[:, -1], transl[:, -1])  # [B,24,4,4]
        return self.body.lbs(x_e, w, A)

    def _shading_normals(self, means: torch.Tensor, out: dict, h_t: torch.Tensor, frame_idx: torch.Tensor | None,
                         codes: torch.Tensor | None, deform: bool) -> torch.Tensor | None:
        """shading.normals=jacobian: each point's canonical body normal carried through the decoder's offset field
        [B,N,3] (no gradient; model/shading.py `deformed_normals`), else None (the shading looks its normal up at
        x_e). A garment sheet's motion basis is not part of the field."""
        if getattr(self.shading, "normals_from", "body") != "jacobian":
            return None
        x_c = means.detach()
        n0 = self.shading.normals(x_c)  # [N,3]
        if not deform:
            return n0[None].expand(h_t.shape[0], -1, -1)
        rep = None if codes is None else codes.detach().repeat(3, 1)
        return deformed_normals(n0, x_c, out["dx"].detach(),
                                lambda x: self.deformer(x, h_t, frame_idx, codes=rep)["dx"], self.shading.jacobian_eps)

    def _sheet_gaussians(self, posed: dict, N: int) -> dict:
        """Replace the sheet's vertices (entries N: of the per-point outputs) by the sheet's Gaussians, which
        follow their cells (model/sheet.py): position, tangent frame and stretch from the posed vertices, the
        canonical-to-posed rotation of the cell's first corner, the rest interpolated bilinearly."""
        sh = self.sheet
        first = sh.corners[:, 0]
        posed["sheet_verts"] = posed["means"][:, N:]  # one row per distinct pose window (sheet.strain's input)
        placed = sh.place(posed["sheet_verts"])
        vert = {
            "means": placed["means"],
            "quats": placed["quats"],
            "scales": placed["scales"],
            "rot": posed["rot"][:, N:][:, first],
            "f_mt": None if posed["f_mt"] is None else sh.interpolate(posed["f_mt"][:, N:]),
            "weights": sh.interpolate(posed["weights"][:, N:]),
            "x_e": sh.interpolate(posed["x_e"][:, N:]),
            "n_c": None if posed["n_c"] is None else sh.interpolate(posed["n_c"][:, N:]),
        }
        for k, v in vert.items():
            if v is not None:
                posed[k] = torch.cat([posed[k][:, :N], v.to(posed[k])], dim=1)
        posed["opacities"] = torch.cat([posed["opacities"], sh.opacities().to(posed["opacities"])])
        return posed

    _PER_SAMPLE = ("means", "quats", "scales", "rot", "f_mt", "weights", "x_e", "n_c")

    def deform_shared(self, poses: torch.Tensor, transl: torch.Tensor, deform: bool = True,
                      frame_idx: torch.Tensor | None = None) -> dict:
        """`deform` once per distinct pose window of the batch, the result shared by every sample with that window
        (a data.sampler=frame_views batch is one frame from several cameras: one network pass, gradients summed)."""
        B = poses.shape[0]
        reps: list[int] = []  # the first sample of each distinct window
        use: list[int] = []  # which of reps each sample takes its deformation from
        for b in range(B):
            hit = next((j for j, r in enumerate(reps)
                        if torch.equal(poses[b], poses[r]) and torch.equal(transl[b], transl[r])), None)
            if hit is None:
                hit = len(reps)
                reps.append(b)
            use.append(hit)
        if len(reps) == B:
            return self.deform(poses, transl, deform=deform, frame_idx=frame_idx)
        sel = torch.tensor(reps, device=poses.device)
        posed = self.deform(poses[sel], transl[sel], deform=deform,
                            frame_idx=None if frame_idx is None else frame_idx[sel])
        inv = torch.tensor(use, device=poses.device)
        for k in self._PER_SAMPLE:
            if posed.get(k) is not None:
                posed[k] = posed[k].index_select(0, inv)
        posed["B"] = B
        return posed

    def shade(self, posed: dict, viewmats: torch.Tensor, frame_idx: torch.Tensor) -> torch.Tensor:
        """View-dependent colour of every Gaussian for each sample's camera: [B,N,3]."""
        cam_centre = camera_centres(viewmats)  # [B,3]
        d = F.normalize(posed["means"] - cam_centre[:, None, :], dim=-1)  # [B,N,3] posed view dir
        # Canonicalise: undo each Gaussian's blended skinning rotation.
        d_c = (posed["rot"].transpose(-1, -2) @ d[..., None]).squeeze(-1)
        rgb = self.color(self.all_features(), F.normalize(d_c, dim=-1), posed["f_mt"], frame_idx)
        residual = getattr(self.gaussians, "normal_residuals", None)
        if residual is not None and self.sheet is not None:  # the sheet's Gaussians have none
            residual = torch.cat([residual, residual.new_zeros(posed["x_e"].shape[1] - residual.shape[0], 3)])
        light = self.shading(posed["x_e"], posed["rot"], posed.get("n_c"), residual)  # world-fixed light, or None
        return rgb if light is None else rgb * light

    def all_features(self) -> torch.Tensor:
        """Colour features of every rendered Gaussian: the free ones, then the garment sheet's [N(+M),F]."""
        feats = self.gaussians.features
        return feats if self.sheet is None else torch.cat([feats, self.sheet.features.to(feats)])

    def canonical_gaussians(self) -> dict:
        """Every rendered Gaussian in canonical space (the free ones, then the sheet's placed on its canonical
        vertices): means [N,3], quats [N,4], scales [N,3], opacities [N]."""
        g = self.gaussians
        out = {"means": g.means, "quats": g.quats, "scales": torch.exp(g.log_scales),
               "opacities": g.opacities()}
        if self.sheet is not None:
            placed = self.sheet.place(self.sheet.vertices[None].to(g.means))
            out = {k: torch.cat([v, (placed[k][0] if k in placed else self.sheet.opacities()).to(v)])
                   for k, v in out.items()}
        return out

    def splat(self, posed: dict, b: int, rgb: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, W: int, H: int):
        """Rasterize sample b of `posed` with colours rgb [N,D] from one camera (viewmat [1,4,4], K [1,3,3]);
        D = 3 composites over the run's background, other values (render_batch's extra channels) over 0."""
        bg = torch.tensor(self.background, dtype=rgb.dtype, device=rgb.device)
        bg = (bg if rgb.shape[-1] == bg.shape[0] else bg.new_zeros(rgb.shape[-1]))[None]
        return rasterize(posed["means"][b], posed["quats"][b], posed["scales"][b], posed["opacities"], rgb,
                         viewmat, K, W, H, backgrounds=bg, **self.render_cfg)

    def render_batch(self, batch: dict, deform: bool = True, extra: Callable[[dict], torch.Tensor] | None = None):
        """Render every sample of a batch from its own camera. Returns rgb [B,H,W,3], alpha [B,H,W,1], metas, posed.

        extra(posed) -> [B,N,E]: per-Gaussian values composited with the image's blend weights in a second pass
        over detached geometry (background 0), returned as posed["extra_image"] [B,H,W,E] (the flow loss renders the
        Gaussians' image motion this way).
        """
        poses, transl = batch["poses"], batch["transl"]
        frame_idx = batch["frame_idx"]
        viewmats, Ks = batch["viewmat"], batch["K"]
        W, H = int(batch["width"][0]), int(batch["height"][0])
        posed = self.deform_shared(poses, transl, deform=deform, frame_idx=frame_idx)
        rgb = self.shade(posed, viewmats, frame_idx)  # [B,N,3]
        images, alphas, metas = [], [], []
        for b in range(posed["B"]):
            img, alpha, meta = self.splat(posed, b, rgb[b], viewmats[b : b + 1], Ks[b : b + 1], W, H)
            images.append(img[0])
            alphas.append(alpha[0])
            metas.append(meta)
        if extra is not None:
            # A second pass over detached geometry: the extra channels' loss reaches the per-Gaussian values only
            # (for the flow term: the Gaussians' motion), never opacity, scale or position through the blend
            # weights, which would let it fade or shrink a Gaussian instead of moving it.
            values = extra(posed).to(rgb)  # [B,N,E]
            fixed = {k: (v.detach() if torch.is_tensor(v) else v) for k, v in posed.items()}
            posed["extra_image"] = torch.stack([
                self.splat(fixed, b, values[b], viewmats[b : b + 1], Ks[b : b + 1], W, H)[0][0]
                for b in range(posed["B"])])
        return torch.stack(images), torch.stack(alphas), metas, posed

    def image_motion(self, batch: dict, deform: bool) -> Callable[[dict], torch.Tensor]:
        """For the flow loss: a function posed -> [B,N,2], each Gaussian's displacement in its sample's image from
        frame t to the earlier frame of batch["prev_poses"], in image heights. The earlier frame is deformed without
        gradient unless flow.prev_grad (then the term moves both frames' Gaussians, at a second network backward)."""
        from realityavatar.losses import project_points

        with torch.set_grad_enabled(torch.is_grad_enabled() and self.flow.prev_grad):
            prev = self.deform(batch["prev_poses"], batch["prev_transl"], deform=deform)["means"]  # [B,N,3]
        H = float(batch["height"][0])

        near = float(self.render_cfg.get("near", 0.01))

        def motion(posed: dict) -> torch.Tensor:
            out = []
            for b in range(posed["B"]):
                uv_t, z_t = project_points(posed["means"][b], batch["viewmat"][b], batch["K"][b])
                uv_p, z_p = project_points(prev[b], batch["viewmat"][b], batch["K"][b])
                # A Gaussian at or behind the near plane in either frame has no image motion (its projection
                # divides by ~0); a displacement beyond max_motion (image heights) is clamped, not followed.
                d = ((uv_p - uv_t) / H).clamp(-self.flow.max_motion, self.flow.max_motion)
                out.append(torch.where(((z_t > near) & (z_p > near))[:, None], d, torch.zeros_like(d)))
            return torch.stack(out)

        return motion

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        check_single_process(self.trainer)

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """Floating-point batch tensors take the module's dtype (float32 images feed a float64 module)."""
        return {k: v.to(self.dtype) if torch.is_tensor(v) and v.is_floating_point() else v for k, v in batch.items()}

    def on_fit_start(self) -> None:
        self.run_info["device"] = str(self.device)  # Lightning's teardown moves the module back to the CPU
        if not bool(self.shading.built):  # the normal grid of shading=irradiance (a checkpoint restores it)
            t0 = time.perf_counter()
            record = self.shading.init_from_body(self.body.canonical_vertices().detach(), self.body.faces)
            self.run_info["shading_grid"] = {**record, "seconds": time.perf_counter() - t0}
        if self.posefit is not None:  # the training masks' distance fields (not in the checkpoint: rebuilt here)
            dm = getattr(self.trainer, "datamodule", None)
            if dm is None or "train" not in getattr(dm, "datasets", {}):
                raise RuntimeError("posefit=silhouette needs the training DataModule (trainer.fit(module, datamodule=...))")
            self.run_info["posefit"] = self.posefit.build(dm)
        # The skinning field starts from the body's weights: the MLP is pre-fitted for schedule.skin_pretrain_steps
        # cheap steps on surface samples (learnt from scratch at the paper's small LR it is still far from them after
        # a short CPU run, which blurs every frame); the grid is built from them. Once per run: a resumed run restores run_info["skin_pretrain"] from its checkpoint (on_load_checkpoint runs
        # before this hook, while global_step is still 0) and keeps the checkpoint's skinning weights.
        if "skin_pretrain" in self.run_info:
            return
        t0 = time.perf_counter()
        record = self.skinning.init_from_body(self.body.canonical_vertices().detach(), self.body.faces,
                                              self.body.skin_weights, steps=self.schedule.skin_pretrain_steps)
        if record is not None:
            self.run_info["skin_pretrain"] = {**record, "seconds": time.perf_counter() - t0}
        if self.sheet is not None:
            record = self.sheet.canonicalise(self.body, self.skinning)  # profile=rest, once per run
            self.run_info["sheet"] = {**self.sheet.layout, **({"canonicalise": record} if record else {})}

    def _skin_targets(self):
        if self._surface is None or self._surface[0].device != self.device or self._surface[0].dtype != self.dtype:
            gen = torch.Generator().manual_seed(1234)
            verts = self.body.canonical_vertices().detach()
            self._surface = sample_surface(verts, self.body.faces, self.body.skin_weights, 20 * self.skin_samples, gen)
        pts, w = self._surface  # on the body's device, in its dtype
        idx = torch.randint(0, pts.shape[0], (self.skin_samples,), device=pts.device)
        return pts[idx], w[idx]

    def training_step(self, batch, batch_idx):
        step = self.global_step
        opt = self.optimizers()
        sched = self.lr_schedulers()
        opt.zero_grad(set_to_none=True)
        deform = self.schedule.deform_on(step)
        self.set_progress(step)
        use_flow = self.flow is not None and "flow" in batch
        extra = self.image_motion(batch, deform) if use_flow else None
        rgb, alpha, metas, posed = self.render_batch(batch, deform=deform, extra=extra)
        skin_pts, skin_w = self._skin_targets()
        total, terms = self.loss_fn(
            rgb, alpha, batch["image"], batch["mask"], skinning=self.skinning, skin_points=skin_pts,
            skin_weights=skin_w, skin_decayed=self.schedule.skin_decayed(step),
        )
        if self.silhouette is not None:
            sil: dict[str, torch.Tensor] = {}
            for b in range(rgb.shape[0]):
                for k, v in self.silhouette(posed["means"][b], batch["viewmat"][b], batch["K"][b], batch["mask"][b],
                                            alpha[b]).items():
                    sil[k] = sil.get(k, 0.0) + v / rgb.shape[0]
                pulled = getattr(self.silhouette, "last_pulled", None)
                if pulled is not None and hasattr(self.density, "observe_coverage"):
                    self.density.observe_coverage(pulled, self.gaussians.num_points)  # counts the free ones only
            if sil:
                total = total + self.silhouette.total(sil)
                terms.update({k: v.detach() for k, v in sil.items()})
        if self.sheet is not None and self.sheet.strain_weight > 0:  # deform put the posed vertices in "sheet_verts"
            term = self.sheet.strain(posed["sheet_verts"])
            total = total + self.sheet.strain_weight * term
            terms["sheet_strain"] = term.detach()
        if use_flow:
            term = self.flow(posed["extra_image"], alpha, batch["flow"], batch["flow_valid"])
            total = total + self.flow.weight * term
            terms["flow"] = term.detach()
        if not torch.isfinite(total):
            raise FloatingPointError(f"training loss became non-finite at step {step}: {terms}")
        self.manual_backward(total)
        if self.grad_clip:
            nets = [p for n in COMPONENTS for p in getattr(self, n).parameters() if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(nets, self.grad_clip)
        opt.step()
        sched.step()
        H, W = rgb.shape[1:3]
        # What actually rendered (gsplat may have fallen back to torch), reported in metrics.json.
        self.run_info["render"] = {"backend": metas[0]["backend"], "device": str(rgb.device), "dtype": str(rgb.dtype)}
        raw = opt.optimizer if hasattr(opt, "optimizer") else opt  # the torch optimizer under Lightning's wrapper
        stats = self.density.step_post_backward(self.gaussians, raw, metas, step, (W, H))
        bs = rgb.shape[0]
        if self.posefit is not None and deform:  # the pose path's own steps on other frames' silhouettes
            # on the torch optimizer: Lightning's would count each of them as a training step
            for k, v in self.posefit.step(self, raw, step, self.grad_clip).items():
                self.log(f"train/{k}", v, batch_size=bs)
        self.log("train/loss", total.detach(), prog_bar=True, batch_size=bs)
        for k, v in terms.items():
            self.log(f"train/{k}", float(v), batch_size=bs)
        self.log("train/num_gaussians", float(self.gaussians.num_points), prog_bar=True, batch_size=bs)
        if stats:
            for k, v in stats.items():
                if isinstance(v, (int, float)):
                    self.log(f"train/density_{k}", float(v), batch_size=bs)
        # Per-image error for samplers that draw hard frames more often (data.sampler=hard_frames, SamplerFeedback):
        # colour L1 plus the mask disagreement, both means over the image.
        with torch.no_grad():
            image_loss = (rgb - batch["image"]).abs().mean((1, 2, 3)) + (alpha - batch["mask"]).abs().mean((1, 2, 3))
        return {"loss": total.detach(), "image_loss": image_loss}

    def param_groups(self) -> list[dict]:
        """Optimizer groups as each component names them (`param_groups()`, else one group under its own name); a
        group without its own entry in optim.lr (e.g. deformer_encoding) takes its component's rate."""
        groups = []
        for name in ("gaussians",) + COMPONENTS + (("sheet",) if self.sheet is not None else ()):
            comp = getattr(self, name)
            named = comp.param_groups() if hasattr(comp, "param_groups") else {name: list(comp.parameters())}
            for gname, params in named.items():
                params = [p for p in params if p.requires_grad]
                if not params:  # an ablated component (e.g. SH colour) contributes no group
                    continue
                # the sheet's groups take the free Gaussians' rates (its normal offset the means')
                base = {"sheet_normal_offset": "means", "sheet_basis": "deformer", "sheet_coeff": "deformer"}.get(
                    gname, gname.removeprefix("sheet_"))
                lr = self.lr.get(gname, self.lr.get(base, self.lr.get(name)))
                if gname in ("means", "sheet_normal_offset"):
                    lr = lr * self.scene_extent
                groups.append({"params": params, "lr": lr, "name": gname})
        return groups

    def configure_optimizers(self):
        opt = self.optimizer_factory(self.param_groups())
        T = self.max_steps

        def decay(name):
            f = self.final_factor.get(name, self.final_factor.get("default", 1.0))
            return lambda s: f ** min(s / T, 1.0)

        sched = torch.optim.lr_scheduler.LambdaLR(opt, [decay(g["name"]) for g in opt.param_groups])
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["density_state"] = self.density.state_dict() if hasattr(self.density, "state_dict") else {}
        checkpoint["num_gaussians"] = self.gaussians.num_points
        checkpoint["realityavatar"] = dict(self.run_info)
        if self.posefit is not None and self.posefit.optimizer_state() is not None:  # posefit.optimizer=own
            checkpoint["posefit_optimizer"] = self.posefit.optimizer_state()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if checkpoint.get("density_state") and hasattr(self.density, "load_state_dict"):
            self.density.load_state_dict(checkpoint["density_state"])
        if self.posefit is not None and checkpoint.get("posefit_optimizer") is not None:
            self.posefit.load_optimizer_state(checkpoint["posefit_optimizer"])
        saved = checkpoint.get("realityavatar", {})
        if "skin_pretrain" in saved:  # done in an earlier part of this run (or checkpoint without a pre-fit: none)
            self.run_info["skin_pretrain"] = saved["skin_pretrain"]
        elif checkpoint.get("global_step", 0) > 0:
            self.run_info["skin_pretrain"] = {"steps": 0, "note": "checkpoint predates pre-fit records; not repeated"}

    # ------------------------------------------------------------------ evaluation
    def test_step(self, batch, batch_idx, dataloader_idx: int = 0):
        from realityavatar.metrics import masked_bbox, psnr, silhouette_iou, ssim

        split = batch["split"][0]
        with torch.no_grad():
            rgb, alpha, _, _ = self.render_batch(batch)
        rgb = rgb.clamp(0, 1)
        for b in range(rgb.shape[0]):
            pred, gt, mask = rgb[b], batch["image"][b], batch["mask"][b]
            rec = {
                "split": split,
                "frame": int(batch["frame"][b]),
                "view": int(batch["view"][b]),
                "psnr": float(psnr(pred, gt)),
                "ssim": float(ssim(pred, gt)),
            }
            rec["iou"] = float(silhouette_iou(alpha[b], mask))
            pb, gb = masked_bbox(pred, gt, mask)
            rec["psnr_masked"] = float(psnr(pb, gb))
            rec["ssim_masked"] = float(ssim(pb, gb))
            if self.lpips is not None:
                rec["lpips"] = float(self.lpips(pred, gt)) * 1000.0
                rec["lpips_masked"] = float(self.lpips(pb, gb)) * 1000.0
            self.test_records.append({**rec, "_pred": pred.cpu(), "_gt": gt.cpu()})
            for k in ("psnr", "ssim", "iou", "psnr_masked", "ssim_masked", "lpips", "lpips_masked"):
                if k in rec:
                    self.log(f"test/{split}/{k}", rec[k], add_dataloader_idx=False, batch_size=1)

    @torch.no_grad()
    def measure_fps(self, batch: dict, warmup: int = 3, repeats: int = 20) -> float:
        """Frames per second of the full path (encoder .. rasterize) for one camera, synchronised on CUDA."""
        one = {k: (v[:1] if torch.is_tensor(v) else v[:1] if isinstance(v, list) else v) for k, v in batch.items()}
        one = self.on_after_batch_transfer({k: v.to(self.device) if torch.is_tensor(v) else v for k, v in one.items()}, 0)
        _, _, metas, _ = self.render_batch(one)
        self.run_info["fps"] = {"backend": metas[0]["backend"], "device": str(self.device)}
        for _ in range(warmup):
            self.render_batch(one)
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(repeats):
            self.render_batch(one)
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        return repeats / (time.perf_counter() - t0)

    def num_parameters(self) -> int:
        """Learnable parameters of the avatar: Gaussians and every network (the body model has none)."""
        return int(sum(p.numel() for p in self.parameters() if p.requires_grad))


FROZEN_NETWORKS = ("lpips.", "loss_fn.vgg.")  # state-dict prefixes of networks loaded from weight files


def _drop_frozen_networks(module: nn.Module, state_dict: dict, prefix: str, local_metadata: dict) -> None:
    for key in [k for k in state_dict if k[len(prefix):].startswith(FROZEN_NETWORKS)]:
        del state_dict[key]


def _ignore_frozen_networks(module: nn.Module, incompatible) -> None:
    for keys in (incompatible.missing_keys, incompatible.unexpected_keys):
        keys[:] = [k for k in keys if not k.startswith(FROZEN_NETWORKS)]


def check_single_process(trainer: Any) -> None:
    """One avatar trains in one process: density control adds Parameters after each refinement (DDP would not see
    them), the deformer is unused before deform_start, and per-rank densification would diverge."""
    if trainer is not None and trainer.world_size > 1:
        raise ValueError(
            f"trainer: {trainer.world_size} processes (devices={trainer.num_devices}, num_nodes={trainer.num_nodes}) "
            "for one run; RealityAvatar trains one avatar per process. Scale with one run per GPU through a hydra "
            "launcher (hydra/launcher=joblib, hydra/launcher=slurm_gpu) and keep trainer.devices=1"
        )


def identity_deformation(B: int, means: torch.Tensor, feature_dim: int) -> dict:
    """Decoder output that leaves the canonical Gaussians unchanged: dx, ds [B,N,3], dq [B,N,4], f_mt [B,N,F]."""
    N = means.shape[0]
    zeros = means.new_zeros(B, N, 3)
    dq = means.new_zeros(B, N, 4)
    dq[..., 0] = 1.0
    return {"dx": zeros, "ds": zeros, "dq": dq, "f_mt": means.new_zeros(B, N, feature_dim)}
