"""`rasterize`: gsplat-1.5-style Gaussian splatting: pure-torch tiled backend, compiled CPU (numba) and gsplat (CUDA)."""
from __future__ import annotations

import contextlib
import os
import warnings
from pathlib import Path
from typing import Any

import torch

try:
    import fcntl
except ImportError:  # Windows: no build lock
    fcntl = None

from realityavatar.geometry import camera_centres

from .project import project_gaussians
from .sh import eval_sh
from .tiles import build_plan, composite_tiles

_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
_RASTER_MODES = ("classic", "antialiased")
_BACKENDS = ("auto", "torch", "gsplat", "numba")
_WHERE = "realityavatar/render/splat.py (rasterize)"
_gsplat_failure: str | None = None  # why gsplat could not be used (warned once)
_gsplat_module: Any = None
_gsplat_ran = False  # a first call has succeeded: from then on every gsplat error is the caller's to see


def _on_cuda(t: torch.Tensor) -> bool:
    """Whether gsplat can take this tensor (a seam: tests stand a fake gsplat in for CUDA on the CPU)."""
    return t.is_cuda


def _fail(field: str, expected: str, got: Any) -> None:
    raise ValueError(f"{_WHERE}: `{field}` expected {expected}, got {got}")


def _shape(t: Any) -> Any:
    return tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                  near, far, render_mode, rasterize_mode, check_finite):
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("colors", colors), ("viewmats", viewmats), ("Ks", Ks)):
        if not isinstance(t, torch.Tensor):
            _fail(name, "a torch.Tensor", type(t).__name__)
        if not t.is_floating_point():
            _fail(name, "a floating-point tensor", t.dtype)
    if means.dim() != 2 or means.shape[1] != 3:
        _fail("means", "shape [N,3]", _shape(means))
    N = means.shape[0]
    if quats.shape != (N, 4):
        _fail("quats", f"shape [N,4] = [{N},4] (wxyz)", _shape(quats))
    if scales.shape != (N, 3):
        _fail("scales", f"shape [N,3] = [{N},3]", _shape(scales))
    if opacities.shape != (N,):
        _fail("opacities", f"shape [N] = [{N}]", _shape(opacities))
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        _fail("viewmats", "shape [C,4,4] (world-to-camera)", _shape(viewmats))
    C = viewmats.shape[0]
    if C == 0:
        _fail("viewmats", "at least one camera", _shape(viewmats))
    if Ks.shape != (C, 3, 3):
        _fail("Ks", f"shape [C,3,3] = [{C},3,3]", _shape(Ks))
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            _fail(name, "a positive int", repr(v))
    if render_mode not in _RENDER_MODES:
        _fail("render_mode", f"one of {_RENDER_MODES}", repr(render_mode))
    if rasterize_mode not in _RASTER_MODES:
        _fail("rasterize_mode", f"one of {_RASTER_MODES}", repr(rasterize_mode))
    if not (0 <= float(near) < float(far)):
        _fail("near/far", "0 <= near < far", (near, far))
    if sh_degree is None:
        if not (colors.dim() == 2 and colors.shape[0] == N) and not (colors.dim() == 3 and colors.shape[:2] == (C, N)):
            _fail("colors", f"[N,D] = [{N},D] or [C,N,D] = [{C},{N},D] (or SH [N,K,3] with sh_degree)",
                  _shape(colors))
    else:
        if not 0 <= int(sh_degree) <= 3:
            _fail("sh_degree", "an int in 0..3", repr(sh_degree))
        k = (int(sh_degree) + 1) ** 2
        ok = (colors.dim() == 3 and colors.shape[0] == N) or (colors.dim() == 4 and colors.shape[:2] == (C, N))
        if not ok or colors.shape[-1] != 3 or colors.shape[-2] < k:
            _fail("colors", f"SH coefficients [N,K,3] or [C,N,K,3] with N={N}, K>={k}", _shape(colors))
    if backgrounds is not None:
        D = 3 if sh_degree is not None else colors.shape[-1]
        if not isinstance(backgrounds, torch.Tensor) or backgrounds.shape != (C, D):
            _fail("backgrounds", f"shape [C,D] = [{C},{D}] (colour channels only)", _shape(backgrounds))
    if check_finite:
        tensors = [("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                   ("colors", colors), ("viewmats", viewmats), ("Ks", Ks)]
        if backgrounds is not None:
            tensors.append(("backgrounds", backgrounds))
        # One flag per check, read from the device once: each host read of a CUDA tensor is a synchronisation.
        # A finite sum means finite entries (NaN and inf propagate), at a tenth of isfinite's cost.
        flags = [torch.isfinite(t.detach().sum()) for _, t in tensors] + [(quats.detach().norm(dim=-1) != 0).all()]
        ok = torch.stack([f.to(means.device) for f in flags])
        if not bool(ok.all()):  # the exact test (a sum of finite entries can overflow)
            for name, t in tensors:
                if not bool(torch.isfinite(t).all()):
                    _fail(name, "finite values", f"{int((~torch.isfinite(t)).sum())} NaN/inf entries")
            if not bool(flags[-1]):
                _fail("quats", "non-zero quaternions", "an all-zero row")


def _extensions_dir() -> Path:
    """Where torch JIT-builds extensions (gsplat builds into <this>/<py-cu tag>/gsplat_cuda)."""
    env = os.environ.get("TORCH_EXTENSIONS_DIR")
    return Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "torch_extensions"


@contextlib.contextmanager
def _build_lock():
    """Serialise gsplat's first-time JIT build across processes (SLURM arrays, joblib): gsplat 1.5 deletes its build
    directory before building, so two first-time builds clobber each other. The second waits, then loads."""
    if fcntl is None:
        yield
        return
    d = _extensions_dir()
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "realityavatar-gsplat.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _load_gsplat() -> Any:
    """Import gsplat and load (or JIT-build) its CUDA kernels once. Any failure is remembered and warned about once;
    the caller then uses the torch backend. `import gsplat` succeeds without kernels, so they are checked here."""
    global _gsplat_module
    if _gsplat_module is not None or _gsplat_failure is not None:
        return _gsplat_module
    try:
        import gsplat

        with _build_lock():
            from gsplat.cuda import _backend  # builds on first import when no prebuilt binary matches
        if getattr(_backend, "_C", None) is None:
            raise ImportError(_NO_KERNELS.format(version=getattr(gsplat, "__version__", "?"), torch=torch.__version__,
                                                 cuda=torch.version.cuda))
        ver = str(getattr(gsplat, "__version__", ""))
        if not ver.startswith("1.5."):
            warnings.warn(f"{_WHERE}: gsplat {ver or '(unknown version)'} is not 1.5.x; the torch backend mirrors 1.5's "
                          "rules, so the two backends may disagree", stacklevel=3)
        _gsplat_module = gsplat
    except Exception as exc:  # noqa: BLE001 - ImportError, or whatever the JIT build raised: fall back
        _gsplat_failed(exc, "unavailable")
    return _gsplat_module


_NO_KERNELS = ("gsplat {version} imports but its CUDA kernels are missing: no prebuilt binary for this torch "
               "({torch}, CUDA {cuda}) and the JIT build failed or found no CUDA toolkit (nvcc). Install nvcc of CUDA "
               "{cuda} (and set CUDA_HOME) or a gsplat wheel built for this torch; see docs/gpu.md")


def gsplat_status() -> str:
    """'ok' when gsplat's CUDA kernels load (building them if needed), else why not."""
    _load_gsplat()
    return "ok" if _gsplat_module is not None else str(_gsplat_failure)


def _gsplat_failed(exc: BaseException, what: str = "failed") -> None:
    global _gsplat_failure, _gsplat_module
    _gsplat_failure = f"{type(exc).__name__}: {exc}"
    _gsplat_module = None
    warnings.warn(f"{_WHERE}: gsplat {what} ({_gsplat_failure}); using the torch backend for the rest of this process",
                  stacklevel=3)


def rasterize(
    means: torch.Tensor,  # [N,3] world
    quats: torch.Tensor,  # [N,4] wxyz, need not be normalised
    scales: torch.Tensor,  # [N,3]
    opacities: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N,D] | [C,N,D] | SH [N,K,3] | [C,N,K,3] with sh_degree
    viewmats: torch.Tensor,  # [C,4,4] world-to-camera, OpenCV
    Ks: torch.Tensor,  # [C,3,3]
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,  # [C,D]
    background: Any = None,  # [D] list/tensor for every camera (the hydra config key); ignored if backgrounds given
    near: float = 0.01,
    far: float = 1e10,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    backend: str = "auto",
    tile_size: int | None = None,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    alpha_max: float = 0.999,
    chunk_elements: int = 1 << 18,
    tile_cull: bool = True,
    check_finite: bool = True,
    **gsplat_kwargs: Any,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render C cameras. Returns colours [C,H,W,D'], alphas [C,H,W,1] and `meta`, like gsplat.rasterization 1.5.

    meta: means2d [C,N,2] (grad retained), radii [C,N] int32 (max of the x/y half-extents, 0 = culled),
    radii_xy [C,N,2] (gsplat 1.5's per-axis radii), depths [C,N], conics [C,N,3], opacities [C,N] (after
    antialiasing compensation), visible [C,N] bool, backend ("torch" | "numba" | "gsplat"), plus tile statistics.
    backend="auto": gsplat for float32 CUDA tensors when its kernels load, numba for CPU tensors where numba
    imports, else torch.
    `tile_size` defaults to 8 for torch, 32 for numba, 16 for gsplat; `alpha_max`, `chunk_elements` and `tile_cull` tune the torch backend; gsplat's own extra options
    go through `gsplat_kwargs` (ignored by the torch backend).
    """
    if backgrounds is None and background is not None:
        bg = torch.as_tensor(background, dtype=means.dtype, device=means.device)
        D = 3 if sh_degree is not None else colors.shape[-1]
        if bg.dim() != 1 or bg.shape[0] != D:
            _fail("background", f"a list of {D} values (one per colour channel)", tuple(bg.shape))
        backgrounds = bg[None].expand(viewmats.shape[0], D)
    if backend not in _BACKENDS:
        _fail("backend", f"one of {_BACKENDS}", repr(backend))
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                  near, far, render_mode, rasterize_mode, check_finite)
    if gsplat_kwargs.pop("packed", False):
        _fail("packed", "False (meta is indexed [C,N] for densification; packed output is not)", True)
    use_gsplat = backend == "gsplat" or (backend == "auto" and _on_cuda(means))
    if use_gsplat and not _on_cuda(means):
        if backend == "gsplat":
            warnings.warn(f"{_WHERE}: backend='gsplat' needs CUDA tensors; using the torch backend", stacklevel=2)
        use_gsplat = False
    inputs = (means, quats, scales, opacities, colors, viewmats, Ks)
    if use_gsplat and any(t.dtype != torch.float32 for t in inputs):
        if backend == "gsplat":
            _fail("means/quats/scales/opacities/colors/viewmats/Ks", "float32 for backend='gsplat' (its kernels are "
                  "float32 only; backend='auto' renders other dtypes with torch)", sorted({str(t.dtype) for t in inputs}))
        use_gsplat = False
    if use_gsplat and means.shape[0] > 0 and _load_gsplat() is not None:
        global _gsplat_ran
        try:
            out = _rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                    sh_degree=sh_degree, backgrounds=backgrounds, near=near, far=far,
                                    render_mode=render_mode, rasterize_mode=rasterize_mode, tile_size=tile_size,
                                    eps2d=eps2d, radius_clip=radius_clip, **gsplat_kwargs)
            _gsplat_ran = True
            return out
        except (AttributeError, ImportError, OSError) as exc:
            # Only a first call can fail from a broken build (kernels missing a symbol, a library not found);
            # afterwards, and for any RuntimeError (CUDA OOM, bad input), the error is real and surfaces.
            if _gsplat_ran:
                raise
            _gsplat_failed(exc)
    return _rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                            composite=_cpu_compositor(backend, means), sh_degree=sh_degree,
                            backgrounds=backgrounds, near=near, far=far,
                            render_mode=render_mode, rasterize_mode=rasterize_mode, tile_size=tile_size,
                            eps2d=eps2d, radius_clip=radius_clip, alpha_max=alpha_max,
                            chunk_elements=chunk_elements, tile_cull=tile_cull)


def _cpu_compositor(backend: str, means: torch.Tensor) -> str:
    """'numba' (compiled CPU kernels, numba_backend.py) for backend='numba', or 'auto' on CPU tensors, where numba
    imports; else 'torch'. auto on CUDA tensors that gsplat could not take (float64, broken build) stays on torch."""
    if backend == "auto" and (_on_cuda(means) or means.is_cuda):
        return "torch"
    if backend not in ("numba", "auto") or means.is_cuda:
        if backend == "numba":
            warnings.warn(f"{_WHERE}: backend='numba' needs CPU tensors; using the torch backend", stacklevel=3)
        return "torch"
    from .numba_backend import NUMBA_ERROR

    if NUMBA_ERROR is not None and backend == "numba":
        warnings.warn(f"{_WHERE}: numba unavailable ({NUMBA_ERROR}); using the torch backend", stacklevel=3)
    return "torch" if NUMBA_ERROR is not None else "numba"


def _sh_colors(colors, sh_degree, means, viewmats, C):
    campos = camera_centres(viewmats)  # [C,3]
    dirs = means[None, :, :] - campos[:, None, :]  # [C,N,3]
    coeffs = colors if colors.dim() == 4 else colors[None].expand(C, *colors.shape)
    return torch.clamp_min(eval_sh(int(sh_degree), coeffs, dirs) + 0.5, 0.0)  # [C,N,3]


def _rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                     backgrounds, near, far, render_mode, rasterize_mode, tile_size, eps2d, radius_clip,
                     alpha_max, chunk_elements, tile_cull, composite="torch"):
    C = viewmats.shape[0]
    if composite == "numba":
        from .numba_backend import project_gaussians_numba as project
    else:
        project = project_gaussians
    proj = project(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                   eps2d=eps2d, radius_clip=radius_clip, antialiased=rasterize_mode == "antialiased")
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()  # densification reads meta["means2d"].grad (gsplat's absgrad=False)

    if sh_degree is not None:
        cols = _sh_colors(colors, sh_degree, means, viewmats, C)
    else:
        cols = colors if colors.dim() == 3 else colors[None].expand(C, *colors.shape)  # [C,N,D]
    bg = backgrounds
    if render_mode in ("RGB+D", "RGB+ED"):
        cols = torch.cat([cols, proj.depths[..., None]], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, bg.new_zeros(C, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        cols = proj.depths[..., None]
        if bg is not None:
            bg = bg.new_zeros(C, 1)

    # Measured fastest each (10k Gaussians, 256², forward + backward, 1 thread): torch 8; numba 32, which was
    # 24.4 / 23.5 / 22.5 ms at 16 / 24 / 32 px tiles in one interleaved run (64: faster with 1 thread, not with 2).
    ts = (32 if composite == "numba" else 8) if tile_size is None else int(tile_size)
    if composite == "numba":
        from .numba_backend import composite_numba

        img, alphas, stats = composite_numba(means2d, proj.conics, proj.opacities, cols.to(means2d.dtype),
                                             proj.depths, proj.radii_xy, width, height, tile_size=ts,
                                             alpha_max=alpha_max, tile_cull=tile_cull)
    else:
        plan = build_plan(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.radii_xy, width, height,
                          tile_size=ts, chunk_elements=chunk_elements, tile_cull=tile_cull)
        img, alphas = composite_tiles(means2d, proj.conics, proj.opacities, cols.to(means2d.dtype), plan,
                                      width, height, alpha_max=alpha_max)
        stats = {"tile_size": plan.tile_size, "tile_pairs": plan.pairs, "padded_elements": plan.elements,
                 "n_chunks": len(plan.chunks)}
    if bg is not None:
        img = img + (1.0 - alphas) * bg[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        img = torch.cat([img[..., :-1], img[..., -1:] / alphas.clamp(min=1e-10)], dim=-1)

    meta = {
        "means2d": means2d,
        "radii": proj.radii_xy.amax(-1),
        "radii_xy": proj.radii_xy,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": proj.opacities,
        "visible": proj.visible,
        "compensations": proj.compensations,
        "colors": cols,
        "width": width,
        "height": height,
        "n_cameras": C,
        **stats,
        "backend": composite,
    }
    return img, alphas, meta


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                      backgrounds, near, far, render_mode, rasterize_mode, tile_size, eps2d, radius_clip,
                      **kwargs):
    gsplat = _gsplat_module
    img, alphas, info = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near, far_plane=far, sh_degree=sh_degree, backgrounds=backgrounds, render_mode=render_mode,
        rasterize_mode=rasterize_mode, tile_size=16 if tile_size is None else int(tile_size),
        eps2d=eps2d, radius_clip=radius_clip, packed=False, **kwargs,
    )
    meta = dict(info)
    radii = meta["radii"]
    radii_xy = radii if radii.dim() == 3 else torch.stack([radii, radii], -1)
    meta["radii_xy"] = radii_xy
    meta["radii"] = radii_xy.amax(-1)
    vis = (radii_xy > 0).all(-1)  # [C,N]
    meta["visible"] = vis
    # gsplat leaves culled entries uninitialised; zero them as the torch backend does. means2d keeps its identity
    # (densification reads its .grad) and is saved for backward, so it is zeroed through .data: the kernels never
    # read culled entries, and autograd's version check must not see this write.
    for k in ("depths", "conics", "opacities", "compensations"):
        t = meta.get(k)
        if isinstance(t, torch.Tensor) and t.shape[:2] == vis.shape:
            meta[k] = torch.where(vis.view(*vis.shape, *([1] * (t.dim() - 2))), t, torch.zeros_like(t))
    meta["means2d"].data.masked_fill_(~vis[..., None], 0.0)
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    meta["backend"] = "gsplat"
    return img, alphas, meta
