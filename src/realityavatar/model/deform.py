"""Motion-trend decoder: encoding of the canonical position ⊕ h_t -> Δx, Δs, Δq, f_mt; deformation-graph variant."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from realityavatar.geometry import quat_multiply, quat_to_matrix
from realityavatar.model.encodings import FrequencyEncoding, HashEncoding


_ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU}


class MotionTrendDecoder(nn.Module):
    """Paper's motion-trend decoder F_mt: enc(x_c) ⊕ h_t -> Δx [B,N,3], Δs [B,N,3] (log), Δq [B,N,4], f_mt [B,N,F].

    x_c is normalised to [0,1]^3 with the box (bbox_min, bbox_max) (persistent buffers). With auto_bounds the
    box is fitted (10% padding) by `fit_bounds`: AvatarModule calls it with the initial canonical Gaussians when
    it is built; a decoder used on its own fits it to the x_c of its first forward call. The encoding sees x_c
    detached, whatever its kind: the canonical means get their gradient from x_e = x_c + Δx, and the hash grid
    has no input gradient, so both encodings give the means the same gradient path. num_layers hidden layers of hidden_dim
    (`activation`: SiLU, or ReLU as in 3DGS-Avatar's non-rigid MLP: the config's default, +0.17 / +0.30 dB NV / NP over
    3 seeds at the same cost per step, README "ReLU decoder"), then one output layer
    whose Δx/Δs/Δq rows start at zero so the deformation starts at the identity.
    """

    def __init__(
        self,
        cond_dim: int = 128,
        encoding: Literal["hash", "frequency"] = "hash",
        hidden_dim: int = 128,
        num_layers: int = 3,
        feature_dim: int = 16,
        num_freqs: int = 6,
        hash_levels: int = 16,
        hash_features_per_level: int = 2,
        hash_log2_table_size: int = 16,
        hash_base_resolution: int = 16,
        hash_max_resolution: int = 1024,
        bbox_min: tuple[float, float, float] = (-1.2, -1.5, -1.2),
        bbox_max: tuple[float, float, float] = (1.2, 1.0, 1.2),
        auto_bounds: bool = True,
        activation: Literal["silu", "relu"] = "silu",
        offsets: Literal["cartesian", "cylindrical"] = "cartesian",
        frame_code_dim: int = 0,
        num_frames: int = 1,
        gaussian_code_dim: int = 0,
    ) -> None:
        super().__init__()
        if activation not in _ACTIVATIONS:
            raise ValueError(f"deformer.activation: expected one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        if offsets not in ("cartesian", "cylindrical"):
            raise ValueError(f"deformer.offsets: expected 'cartesian' or 'cylindrical', got {offsets!r}")
        self.offsets = offsets
        # offsets=cylindrical: the first three outputs are (dr, dtheta, dh) about the body's vertical axis through
        # its pelvis (set_axis; AvatarModule sets it from the body model whenever it is built, so the buffers are not
        # in the checkpoint and runs saved before this option load unchanged).
        self.register_buffer("axis_origin", torch.zeros(3), persistent=False)
        self.register_buffer("axis_dir", torch.tensor([0.0, 1.0, 0.0]), persistent=False)
        self.activation = activation
        act = _ACTIVATIONS[activation]
        self.in_act = act()  # after the first layer; the hidden layers have their own
        if encoding == "hash":
            self.encoding: nn.Module = HashEncoding(
                hash_levels, hash_features_per_level, hash_log2_table_size, hash_base_resolution, hash_max_resolution
            )
        elif encoding == "frequency":
            self.encoding = FrequencyEncoding(num_freqs)
        else:
            raise ValueError(f"deformer.encoding: expected 'hash' or 'frequency', got {encoding!r}")
        self.encoding_kind = encoding
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
        # frame_code_dim > 0: a learnt code per training frame joins h_t (a deformation code, as in Nerfies /
        # HyperNeRF). It lets the decoder fit any training frame's shape, whether or not the pose window determines
        # it, so it is the diagnostic upper bound of what the inputs cannot explain; frames not trained on (novel
        # pose) take the mean code. Off by default: the paper's decoder sees h_t only.
        if frame_code_dim < 0:
            raise ValueError(f"deformer.frame_code_dim: expected >= 0, got {frame_code_dim}")
        if gaussian_code_dim < 0:
            raise ValueError(f"deformer.gaussian_code_dim: expected >= 0, got {gaussian_code_dim}")
        self.frame_code_dim = int(frame_code_dim)
        if self.frame_code_dim > 0:
            if num_frames < 1:
                raise ValueError(f"deformer.num_frames: expected >= 1 training frames, got {num_frames}")
            self.num_frames = int(num_frames)
            self.frame_codes = nn.Embedding(self.num_frames, self.frame_code_dim)
            nn.init.normal_(self.frame_codes.weight, std=0.01)
            self.in_code = nn.Linear(self.frame_code_dim, hidden_dim, bias=False)
        # gaussian_code_dim > 0: each Gaussian's learnt code (gaussians.deform_codes) joins its position encoding, so
        # the offset field can differ between Gaussians that share a canonical neighbourhood.
        self.gaussian_code_dim = int(gaussian_code_dim)
        self.in_g = nn.Linear(self.gaussian_code_dim, hidden_dim, bias=False) if self.gaussian_code_dim else None
        with torch.no_grad():
            self.out.weight[:10].zero_()
            self.out.bias[:10].zero_()

    def set_window(self, fraction: float) -> None:
        """Coarse-to-fine (schedule.deform_anneal, Nerfies' window): with the frequency encoding, open its bands up to
        `fraction` (0: the position alone, 1: every band) so that a large, smooth motion is found before the fine
        bands let neighbouring Gaussians move apart. A no-op with the hash encoding."""
        if isinstance(self.encoding, FrequencyEncoding):
            self.encoding.set_window(self.encoding.num_freqs * float(fraction))

    @torch.no_grad()
    def fit_bounds(self, points: torch.Tensor, padding: float = 0.1) -> None:
        """Set the normalisation box from points [P,3] with a relative padding per axis."""
        lo, hi = points.min(0).values, points.max(0).values
        pad = (hi - lo) * padding
        self.bbox_min.copy_(lo - pad)
        self.bbox_max.copy_(hi + pad)
        self.bounds_fitted.fill_(1)

    @torch.no_grad()
    def set_axis(self, origin: torch.Tensor, direction: torch.Tensor) -> None:
        """The vertical axis of offsets=cylindrical: a point on it and its direction (canonical space)."""
        self.axis_origin.copy_(origin.reshape(3))
        self.axis_dir.copy_(F.normalize(direction.reshape(3), dim=0))

    def _cylindrical(self, x_c: torch.Tensor, o: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(dr, dtheta, dh) [B,N,3] about the axis -> Cartesian dx [B,N,3] and the twist's quaternion [B,N,4].

        A Gaussian at radius r and azimuth phi moves to radius r + dr, azimuth phi + dtheta, height h + dh. A skirt's
        flare (dr) and its swirl around the body (dtheta) are then functions of height and time that do not vary
        around the body, where in Cartesian offsets they turn with the azimuth. The frame comes from x_c detached, as
        the encoding does, so the canonical means keep the identity as their gradient path.
        """
        u = self.axis_dir.to(x_c)
        rel = x_c.detach() - self.axis_origin.to(x_c)
        radial = rel - (rel @ u)[:, None] * u  # [N,3]
        r = radial.norm(dim=-1, keepdim=True)
        e_r = radial / r.clamp_min(1e-6)
        e_t = torch.linalg.cross(u.expand_as(e_r), e_r, dim=-1)
        dr, dth, dh = o[..., 0:1], o[..., 1:2], o[..., 2:3]
        c, s_ = torch.cos(dth), torch.sin(dth)
        dx = (r + dr) * (c * e_r + s_ * e_t) - radial + dh * u
        half = 0.5 * dth
        twist = torch.cat([torch.cos(half), torch.sin(half) * u], dim=-1)  # rotation by dtheta about the axis
        return dx, twist

    def code(self, frame_idx: torch.Tensor | None, B: int) -> torch.Tensor:
        """frame_idx [B] (long, -1 or None: not a training frame) -> the frame codes [B,frame_code_dim]."""
        table = self.frame_codes.weight
        mean = table.mean(0, keepdim=True).expand(B, -1)
        if frame_idx is None:
            return mean
        frame_idx = frame_idx.long().to(table.device)
        if frame_idx.numel() and int(frame_idx.max()) >= self.num_frames:
            raise IndexError(f"deformer: frame_idx {int(frame_idx.max())} out of range for {self.num_frames} "
                             "training frames")
        return torch.where((frame_idx < 0)[:, None], mean, table[frame_idx.clamp_min(0)])

    def forward(self, x_c: torch.Tensor, h_t: torch.Tensor, frame_idx: torch.Tensor | None = None,
                codes: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """x_c [N,3], h_t [B,H], frame_idx [B] | None (used with frame codes only), codes [N,gaussian_code_dim]
        (with gaussian codes only) -> dict(dx [B,N,3], ds [B,N,3], dq [B,N,4] unit wxyz, f_mt [B,N,F])."""
        if not bool(self.bounds_fitted):
            self.fit_bounds(x_c.detach())  # auto_bounds: the first x_c seen (the initial canonical Gaussians)
        u = (x_c - self.bbox_min) / (self.bbox_max - self.bbox_min)
        if self.encoding_kind == "frequency":
            u = u * 2 - 1
        enc = self.encoding(u.detach())  # [N,E]
        eh = self.in_h(h_t)  # [B,H]
        if self.frame_code_dim > 0:
            eh = eh + self.in_code(self.code(frame_idx, h_t.shape[0]))
        # h_t's term enters as the first layer's bias (one addmm per sample instead of a broadcast add over [B,N,H])
        # The MLP runs on [B*N,H] rows (2-D matmuls: no copies in the backward of 3-D inputs).
        if self.in_g is None:
            z = torch.cat([F.linear(enc, self.in_x.weight, self.in_x.bias + e) for e in eh])  # [B*N,H]
        else:
            if codes is None or codes.shape != (x_c.shape[0], self.gaussian_code_dim):
                got = None if codes is None else tuple(codes.shape)
                raise ValueError(f"deformer: gaussian_code_dim={self.gaussian_code_dim} needs codes "
                                 f"[{x_c.shape[0]},{self.gaussian_code_dim}] (gaussians.deform_code_dim), got {got}")
            xin = self.in_x(enc) + self.in_g(codes)
            z = torch.cat([xin + e for e in eh])
        o = self.out(self.hidden(self.in_act(z))).reshape(eh.shape[0], enc.shape[0], -1)  # [B,N,10+F]
        dq = F.normalize(o[..., 6:10] + o.new_tensor([1.0, 0.0, 0.0, 0.0]), dim=-1)
        dx = o[..., :3]
        if self.offsets == "cylindrical":
            dx, twist = self._cylindrical(x_c, dx)
            dq = quat_multiply(twist, dq)  # the Gaussian turns with its swirl
        return {"dx": dx, "ds": o[..., 3:6], "dq": dq, "f_mt": o[..., 10:]}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        enc = list(self.encoding.parameters())
        codes = [self.frame_codes.weight] if self.frame_code_dim > 0 else []
        ids = {id(p) for p in enc + codes}
        groups = {"deformer": [p for p in self.parameters() if id(p) not in ids]}
        if enc:
            groups["deformer_encoding"] = enc
        if codes:  # optim.lr.deformer_codes, else the deformer's rate
            groups["deformer_codes"] = codes
        return groups


def apply_deformation(
    means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, out: dict[str, torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Paper eqs.: x_e = x_c + Δx, R_e = ΔR R_c (q_e = Δq ⊗ q_c), s_e = s_c exp(Δs) (log_s_e = log_s_c + Δs).

    means, log_scales [N,3], quats [N,4] -> x_e [B,N,3], log_s_e [B,N,3], q_e [B,N,4] (unit).
    """
    x_e = means + out["dx"]
    log_s_e = log_scales + out["ds"]
    q_e = F.normalize(quat_multiply(out["dq"], F.normalize(quats, dim=-1).expand_as(out["dq"])), dim=-1)
    return x_e, log_s_e, q_e


def farthest_points(points: torch.Tensor, k: int, seed: int = 0) -> torch.Tensor:
    """Indices [k] of a farthest-point sample of points [P,3] (deterministic for a seed)."""
    P = points.shape[0]
    k = min(k, P)
    gen = torch.Generator().manual_seed(seed)
    idx = torch.empty(k, dtype=torch.long)
    idx[0] = torch.randint(0, P, (1,), generator=gen)
    d = (points - points[idx[0]]).square().sum(-1)
    for i in range(1, k):
        idx[i] = d.argmax()
        d = torch.minimum(d, (points - points[idx[i]]).square().sum(-1))
    return idx.to(points.device)


class NodeDeformer(MotionTrendDecoder):
    """Motion-trend decoder on a deformation graph (embedded deformation, as in DDC; latent bones in GART).

    The decoder runs on `num_nodes` nodes g_j (a farthest-point sample of the initial canonical Gaussians, stored
    with the checkpoint) instead of every Gaussian: enc(g_j) ⊕ h_t -> rotation R_j (axis-angle), translation t_j,
    Δs_j, f_mt_j. A Gaussian at x blends its `k` nearest nodes with w_j ∝ exp(-|x-g_j|²/2σ²) (σ = `radius` x
    the mean node spacing): x_e = Σ w_j (R_j (x - g_j) + g_j + t_j), Δq = normalised Σ w_j q_j, Δs and f_mt
    blended likewise. One supervised hem pixel moves its whole neighbourhood coherently, and the MLP cost no
    longer grows with the Gaussian count. Starts at the identity (zero rotation and translation).
    """

    def __init__(self, num_nodes: int = 256, k: int = 4, radius: float = 1.0, **kwargs) -> None:
        super().__init__(**kwargs)
        if self.gaussian_code_dim:
            raise ValueError("deformer.gaussian_code_dim: per-Gaussian codes need the per-Gaussian decoder "
                             "(deformer=motion_trend), not the deformation graph")
        if num_nodes < 1 or k < 1:
            raise ValueError(f"deformer.num_nodes and deformer.k must be >= 1, got {num_nodes}, {k}")
        self.num_nodes, self.k, self.radius = int(num_nodes), int(k), float(radius)
        self.register_buffer("nodes", torch.zeros(self.num_nodes, 3))  # [K,3] canonical node positions
        self.register_buffer("sigma", torch.tensor(1.0))
        self.register_buffer("nodes_fitted", torch.tensor(0, dtype=torch.uint8))

    @torch.no_grad()
    def fit_nodes(self, points: torch.Tensor) -> None:
        """Place the nodes on a farthest-point sample of points [P,3]; σ from the mean nearest-node spacing."""
        idx = farthest_points(points.detach().float().cpu(), self.num_nodes).to(points.device)
        nodes = points.detach()[idx].to(self.nodes)
        self.nodes.zero_()
        self.nodes[: nodes.shape[0]] = nodes
        if nodes.shape[0] < self.num_nodes:  # fewer points than nodes: repeat the last (never nearest twice)
            self.nodes[nodes.shape[0]:] = nodes[-1]
        d = torch.cdist(nodes, nodes) + torch.eye(nodes.shape[0], device=nodes.device, dtype=nodes.dtype) * 1e9
        spacing = d.min(1).values.mean() if nodes.shape[0] > 1 else nodes.new_tensor(0.05)
        self.sigma.fill_(float(spacing) * self.radius)
        self.nodes_fitted.fill_(1)

    def forward(self, x_c: torch.Tensor, h_t: torch.Tensor, frame_idx: torch.Tensor | None = None,
                codes: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """x_c [N,3], h_t [B,H], frame_idx [B] | None -> dict(dx [B,N,3], ds [B,N,3], dq [B,N,4], f_mt [B,N,F]).
        codes: per-Gaussian codes, which the graph refuses at construction (always None here)."""
        if not bool(self.nodes_fitted):
            self.fit_nodes(x_c)
        return self.blend(x_c, super().forward(self.nodes, h_t, frame_idx))

    def blend(self, x_c: torch.Tensor, node_out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Per-node outputs (dx = t_j [B,K,3], ds [B,K,3], dq unit [B,K,4], f_mt [B,K,F]) -> per-Gaussian outputs."""
        # k nearest nodes of every Gaussian and their normalised RBF weights (distances carry no gradient to x_c:
        # the graph moves Gaussians, it is not moved by them).
        d2 = torch.cdist(x_c.detach(), self.nodes).square()  # [N,K]
        d2k, nn_idx = d2.topk(min(self.k, self.num_nodes), dim=1, largest=False)  # [N,k]
        w = torch.softmax(-d2k / (2 * self.sigma**2), dim=1)  # [N,k]
        g = self.nodes[nn_idx]  # [N,k,3]
        dq = node_out["dq"][:, nn_idx]  # [B,N,k,4]
        R = quat_to_matrix(dq)  # [B,N,k,3,3]
        local = (x_c[:, None, :] - g)[None, ..., None]  # [1,N,k,3,1]
        moved = (R @ local).squeeze(-1) + g[None] + node_out["dx"][:, nn_idx]  # [B,N,k,3]
        x_e = (w[None, ..., None] * moved).sum(2)  # [B,N,3]
        blend = lambda v: (w[None, ..., None] * v[:, nn_idx]).sum(2)  # noqa: E731  [B,K,D] -> [B,N,D]
        # Quaternions: align signs with the first neighbour's before averaging.
        sign = torch.sign((dq * dq[:, :, :1]).sum(-1, keepdim=True)).clamp(min=0) * 2 - 1
        q = F.normalize((w[None, ..., None] * dq * sign).sum(2), dim=-1)
        return {"dx": x_e - x_c, "ds": blend(node_out["ds"]), "dq": q, "f_mt": blend(node_out["f_mt"])}
