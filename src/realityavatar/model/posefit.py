"""The pose path's own updates from other frames' silhouettes (`posefit=silhouette`).

Why: the garment's shape during a spin is a function of the pose window that the encoder, temporal module, decoder
and the sheet's motion basis learn far slower than the images arrive. Given the simulated cloth in 3D as target,
those networks are still 4.9 cm off over the spin after 1,000 one-frame steps and need ~10,000 to get within 2 cm
(`ablations/garment_regress.py`, README "Can the pose window learn the garment?"), while a sweep-preset run gives
them 1,000 steps of one image each. Rendering more images per step would cost a whole step each.

What: after each image step, `passes` more optimizer steps of the pose path alone (the groups named in `groups`),
each on `frames` training frames drawn uniformly, seen by every training camera of that frame, with no rendering:
the centres of the sheet's vertices and of `free_points` free Gaussians (drawn afresh each pass) are deformed and
skinned for the frame's pose window and projected, and a 2D chamfer with the frame's masks (as `silhouette=chamfer`,
image heights squared) pulls them:
- outside: a projected centre outside a mask follows the mask's distance field (the visual-hull condition);
- coverage: each sampled mask pixel farther than `margin_px` from every projected centre pulls its nearest one
  (without a render there is no alpha to say which pixels are uncovered; the margin stands in for a footprint).
cover=garment: only the mask pixels farther than `body_margin_px` from the posed body model's projected vertices pull,
and they pull the garment sheet's vertices and Gaussians (a free Gaussian cannot cover the garment for it).
optimizer=own: Adam moments of its own over those groups (saved in the checkpoint); shared: the run's optimizer.
The masks' distance fields (and cover=garment's pixels) are computed once, when training starts. The frames drawn
depend only on the seed, the step and the pass, so a resumed run draws the same ones.

Measured (README, "Tried against this, kept as an option"): on the sweep scene the image steps alone already meet
the training silhouettes within ~1.5 px, and this option moves the held-out spin by about one seed's spread.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import nn

from realityavatar.losses import mask_distance, nearest_index, outside_distance, project_points

POSE_PATH_GROUPS = ("encoder", "temporal", "deformer", "sheet_basis", "sheet_coeff")


class NoPoseFit(nn.Module):
    """posefit=none: the pose path learns from the image steps only."""

    passes = 0

    def build(self, dm) -> dict | None:
        return None


class SilhouettePoseFit(nn.Module):
    def __init__(self, frames: int = 4, passes: int = 2, weight: float = 10.0, outside_weight: float = 1.0,
                 coverage_weight: float = 1.0, free_points: int = 1024, max_pixels: int = 512, margin_px: float = 1.0,
                 near: float = 0.05, groups: tuple | list = POSE_PATH_GROUPS, optimizer: str = "own",
                 cover: str = "all", body_margin_px: float = 2.0, seed: int = 0) -> None:
        super().__init__()
        for name, v, lo in (("frames", frames, 1), ("passes", passes, 0), ("free_points", free_points, 0),
                            ("max_pixels", max_pixels, 1)):
            if int(v) != v or v < lo:
                raise ValueError(f"posefit.{name}: expected a whole number >= {lo}, got {v!r}")
        for name, v in (("weight", weight), ("outside_weight", outside_weight), ("coverage_weight", coverage_weight),
                        ("margin_px", margin_px)):
            if not (float(v) >= 0):
                raise ValueError(f"posefit.{name}: expected a number >= 0, got {v!r}")
        unknown = sorted(set(groups) - set(POSE_PATH_GROUPS))
        if unknown:
            raise ValueError(f"posefit.groups: {unknown} are not pose-path groups; choose from {list(POSE_PATH_GROUPS)}")
        self.frames, self.passes, self.free_points, self.max_pixels = int(frames), int(passes), int(free_points), \
            int(max_pixels)
        self.weight, self.outside_weight, self.coverage_weight = float(weight), float(outside_weight), \
            float(coverage_weight)
        if cover not in ("all", "garment"):
            raise ValueError(f"posefit.cover: expected 'all' or 'garment', got {cover!r}")
        if not (float(body_margin_px) >= 0):
            raise ValueError(f"posefit.body_margin_px: expected a number >= 0, got {body_margin_px!r}")
        self.cover, self.body_margin_px = cover, float(body_margin_px)
        if optimizer not in ("own", "shared"):
            raise ValueError(f"posefit.optimizer: expected 'own' or 'shared', got {optimizer!r}")
        self.margin_px, self.near, self.groups, self.seed = float(margin_px), float(near), tuple(groups), int(seed)
        self.optimizer = optimizer
        self.bank: list[dict] | None = None
        self._opt: torch.optim.Optimizer | None = None  # optimizer=own: Adam over the pose-path groups
        self._pending: dict | None = None  # its state from a checkpoint, loaded when it is built

    # ------------------------------------------------------------------ data
    def build(self, dm) -> dict:
        """Per training frame: its pose window and, per training camera, viewmat, K, the mask's distance field and
        its pixels. Reads the training split's (cached) images once."""
        t0 = time.perf_counter()
        ds = dm.datasets["train"]
        by_frame: dict[int, list[int]] = {}
        for i, r in enumerate(ds.records):
            by_frame.setdefault(int(r.frame), []).append(i)
        bank = []
        body = getattr(dm, "body", None)
        if self.cover == "garment" and body is None:
            raise ValueError("posefit.cover=garment needs the DataModule's body model (dm.body)")
        for frame in sorted(by_frame):
            poses, transl = ds.poses.window(frame, ds.window_len, ds.window_step)
            body_pts = None
            if self.cover == "garment":  # the body model's mesh in the frame's pose
                with torch.no_grad():
                    body_pts = body.posed_vertices(poses[-1].float(), transl[-1].float())
            views = []
            for i in by_frame[frame]:
                rec = ds.records[i]
                _, mask_b, K = ds._decoded(i)
                mask = torch.from_numpy(np.asarray(mask_b, dtype=np.float32))
                pix = (mask > 0.5).nonzero().flip(-1).to(torch.int16)  # [P,2] (x,y)
                view = {"viewmat": torch.as_tensor(rec.viewmat, dtype=torch.float32),
                        "K": torch.as_tensor(K, dtype=torch.float32),
                        "dist": mask_distance(mask).to(torch.float16), "pix": pix}
                if body_pts is not None:  # cover=garment: the mask pixels the posed body does not explain
                    view["pix"] = self._beyond_body(pix, body_pts, view["viewmat"], view["K"])
                views.append(view)
            bank.append({"frame": frame, "poses": poses.float(), "transl": transl.float(), "views": views})
        self.bank = bank
        return {"frames": len(bank), "images": sum(len(b["views"]) for b in bank),
                "seconds": round(time.perf_counter() - t0, 3)}

    def _beyond_body(self, pix: torch.Tensor, body_pts: torch.Tensor, viewmat: torch.Tensor,
                     K: torch.Tensor) -> torch.Tensor:
        uv, z = project_points(body_pts, viewmat, K)
        uv = uv[z > self.near]
        if not uv.shape[0] or not pix.shape[0]:
            return pix
        p = pix.float()
        d = (uv[nearest_index(p, uv)] - p).norm(dim=-1)
        return pix[d > self.body_margin_px]

    def draw(self, step: int, k: int) -> tuple[list[int], torch.Generator]:
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step * 101 + k)
        n = len(self.bank)
        return torch.randint(0, n, (min(self.frames, n),), generator=gen).tolist(), gen

    # ------------------------------------------------------------------ loss
    def loss(self, module, step: int, k: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Pass k of step `step`: the chamfer over the drawn frames' training cameras, and its two terms."""
        if not self.bank:
            raise RuntimeError("posefit: build(datamodule) must run before training (AvatarModule.on_fit_start)")
        idx, gen = self.draw(step, k)
        dev, dt = module.device, module.dtype
        poses = torch.stack([self.bank[i]["poses"] for i in idx]).to(dev, dt)
        transl = torch.stack([self.bank[i]["transl"] for i in idx]).to(dev, dt)
        n_free = module.gaussians.num_points
        free = torch.randperm(n_free, generator=gen)[: self.free_points].to(dev)
        pts = module.deform_points(poses, transl, free)  # [B,S+V,3]
        cover = pts
        if self.cover == "garment":  # the garment's pixels are the sheet's to cover: its vertices and Gaussians
            if module.sheet is None:
                raise ValueError("posefit.cover=garment needs a garment sheet (sheet=skirt)")
            verts = pts[:, len(free):]
            cover = torch.cat([verts, module.sheet.interpolate(verts)], 1)
        outs, covs = [], []
        for b, i in enumerate(idx):
            for v in self.bank[i]["views"]:
                o, c = self._image_terms(pts[b], cover[b], v, gen)
                outs.append(o)
                covs.append(c)
        terms = {"posefit_outside": torch.stack(outs).mean(), "posefit_coverage": torch.stack(covs).mean()}
        total = self.weight * (self.outside_weight * terms["posefit_outside"]
                               + self.coverage_weight * terms["posefit_coverage"])
        return total, terms

    def _image_terms(self, points: torch.Tensor, cover: torch.Tensor, view: dict, gen: torch.Generator):
        """points [N,3] kept inside the mask, cover [M,3] pulled by its uncovered pixels -> (outside, coverage)."""
        dist = view["dist"].to(points)
        H = dist.shape[0]
        uv, z = project_points(points, view["viewmat"].to(points), view["K"].to(points))
        uv = uv[z > self.near]
        if not uv.shape[0]:
            return points.sum() * 0, points.sum() * 0
        outside = ((outside_distance(uv, dist) / H) ** 2).mean()
        pix = view["pix"]
        uc, zc = project_points(cover, view["viewmat"].to(points), view["K"].to(points))
        uc = uc[zc > self.near]
        if not pix.shape[0] or not uc.shape[0]:
            return outside, outside * 0
        if pix.shape[0] > self.max_pixels:
            pix = pix[torch.randperm(pix.shape[0], generator=gen)[: self.max_pixels]]
        pix = pix.to(uc)
        near = uc[nearest_index(pix, uc.detach()).to(uc.device)]
        gap = ((near - pix).norm(dim=-1) - self.margin_px).clamp_min(0.0)
        return outside, ((gap / H) ** 2).mean()

    def optimizer_state(self) -> dict | None:
        """optimizer=own: its Adam state for the checkpoint (None before the first pass, or with shared moments)."""
        return self._opt.state_dict() if self._opt is not None else self._pending

    def load_optimizer_state(self, state: dict | None) -> None:
        self._opt, self._pending = None, state

    def step(self, module, optimizer, step: int, grad_clip: float | None = None) -> dict[str, float]:
        """The `passes` pose-path steps after image step `step` (optimizer: the torch optimizer itself, so the
        Trainer's step count is not advanced). Returns the last pass's terms."""
        names = set(self.groups)
        mine = [g for g in optimizer.param_groups if g.get("name") in names]
        keep = [p for g in mine for p in g["params"]]
        others = [p for g in optimizer.param_groups if g.get("name") not in names for p in g["params"]]
        opt = optimizer
        if self.optimizer == "own":
            # Adam moments of their own, built on the first pass from the run's groups (their current rates)
            if self._opt is None:
                kw = {k: v for k, v in optimizer.defaults.items() if k != "lr"}
                self._opt = type(optimizer)([{"params": list(g["params"]), "lr": g["lr"], "name": g["name"]}
                                             for g in mine], **kw)
                if self._pending is not None:  # a resumed run continues with the moments it had
                    self._opt.load_state_dict(self._pending)
                    self._pending = None
            for g, m in zip(self._opt.param_groups, mine):
                g["lr"] = m["lr"]  # the run's schedule
            opt = self._opt
        out: dict[str, float] = {}
        for k in range(self.passes):
            optimizer.zero_grad(set_to_none=True)
            total, terms = self.loss(module, step, k)
            if not torch.isfinite(total):
                raise FloatingPointError(f"posefit loss became non-finite at step {step}, pass {k}: {terms}")
            total.backward()
            for p in others:
                p.grad = None
            if grad_clip:
                torch.nn.utils.clip_grad_norm_([p for p in keep if p.grad is not None], grad_clip)
            opt.step()
            out = {k2: float(v.detach()) for k2, v in terms.items()}
        optimizer.zero_grad(set_to_none=True)
        return out
