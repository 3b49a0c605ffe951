"""Motion-trend decoder: encoding of the canonical position ⊕ h_t -> Δx, Δs, Δq, f_mt."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import quat_multiply, unit
from realityavatar.model.encodings import FrequencyEncoding
from realityavatar.runtime import Table, constant

_ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU}

_IDENTITY_QUAT = Table(torch.tensor([1.0, 0.0, 0.0, 0.0]))


class MotionTrendDecoder(nn.Module):
    """Paper's motion-trend decoder F_mt: enc(x_c) ⊕ h_t -> Δx [B,N,3], Δs [B,N,3] (log), Δq [B,N,4], f_mt [B,N,F].

    x_c is normalised to [-1,1]^3 with the box (bbox_min, bbox_max) (persistent buffers) and encoded with NeRF's
    frequency encoding. With auto_bounds the box is fitted (10% padding) by `fit_bounds`: AvatarModule calls it with
    the initial canonical Gaussians when it is built (a decoder used on its own: call it before the first forward).
    The encoding sees x_c detached: the canonical means get their gradient from x_e = x_c + Δx. num_layers hidden
    layers of hidden_dim (`activation`: SiLU, or ReLU as in 3DGS-Avatar's non-rigid MLP: the config's default, +0.17 /
    +0.30 dB NV / NP over 3 seeds at the same cost per step, docs/configs.md), then one output layer whose Δx/Δs/Δq
    rows start at zero so the deformation starts at the identity.
    """

    def __init__(self, cond_dim: int, hidden_dim: int, num_layers: int, feature_dim: int, num_freqs: int,
                 bbox_min: tuple[float, float, float], bbox_max: tuple[float, float, float], auto_bounds: bool,
                 activation: Literal["silu", "relu"]) -> None:
        super().__init__()
        if activation not in _ACTIVATIONS:
            raise ValueError(f"deformer.activation: expected one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        self.activation = activation
        act = _ACTIVATIONS[activation]
        self.in_act = act()  # after the first layer; the hidden layers have their own
        self.encoding = FrequencyEncoding(num_freqs)
        self.feature_dim = feature_dim
        self.register_buffer("bbox_min", torch.tensor(bbox_min, dtype=torch.float32))
        self.register_buffer("bbox_max", torch.tensor(bbox_max, dtype=torch.float32))
        # 0 until the box is fitted; persistent, so a loaded checkpoint keeps the box it was trained with.
        self.register_buffer("bounds_fitted", torch.tensor(0 if auto_bounds else 1, dtype=torch.uint8))
        # First layer split into position and condition parts: h_t's contribution is computed once per batch item.
        self.in_x = nn.Linear(self.encoding.out_dim, hidden_dim)
        self.in_h = nn.Linear(cond_dim, hidden_dim, bias=False)
        hidden: list[nn.Module] = []
        for _ in range(num_layers - 1):
            hidden += [nn.Linear(hidden_dim, hidden_dim), act()]
        self.hidden = nn.Sequential(*hidden)
        self.out = nn.Linear(hidden_dim, 3 + 3 + 4 + feature_dim)
        with torch.no_grad():
            self.out.weight[:10].zero_()
            self.out.bias[:10].zero_()

    def set_window(self, fraction: float) -> None:
        """Coarse-to-fine (schedule.deform_anneal, Nerfies' window): open the encoding's bands up to `fraction` (0: the
        position alone, 1: every band) so that a large, smooth motion is found before the fine bands let
        neighbouring Gaussians move apart."""
        self.encoding.set_window(self.encoding.num_freqs * float(fraction))

    @torch.no_grad()
    def fit_bounds(self, points: torch.Tensor, padding: float = 0.1) -> None:
        """Set the normalisation box from points [P,3] with a relative padding per axis, at least 1 mm (a box flat
        along an axis, e.g. of one point, would divide by zero: NaN offsets)."""
        lo, hi = points.min(0).values, points.max(0).values
        pad = ((hi - lo) * padding).clamp_min(1e-3)
        self.bbox_min.copy_(lo - pad)
        self.bbox_max.copy_(hi + pad)
        self.bounds_fitted.fill_(1)

    def forward(self, x_c: torch.Tensor, h_t: torch.Tensor) -> dict[str, torch.Tensor]:
        """x_c [N,3], h_t [B,H] -> dict(dx [B,N,3], ds [B,N,3], dq [B,N,4] unit wxyz, f_mt [B,N,F])."""
        u = (x_c - self.bbox_min) / (self.bbox_max - self.bbox_min)
        enc = self.encoding((u * 2 - 1).detach())  # [N,E]
        eh = self.in_h(h_t)  # [B,H]
        # h_t's term enters as the first layer's bias (one addmm per sample instead of a broadcast add over [B,N,H])
        # The MLP runs on [B*N,H] rows (2-D matmuls: no copies in the backward of 3-D inputs).
        z = [F.linear(enc, self.in_x.weight, self.in_x.bias + e) for e in eh.unbind(0)]
        z = z[0] if len(z) == 1 else torch.cat(z)  # [B*N,H]
        o = self.out(self.hidden(self.in_act(z))).reshape(eh.shape[0], enc.shape[0], -1)  # [B,N,10+F]
        dx, ds, dq, f_mt = o.split([3, 3, 4, o.shape[-1] - 10], -1)  # one backward node (slices: one each)
        return {"dx": dx, "ds": ds, "dq": unit(dq + constant(_IDENTITY_QUAT, o)), "f_mt": f_mt}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"deformer": list(self.parameters())}


def apply_deformation(
    means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, out: dict[str, torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Paper eqs.: x_e = x_c + Δx, R_e = ΔR R_c (q_e = Δq ⊗ q_c), s_e = s_c exp(Δs) (log_s_e = log_s_c + Δs).

    means, log_scales [N,3], quats [N,4] -> x_e [B,N,3], log_s_e [B,N,3], q_e [B,N,4] (the product of two unit
    quaternions: unit up to rounding; LBS normalises it).
    """
    x_e = means + out["dx"]
    log_s_e = log_scales + out["ds"]
    q_e = quat_multiply(out["dq"], unit(quats).expand_as(out["dq"]))
    return x_e, log_s_e, q_e
