"""Canonical 3D Gaussians sampled on the body's canonical-pose surface: the avatar's learnable point set."""

from __future__ import annotations

import math

import torch
from torch import nn

from realityavatar.body.base import BodyModel
from realityavatar.geometry import sample_surface

# Order matters only for readability; density control and checkpoint resizing iterate over these names.
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "features")


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x / (1 - x))


class CanonicalGaussians(nn.Module):
    """N Gaussians in canonical space with position, log-scale, rotation (wxyz), opacity logit and a colour feature.

    The count N changes during training (density control) and when a checkpoint with a different count is
    loaded: a load_state_dict pre-hook resizes the parameters to the checkpoint's shapes first.
    """

    def __init__(
        self,
        body: BodyModel,
        num_points: int,
        feature_dim: int,
        init_scale: float | None,
        init_opacity: float,
        feature_init_std: float,
        seed: int,
    ) -> None:
        super().__init__()
        if num_points < 1:
            raise ValueError(f"gaussians.num_points: expected a positive count, got {num_points}")
        if feature_dim < 1:
            raise ValueError(f"gaussians.feature_dim: expected a positive size, got {feature_dim}")
        if not 0.0 < init_opacity < 1.0:
            raise ValueError(f"gaussians.init_opacity: expected a value in (0,1), got {init_opacity}")
        self.feature_dim = feature_dim
        self.param_names = PARAM_NAMES
        gen = torch.Generator().manual_seed(seed)
        verts = body.canonical_vertices().detach().float().cpu()  # [V,3]
        faces = body.faces.cpu()
        points = sample_surface(verts, faces, None, num_points, gen)[0]  # [N,3] uniform on the canonical surface
        if init_scale is None:
            # Uniform samples with density N/A lie about 0.5*sqrt(A/N) from their nearest neighbour.
            tri = verts[faces]
            area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1).sum() / 2
            init_scale = 0.5 * math.sqrt(float(area) / num_points)
        self.init_scale = float(init_scale)
        self.means = nn.Parameter(points)
        self.log_scales = nn.Parameter(torch.full((num_points, 3), math.log(self.init_scale)))
        quats = torch.zeros(num_points, 4)
        quats[:, 0] = 1.0
        self.quats = nn.Parameter(quats)
        self.opacity_logits = nn.Parameter(torch.full((num_points,), float(inverse_sigmoid(torch.tensor(init_opacity)))))
        self.features = nn.Parameter(torch.randn(num_points, feature_dim, generator=gen) * feature_init_std)
        self.register_load_state_dict_pre_hook(self._resize_to_checkpoint)

    @property
    def num_points(self) -> int:
        return self.means.shape[0]

    def scales(self) -> torch.Tensor:
        """[N,3] positive scales."""
        return self.log_scales.exp()

    def opacities(self) -> torch.Tensor:
        """[N] opacities in (0,1)."""
        return torch.sigmoid(self.opacity_logits)

    # ------------------------------------------------------------------ the source interface (model/avatar.py)
    def points(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The decoder moves every Gaussian: means [N,3], log-scales [N,3], quaternions [N,4]."""
        return self.means, self.log_scales, self.quats

    def move(self, dx: torch.Tensor, h_t: torch.Tensor) -> torch.Tensor:
        """The decoder's offsets [B,N,3] are the Gaussians' whole motion before skinning."""
        return dx

    def splats(self, posed: dict, inputs: dict) -> dict:
        """Each posed point is a Gaussian (inputs: deform's, unused)."""
        return posed

    def canonical(self) -> dict:
        return {"means": self.means, "quats": self.quats, "scales": torch.exp(self.log_scales),
                "opacities": self.opacities()}

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """One optimizer group per attribute, named like the parameters (they need different learning rates)."""
        return {name: [getattr(self, name)] for name in self.param_names}

    def replace(self, params: dict[str, torch.Tensor]) -> dict[str, tuple[nn.Parameter, nn.Parameter]]:
        """Swap in new tensors (same leading count for all) as fresh Parameters; returns {name: (old, new)}.

        Callers holding an optimizer must re-point it (density control does this).
        """
        swapped = {}
        for name, value in params.items():
            if name not in self.param_names:
                raise KeyError(f"CanonicalGaussians.replace: unknown parameter {name!r}; expected one of "
                               f"{self.param_names}")
            old = getattr(self, name)
            new = nn.Parameter(value.detach().to(device=old.device, dtype=old.dtype).contiguous(), requires_grad=old.requires_grad)
            setattr(self, name, new)
            swapped[name] = (old, new)
        counts = {getattr(self, n).shape[0] for n in self.param_names}
        if len(counts) != 1:
            raise ValueError(f"CanonicalGaussians.replace: parameters disagree on the Gaussian count: {counts}")
        return swapped

    def resize(self, n: int) -> None:
        """Re-allocate every parameter with n rows (values are placeholders, to be overwritten by a load)."""
        self.replace({name: getattr(self, name).new_zeros((n,) + getattr(self, name).shape[1:])
                      for name in self.param_names})

    def _resize_to_checkpoint(self, module, state_dict, prefix, local_metadata, strict, missing, unexpected, errors):
        key = prefix + "means"
        if key in state_dict and state_dict[key].shape[0] != self.num_points:
            n = state_dict[key].shape[0]
            for name in self.param_names:
                k = prefix + name
                if k in state_dict and state_dict[k].shape[0] != n:
                    raise ValueError(f"checkpoint field {k}: has {state_dict[k].shape[0]} rows but {key} has {n}")
            self.resize(n)

    def extra_repr(self) -> str:
        return f"num_points={self.num_points}, feature_dim={self.feature_dim}"
