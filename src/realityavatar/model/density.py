"""Adaptive density control of the canonical Gaussians (clone / split / prune / opacity reset) as a strategy object."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from realityavatar.geometry import quat_to_matrix
from realityavatar.model.gaussians import CanonicalGaussians, inverse_sigmoid
from realityavatar.runtime import constant


def _swap_in_optimizer(
    optimizer: torch.optim.Optimizer | None,
    swapped: dict[str, tuple[nn.Parameter, nn.Parameter]],
    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
) -> None:
    """Point the optimizer at the new Parameters and rewrite their per-row state (Adam exp_avg, exp_avg_sq)."""
    if optimizer is None:
        return
    for name, (old, new) in swapped.items():
        for group in optimizer.param_groups:
            for i, p in enumerate(group["params"]):
                if p is old:
                    group["params"][i] = new
                    st = optimizer.state.pop(old, None)
                    if st is not None:
                        optimizer.state[new] = {
                            k: (state_fn(name, v) if torch.is_tensor(v) and v.ndim > 0 and v.shape[0] == old.shape[0] else v)
                            for k, v in st.items()
                        }


class NoDensityControl:
    """Density control off (`density=off`): the Gaussian count stays at gaussians.num_points (gsplat's null
    strategy). Same interface as DensityControl, no state.

    DensityControl's settings are accepted and unused, so a preset or experiment that tunes density control
    (`density.prune_opacity` in `preset=sweep` and `experiment=demo`) composes with `density=off`; any other key is
    an error naming it.
    """

    changes_count = False  # the Gaussian count stays fixed: torch.compile may specialise on it

    def __init__(self, **settings) -> None:
        import inspect

        known = set(inspect.signature(DensityControl.__init__).parameters) - {"self"}
        unknown = sorted(set(settings) - known)
        if unknown:
            raise TypeError(f"density=off: unknown option(s) {unknown}; density settings are {sorted(known)}")
        self.unused_settings = dict(settings)

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass

    def step_post_backward(self, gaussians, optimizer, meta, step: int, image_size: tuple[int, int]) -> dict:
        return {}


class DensityControl:
    """3DGS densification with explicit state (accumulated screen-space gradient norms and visibility counts).

    Per step: for every Gaussian seen by a camera, add |d loss / d means2d| scaled to pixels (x W/2, y H/2, times
    the number of cameras, like gsplat) and count the visibility. Every `refine_every` steps in
    [refine_start, refine_stop): Gaussians with mean gradient > grad_threshold are cloned (max scale <=
    grow_scale3d * scene_scale) or split into two samples of their Gaussian with scales / 1.6; then Gaussians
    with opacity < prune_opacity (and, after the first opacity reset, max scale > prune_scale3d * scene_scale)
    are pruned; growth stops at max_points. Every `reset_every` steps (0 = never) opacities are clamped to
    2 * prune_opacity. New rows of the optimizer state start at zero; the accumulators reset after each refine.
    """

    changes_count = True  # refinements change the Gaussian count: compiled graphs treat it as dynamic

    def __init__(self, refine_start: int, refine_stop: int, refine_every: int, grad_threshold: float,
                 prune_opacity: float, grow_scale3d: float, prune_scale3d: float, scene_scale: float, reset_every: int,
                 max_points: int, seed: int) -> None:
        self.refine_start = refine_start
        self.refine_stop = refine_stop
        self.refine_every = max(int(refine_every), 1)
        self.grad_threshold = grad_threshold
        self.prune_opacity = prune_opacity
        self.grow_scale3d = grow_scale3d
        self.prune_scale3d = prune_scale3d
        self.scene_scale = scene_scale
        self.reset_every = reset_every
        self.max_points = max_points
        self.generator = torch.Generator().manual_seed(seed)
        self.grad2d: torch.Tensor | None = None  # [N] accumulated pixel-gradient norms
        self.count: torch.Tensor | None = None  # [N] number of visible observations

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count, "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.grad2d = state.get("grad2d")
        self.count = state.get("count")
        if state.get("generator") is not None:
            self.generator.set_state(state["generator"])

    # ------------------------------------------------------------------ accumulate
    def _accumulate(self, gaussians: CanonicalGaussians, metas: list[dict], image_size: tuple[int, int]) -> None:
        N = gaussians.num_points
        dev = gaussians.means.device
        if self.grad2d is None or self.grad2d.shape[0] != N:
            self.grad2d = torch.zeros(N, device=dev)
            self.count = torch.zeros(N, device=dev)
        self.grad2d = self.grad2d.to(dev)
        self.count = self.count.to(dev)
        W, H = image_size
        # gsplat's rule: the loss is a mean over the batch's images, so each image's means2d gradient is scaled back
        # by their number (C cameras in one meta, or one meta per sample of a multi-image batch).
        # A render may hold more Gaussians than these N (a garment sheet's follow the free ones): the first N are
        # the ones density control edits.
        n_images = sum(int(m["means2d"].reshape(-1, m["means2d"].shape[-2], 2).shape[0]) for m in metas
                       if m["means2d"].grad is not None)
        for meta in metas:
            m2d = meta["means2d"]
            if m2d.grad is None:
                continue
            P = m2d.shape[-2]  # Gaussians rendered
            g = m2d.grad.detach().reshape(-1, P, 2)[:, :N]  # [C,N,2]
            C = g.shape[0]
            g = g * constant((W / 2.0 * n_images, H / 2.0 * n_images), g)  # to pixels, like gsplat
            if "radii" in meta:
                vis = meta["radii"].reshape(C, P, -1)[:, :N].amax(-1) > 0  # [C,N]
            else:
                vis = meta["visible"].reshape(C, P)[:, :N]
            self.grad2d += (g.norm(dim=-1) * vis).sum(0)
            self.count += vis.sum(0).to(self.count.dtype)

    # ------------------------------------------------------------------ main entry
    @torch.no_grad()
    def step_post_backward(
        self,
        gaussians: CanonicalGaussians,
        optimizer: torch.optim.Optimizer | None,
        meta: dict | list[dict],
        step: int,
        image_size: tuple[int, int],
    ) -> dict:
        """Call after backward (means2d.grad filled). Returns stats: num_points and, on refine steps, cloned/split/pruned."""
        metas = meta if isinstance(meta, (list, tuple)) else [meta]
        if step < self.refine_stop:
            self._accumulate(gaussians, metas, image_size)
        stats: dict = {"num_points": gaussians.num_points}
        if self.refine_start <= step < self.refine_stop and step > 0 and step % self.refine_every == 0:
            stats.update(self.refine(gaussians, optimizer, step))
        if self.reset_every > 0 and step > 0 and step % self.reset_every == 0 and step < self.refine_stop:
            self.reset_opacity(gaussians, optimizer)
            stats["reset"] = 1
        stats["num_points"] = gaussians.num_points
        return stats

    def refine(self, gaussians: CanonicalGaussians, optimizer: torch.optim.Optimizer | None, step: int) -> dict:
        N = gaussians.num_points
        avg = self.grad2d / self.count.clamp_min(1)  # [N]
        high = avg > self.grad_threshold
        small = gaussians.scales().amax(-1) <= self.grow_scale3d * self.scene_scale
        clone_mask, split_mask = high & small, high & ~small
        room = max(self.max_points - N, 0)
        # Respect the cap: keep the candidates with the largest gradients (a split adds one net Gaussian, like a clone).
        cand = (clone_mask | split_mask).nonzero().squeeze(-1)
        if cand.numel() > room:
            keep = cand[avg[cand].argsort(descending=True)[:room]]
            sel = torch.zeros_like(clone_mask)
            sel[keep] = True
            clone_mask, split_mask = clone_mask & sel, split_mask & sel
        n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
        if n_clone:
            self.duplicate(gaussians, optimizer, clone_mask)
        if n_split:
            split_mask = torch.cat([split_mask, split_mask.new_zeros(n_clone)])
            self.split(gaussians, optimizer, split_mask)
        prune = gaussians.opacities() < self.prune_opacity
        if self.reset_every > 0 and step > self.reset_every:
            prune |= gaussians.scales().amax(-1) > self.prune_scale3d * self.scene_scale
        if bool(prune.all()):  # never remove the whole avatar
            prune[gaussians.opacities().argmax()] = False
        n_prune = int(prune.sum())
        if n_prune:
            self.remove(gaussians, optimizer, prune)
        self.grad2d = torch.zeros(gaussians.num_points, device=gaussians.means.device)
        self.count = torch.zeros_like(self.grad2d)
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    # ------------------------------------------------------------------ operations (also used by tests)
    def duplicate(self, gaussians: CanonicalGaussians, optimizer, mask: torch.Tensor) -> None:
        """Append a copy of every masked Gaussian; new optimizer rows are zero."""
        sel = mask.nonzero().squeeze(-1)
        params = {n: torch.cat([getattr(gaussians, n), getattr(gaussians, n)[sel]]) for n in gaussians.param_names}
        swapped = gaussians.replace(params)
        _swap_in_optimizer(optimizer, swapped, lambda n, v: torch.cat([v, v.new_zeros((len(sel),) + v.shape[1:])]))

    def split(self, gaussians: CanonicalGaussians, optimizer, mask: torch.Tensor) -> None:
        """Replace every masked Gaussian by two samples drawn from it with scales / 1.6; new optimizer rows are zero."""
        sel = mask.nonzero().squeeze(-1)
        rest = (~mask).nonzero().squeeze(-1)
        k = len(sel)
        scales = gaussians.scales()[sel]  # [k,3]
        R = quat_to_matrix(gaussians.quats[sel])  # [k,3,3]
        noise = torch.randn(2, k, 3, generator=self.generator).to(scales)
        offsets = (R[None] @ (noise * scales[None])[..., None]).squeeze(-1)  # [2,k,3]
        new = {
            "means": (gaussians.means[sel][None] + offsets).reshape(2 * k, 3),
            "log_scales": torch.log(scales / 1.6).repeat(2, 1),
            "quats": gaussians.quats[sel].repeat(2, 1),
            "opacity_logits": gaussians.opacity_logits[sel].repeat(2),
        }
        # every other attribute (features, deformation codes): each child takes its parent's value
        new.update({n: getattr(gaussians, n)[sel].repeat(2, 1) for n in gaussians.param_names if n not in new})
        params = {n: torch.cat([getattr(gaussians, n)[rest], new[n]]) for n in gaussians.param_names}
        swapped = gaussians.replace(params)
        _swap_in_optimizer(optimizer, swapped, lambda n, v: torch.cat([v[rest], v.new_zeros((2 * k,) + v.shape[1:])]))

    def remove(self, gaussians: CanonicalGaussians, optimizer, mask: torch.Tensor) -> None:
        """Drop every masked Gaussian and its optimizer rows."""
        keep = (~mask).nonzero().squeeze(-1)
        swapped = gaussians.replace({n: getattr(gaussians, n)[keep] for n in gaussians.param_names})
        _swap_in_optimizer(optimizer, swapped, lambda n, v: v[keep])

    def reset_opacity(self, gaussians: CanonicalGaussians, optimizer) -> None:
        """Clamp opacities to 2 * prune_opacity and zero the opacity optimizer state (as 3DGS/gsplat do)."""
        cap = float(inverse_sigmoid(torch.tensor(min(2 * self.prune_opacity, 0.99))))
        swapped = gaussians.replace({"opacity_logits": gaussians.opacity_logits.clamp_max(cap)})
        _swap_in_optimizer(optimizer, swapped, lambda n, v: torch.zeros_like(v))
