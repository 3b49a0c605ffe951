"""Tests of the splat renderer: dense-reference agreement, gradients, analytic footprint, culling, batching, errors."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from omegaconf import OmegaConf

import realityavatar.render.splat as rast_mod
from realityavatar.geometry import camera_centres
from realityavatar.render import eval_sh, rasterize, sh_basis
from realityavatar.render.reference import human_scene, rasterize_reference
from tests.render.scenes import CONF, F64, gradcheck_gaussians, look_at, random_scene, single_gaussian


def _ref_projection(means, quats, scales, op, vms, Ks, w, h, mode):
    return rasterize_reference(means, quats, scales, op, torch.zeros(means.shape[0], 1, dtype=means.dtype), vms, Ks,
                               w, h, rasterize_mode=mode)[2]


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("alpha_max,tile_size,chunk", [(0.999, 8, 1 << 20), (0.99, 16, 1 << 20), (0.999, 8, 256)])
def test_matches_dense_reference(mode, alpha_max, tile_size, chunk):
    means, quats, scales, op, colors, vms, Ks, w, h = random_scene(150, seed=3, cams=2)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.5, 0.0]], dtype=F64)
    img, alpha, meta = rasterize(means, quats, scales, op, colors, vms, Ks, w, h, rasterize_mode=mode,
                                 backgrounds=bg, alpha_max=alpha_max, tile_size=tile_size, chunk_elements=chunk,
                                 backend="torch")  # the numba backend: tests/render/test_numba.py
    ref, ref_alpha, _ = rasterize_reference(means, quats, scales, op, colors, vms, Ks, w, h,
                                            rasterize_mode=mode, backgrounds=bg, alpha_max=alpha_max)
    assert img.shape == (2, h, w, 3) and alpha.shape == (2, h, w, 1)
    assert (img - ref).abs().max() < 1e-6
    assert (alpha - ref_alpha).abs().max() < 1e-6
    # the scene really exercises early termination: some pixels end with T < 1e-3 (only reachable near 1e-4 stop)
    assert (1 - ref_alpha).min() < 1e-3
    if chunk == 256:
        assert meta["n_chunks"] > 1
    # screen-space means, depths and radii agree with the reference's projection from the equations
    proj = _ref_projection(means, quats, scales, op, vms, Ks, w, h, mode)
    assert torch.allclose(meta["means2d"].detach(), proj.means2d, atol=1e-9)
    assert torch.equal(meta["radii_xy"].to(torch.int32), proj.radii_xy) and torch.equal(meta["visible"], proj.visible)
    # the matrix form of the reference agrees with the literal per-pixel loop
    dense, _, _ = rasterize_reference(means, quats, scales, op, colors, vms, Ks, w, h, rasterize_mode=mode,
                                                backgrounds=bg, alpha_max=alpha_max, method="matrix")
    assert (dense - ref).abs().max() < 1e-9


def test_alpha_clamp_is_hit():
    # one opaque Gaussian centred on a pixel centre: alpha there is exactly alpha_max
    means, quats, scales, _, colors, vms, Ks, w, h = single_gaussian(x=0.01, y=0.01)  # u, v = 32.5, 24.5
    for amax in (0.99, 0.999):
        _, alpha, _ = rasterize(means, quats, scales, torch.ones(1, dtype=F64), colors, vms, Ks, w, h,
                                alpha_max=amax)
        assert alpha.max().item() == pytest.approx(amax, abs=1e-12)


@pytest.mark.parametrize("backend", ["torch", "auto"])  # auto: numba on CPU where it imports
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gradcheck(mode, backend):
    means, quats, scales, op, colors = gradcheck_gaussians(cameras=2)  # per-camera colours
    vms = torch.stack([look_at((0, -3, 0), (0, 0, 0)), look_at((1, -2.8, 0.3), (0, 0, 0))])
    Ks = torch.tensor([[18.0, 0, 8.3], [0, 18.0, 7.6], [0, 0, 1]], dtype=F64)[None].repeat(2, 1, 1)

    def f(m, q, s, o, c):
        img, alpha, _ = rasterize(m, q, s, o, c, vms, Ks, 16, 14, rasterize_mode=mode, render_mode="RGB+ED",
                                  backend=backend)
        return img, alpha

    inputs = (means, quats, scales, op, colors)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)

    # the full Jacobian on one small camera (slow mode checks every output entry)
    def f1(m, q, s, o, c):
        img, alpha, _ = rasterize(m, q, s, o, c[0], vms[:1], Ks[:1], 7, 6, rasterize_mode=mode, backend=backend)
        return img, alpha

    Ks[:, :2, 2] = torch.tensor([3.4, 2.9], dtype=F64)
    assert torch.autograd.gradcheck(f1, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_single_gaussian_analytic_footprint(mode):
    x, y, z, s, f = 0.1, -0.05, 2.0, 0.02, 100.0
    means, quats, scales, op, colors, vms, Ks, w, h = single_gaussian(x, y, z, s, f)
    img, alpha, meta = rasterize(means, quats, scales, op, colors, vms, Ks, w, h, rasterize_mode=mode,
                                 render_mode="RGB+ED")
    u, v = f * x / z + w / 2, f * y / z + h / 2
    var0 = (f * s / z) ** 2  # EWA: isotropic 3D Gaussian at the optical axis plane -> isotropic 2D
    # off-axis the Jacobian adds a small anisotropy; compute it exactly for the check
    J = torch.tensor([[f / z, 0, -f * x / z**2], [0, f / z, -f * y / z**2]], dtype=F64)
    cov = J @ (s**2 * torch.eye(3, dtype=F64)) @ J.T + 0.3 * torch.eye(2, dtype=F64)
    o = 0.8
    if mode == "antialiased":
        cov0 = cov - 0.3 * torch.eye(2, dtype=F64)
        o *= math.sqrt(torch.det(cov0) / torch.det(cov))
    assert var0 < cov[0, 0] < var0 + 0.31
    ys, xs = torch.meshgrid(torch.arange(h, dtype=F64) + 0.5, torch.arange(w, dtype=F64) + 0.5, indexing="ij")
    d = torch.stack([xs - u, ys - v], -1)
    sigma = 0.5 * torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d)
    a = o * torch.exp(-sigma)
    a = torch.where(a >= 1 / 255, a, torch.zeros_like(a))
    assert torch.allclose(alpha[0, ..., 0], a, atol=1e-12)
    assert torch.allclose(img[0, ..., :3], a[..., None] * colors[0], atol=1e-12)
    # expected depth is the camera z wherever the Gaussian is seen
    seen = a > 0
    assert torch.allclose(img[0, ..., 3][seen], torch.full_like(img[0, ..., 3][seen], z), atol=1e-9)
    assert torch.allclose(meta["means2d"][0, 0], torch.tensor([u, v], dtype=F64))
    assert meta["depths"][0, 0].item() == pytest.approx(z)
    extend = min(3.33, math.sqrt(2 * math.log(o * 255)))
    assert meta["radii_xy"][0, 0].tolist() == [math.ceil(extend * math.sqrt(cov[0, 0])),
                                                math.ceil(extend * math.sqrt(cov[1, 1]))]
    assert meta["radii"][0, 0].item() == max(meta["radii_xy"][0, 0].tolist())
    assert torch.allclose(meta["conics"][0, 0], torch.linalg.inv(cov)[[0, 0, 1], [0, 1, 1]])


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_anisotropic_rotated_gaussian_analytic_footprint(mode):
    """A flat, rotated Gaussian on the optical axis: its image ellipse follows from geometry alone.

    q = q_z(θ) ⊗ q_x(90°): the local x axis (σ = sx) stays in the image plane at angle θ from the image x axis, the
    local y axis turns into the viewing direction (σ = sy, invisible), the local z axis into the image direction
    θ + 90° (σ = sz). So the 2D covariance is (f/z)² (sx² d1 d1ᵀ + sz² d2 d2ᵀ) + 0.3 I, d1 = (cos θ, sin θ),
    d2 = (-sin θ, cos θ) (image y points down). A transposed rotation, a swapped quaternion order or a wrong
    camera transform tilts the ellipse the other way or shows the wrong axis.
    """
    z, f, w, h, theta = 2.0, 100.0, 64, 48, math.radians(30)
    sx, sy, sz = 0.12, 0.3, 0.03
    ct, st, c45, s45 = math.cos(theta / 2), math.sin(theta / 2), math.cos(math.pi / 4), math.sin(math.pi / 4)
    quat = torch.tensor([[ct * c45, ct * s45, st * s45, st * c45]], dtype=F64)  # Hamilton product, worked by hand
    means = torch.tensor([[0.0, 0.0, z]], dtype=F64)
    scales = torch.tensor([[sx, sy, sz]], dtype=F64)
    colors = torch.tensor([[0.2, 0.5, 0.9]], dtype=F64)
    vms, Ks = torch.eye(4, dtype=F64)[None], torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=F64)[None]
    img, alpha, meta = rasterize(means, quat, scales, torch.tensor([0.9], dtype=F64), colors, vms, Ks, w, h,
                                 rasterize_mode=mode)
    d1 = torch.tensor([math.cos(theta), math.sin(theta)], dtype=F64)
    d2 = torch.tensor([-math.sin(theta), math.cos(theta)], dtype=F64)
    cov0 = (f / z) ** 2 * (sx**2 * torch.outer(d1, d1) + sz**2 * torch.outer(d2, d2))
    cov = cov0 + 0.3 * torch.eye(2, dtype=F64)
    o = 0.9 * (math.sqrt(torch.det(cov0) / torch.det(cov)) if mode == "antialiased" else 1.0)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=F64) + 0.5, torch.arange(w, dtype=F64) + 0.5, indexing="ij")
    d = torch.stack([xs - w / 2, ys - h / 2], -1)
    a = o * torch.exp(-0.5 * torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d))
    a = torch.where(a >= 1 / 255, a, torch.zeros_like(a))
    assert torch.allclose(alpha[0, ..., 0], a, atol=1e-12)
    assert torch.allclose(img[0], a[..., None] * colors[0], atol=1e-12)
    assert torch.allclose(meta["conics"][0, 0], torch.linalg.inv(cov)[[0, 0, 1], [0, 1, 1]])
    # the long axis runs down-right in the image (θ = +30°): the pixel 10 px along d1 is brighter than along d2
    assert alpha[0, int(h / 2 + 10 * d1[1]), int(w / 2 + 10 * d1[0]), 0] > 10 * alpha[0, int(h / 2 + 10 * d2[1]), int(w / 2 + 10 * d2[0]), 0]


def test_reference_projection_is_written_from_the_equations():
    """The dense reference must not share the projection under test (a common bug would pass both)."""
    import inspect

    import realityavatar.render.reference as ref

    assert "project_gaussians" not in inspect.getsource(ref)


def test_culling_near_far_and_behind():
    means = torch.tensor([[0.0, 0, -2.0], [0, 0, 0.005], [0, 0, 50.0], [0, 0, 2.0]], dtype=F64)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1)
    scales = torch.full((n, 3), 0.05, dtype=F64)
    op = torch.full((n,), 0.9, dtype=F64)
    colors = torch.eye(4, 3, dtype=F64)
    vms = torch.eye(4, dtype=F64)[None]
    Ks = torch.tensor([[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]], dtype=F64)[None]
    img, alpha, meta = rasterize(means, quats, scales, op, colors, vms, Ks, 32, 32, near=0.01, far=10.0)
    assert meta["visible"][0].tolist() == [False, False, False, True]
    assert (meta["radii"][0] > 0).tolist() == [False, False, False, True]
    assert (meta["means2d"][0, :3] == 0).all()
    # only the last (blue-less zero colour row) Gaussian shows: the image is its colour times alpha
    assert torch.allclose(img[0], alpha[0] * colors[3], atol=1e-12)
    # moving it past `far` removes everything
    means2 = means.clone()
    means2[3, 2] = 20.0
    _, alpha2, meta2 = rasterize(means2, quats, scales, op, colors, vms, Ks, 32, 32, near=0.01, far=10.0)
    assert alpha2.abs().max() == 0 and not meta2["visible"].any()


def test_batch_equals_separate_calls():
    means, quats, scales, op, _, vms, Ks, w, h = random_scene(80, seed=5, cams=3)
    cols = torch.rand(3, 80, 3, dtype=F64)
    params = [t.clone().requires_grad_() for t in (means, quats, scales, op, cols)]
    img, alpha, meta = rasterize(*params, vms, Ks, w, h, render_mode="RGB+D")
    (img.square().sum() + alpha.sum()).backward()
    for c in range(3):
        p1 = [t.clone().requires_grad_() for t in (means, quats, scales, op, cols[c])]
        img1, alpha1, meta1 = rasterize(*p1, vms[c : c + 1], Ks[c : c + 1], w, h, render_mode="RGB+D")
        assert torch.allclose(img[c : c + 1], img1, atol=1e-12) and torch.allclose(alpha[c : c + 1], alpha1, atol=1e-12)
        assert torch.equal(meta["radii"][c : c + 1], meta1["radii"])
        (img1.square().sum() + alpha1.sum()).backward()
        assert torch.allclose(meta["means2d"].grad[c : c + 1], meta1["means2d"].grad, atol=1e-10)
        assert torch.allclose(params[4].grad[c], p1[4].grad, atol=1e-10)


def test_means2d_grad_for_densification():
    args = [t.clone().requires_grad_() if i < 5 else t for i, t in enumerate(random_scene(60, seed=2)[:7])]
    img, _, meta = rasterize(*args, 40, 32)
    img.sum().backward()
    g = meta["means2d"].grad
    assert g is not None and g.shape == (1, 60, 2)
    vis = meta["visible"][0]
    assert (g[0, ~vis] == 0).all() and g[0, vis].abs().sum() > 0
    assert meta["radii"].dtype == torch.int32 and meta["radii"].shape == (1, 60)


def test_empty_scene_renders_background():
    z = torch.zeros
    bg = torch.tensor([[0.2, 0.4, 0.6]])
    vms, Ks = torch.eye(4)[None], torch.tensor([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]])[None]
    img, alpha, meta = rasterize(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), vms, Ks, 16, 12, backgrounds=bg)
    assert img.shape == (1, 12, 16, 3) and torch.allclose(img, bg.expand(12, 16, 3)[None])
    assert (alpha == 0).all() and meta["means2d"].shape == (1, 0, 2)
    # every Gaussian behind the camera: also just the background
    img, alpha, _ = rasterize(torch.tensor([[0.0, 0, -1]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
                              torch.ones(1), torch.ones(1, 3), vms, Ks, 16, 12, background=[0.2, 0.4, 0.6])
    assert torch.allclose(img, bg.expand(12, 16, 3)[None]) and (alpha == 0).all()


@pytest.mark.parametrize(
    "change,field",
    [
        (lambda a: a.__setitem__(0, torch.zeros(5, 2)), "means"),
        (lambda a: a.__setitem__(1, torch.zeros(5, 3)), "quats"),
        (lambda a: a.__setitem__(3, torch.zeros(5, 1)), "opacities"),
        (lambda a: a.__setitem__(4, torch.zeros(2, 5, 3)), "colors"),
        (lambda a: a.__setitem__(5, torch.eye(4)), "viewmats"),
        (lambda a: a.__setitem__(6, torch.eye(3)[None].repeat(2, 1, 1)), "Ks"),
        (lambda a: a[0].__setitem__((1, 2), float("nan")), "means"),
        (lambda a: a[2].__setitem__((0, 0), float("inf")), "scales"),
        (lambda a: a[1].__setitem__(2, 0.0), "quats"),
    ],
)
def test_bad_inputs_raise_clear_errors(change, field):
    args = [torch.rand(5, 3), torch.rand(5, 4) + 0.1, torch.rand(5, 3), torch.rand(5), torch.rand(5, 3),
            torch.eye(4)[None], torch.eye(3)[None]]
    change(args)
    with pytest.raises(ValueError, match=rf"rasterize\): `{field}`"):
        rasterize(*args, 8, 8)


def test_bad_options_raise():
    args = [torch.rand(5, 3), torch.rand(5, 4), torch.rand(5, 3), torch.rand(5), torch.rand(5, 3),
            torch.eye(4)[None], torch.eye(3)[None]]
    for kw, field in [({"render_mode": "RGBD"}, "render_mode"), ({"rasterize_mode": "aa"}, "rasterize_mode"),
                      ({"backend": "cuda"}, "backend"), ({"backgrounds": torch.zeros(1, 4)}, "backgrounds")]:
        with pytest.raises(ValueError, match=field):
            rasterize(*args, 8, 8, **kw)
    with pytest.raises(ValueError, match="width"):
        rasterize(*args, 0, 8)


def test_sh_basis_orthonormal_and_rasterize_sh():
    # Fibonacci sphere quadrature: the real SH basis is orthonormal over the sphere
    n = 20000
    i = torch.arange(n, dtype=F64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    dirs = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1)
    B = sh_basis(3, dirs * 2.5)  # unnormalised input is normalised
    gram = 4 * math.pi * B.T @ B / n
    assert torch.allclose(gram, torch.eye(16, dtype=F64), atol=2e-3)
    # the gsplat sign convention for degree 1: -C1*y, C1*z, -C1*x
    assert torch.allclose(sh_basis(1, torch.tensor([[1.0, 0, 0]], dtype=F64))[0, 1:],
                          torch.tensor([0, 0, -0.4886025119029199], dtype=F64))
    # rasterize with SH equals rasterize with the colours the SH evaluate to (+0.5, clamped at 0)
    means, quats, scales, op, _, vms, Ks, w, h = random_scene(40, seed=9, cams=2)
    sh = torch.randn(40, 16, 3, dtype=F64) * 0.3
    img, _, _ = rasterize(means, quats, scales, op, sh, vms, Ks, w, h, sh_degree=3)
    campos = camera_centres(vms)
    cols = torch.clamp_min(eval_sh(3, sh[None], means[None] - campos[:, None]) + 0.5, 0)
    img2, _, _ = rasterize(means, quats, scales, op, cols, vms, Ks, w, h)
    assert torch.allclose(img, img2, atol=1e-12)
    with pytest.raises(ValueError, match="colors"):
        rasterize(means, quats, scales, op, sh[:, :4], vms, Ks, w, h, sh_degree=3)


@pytest.mark.parametrize("mode", ["D", "ED", "RGB+D"])
def test_depth_modes(mode):
    means, quats, scales, op, colors, vms, Ks, w, h = random_scene(50, seed=4)
    img, _, meta = rasterize(means, quats, scales, op, colors, vms, Ks, w, h, render_mode=mode)
    dref, aref, _ = rasterize_reference(means, quats, scales, op, meta["depths"][0][:, None], vms, Ks, w, h)
    depth = img[..., -1:]
    expect = dref / aref.clamp(min=1e-10) if mode == "ED" else dref
    assert torch.allclose(depth, expect, atol=1e-9)
    assert img.shape[-1] == (4 if mode == "RGB+D" else 1)


def test_configs_are_rasterize_kwargs():
    from realityavatar.config import RENDER_BACKENDS, check_settings

    means, quats, scales, op, colors, vms, Ks, w, h = random_scene(20, seed=0, dtype=torch.float32)
    default = OmegaConf.to_container(OmegaConf.load(CONF / "default.yaml"))
    assert {"backend", "rasterize_mode", "near", "far", "tile_size", "background"} <= set(default)
    assert set(RENDER_BACKENDS) == set(rast_mod._BACKENDS)  # what the config accepts is what rasterize takes
    with pytest.raises(ValueError, match=r"render\.backend='gspalt': expected one of auto, numba, torch, gsplat"):
        check_settings(OmegaConf.create({"render": {**default, "backend": "gspalt"}}))
    for name in ("torch", "gsplat", "auto"):
        cfg = {**default, "backend": name}  # render.backend=<name>
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            img, _, meta = rasterize(means, quats, scales, op, colors, vms, Ks, w, h, **cfg)
        # auto on CPU: the compiled numba kernels where numba imports, else the torch backend
        expect = {"torch": "torch", "gsplat": "torch", "auto": "numba" if _has_numba() else "torch"}[name]
        assert meta["backend"] == expect and img.dtype == torch.float32
        # render.backend=gsplat on CPU tensors falls back to torch, and says so; torch and auto fall back silently by design
        fell_back = [r for r in rec if "backend='gsplat' needs CUDA" in str(r.message)]
        assert len(fell_back) == (1 if name == "gsplat" else 0), (name, [str(r.message) for r in rec])


def _has_numba():
    from realityavatar.render.numba_backend import NUMBA_ERROR

    return NUMBA_ERROR is None


def test_gsplat_fallback_warns_once(monkeypatch):
    monkeypatch.setattr(rast_mod, "_gsplat_failure", None)
    monkeypatch.setattr(rast_mod, "_gsplat_module", None)
    monkeypatch.setitem(__import__("sys").modules, "gsplat", None)  # import gsplat -> ImportError
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert rast_mod._load_gsplat() is None
        assert rast_mod._load_gsplat() is None
    assert len([r for r in rec if "gsplat unavailable" in str(r.message)]) == 1


def test_float32_close_to_float64():
    a64 = random_scene(200, seed=7, cams=1, w=64, h=48)
    a32 = [t.float() if isinstance(t, torch.Tensor) else t for t in a64]
    img64, _, _ = rasterize(*a64)
    img32, _, _ = rasterize(*a32)
    assert (img64.float() - img32).abs().mean() < 1e-5 and (img64.float() - img32).abs().max() < 1e-2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.gpu
def test_torch_backend_on_cuda():
    a = random_scene(100, seed=1, cams=2)
    cpu, _, _ = rasterize(*a, backend="torch")
    gpu, _, _ = rasterize(*[t.cuda() if isinstance(t, torch.Tensor) else t for t in a], backend="torch")
    assert (cpu - gpu.cpu()).abs().max() < 1e-9


def _has_gsplat():
    # `import gsplat` succeeds without a CUDA toolkit; gsplat_status loads (or builds) the kernels themselves
    return torch.cuda.is_available() and rast_mod.gsplat_status() == "ok"


@pytest.mark.gpu
@pytest.mark.skipif(not _has_gsplat(), reason="needs CUDA and gsplat")
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_torch_matches_gsplat(mode):
    args = human_scene(5000, 256, device="cuda")
    t_img, t_alpha, t_meta = rasterize(*args, 256, 256, backend="torch", rasterize_mode=mode, render_mode="RGB+ED")
    g_img, g_alpha, g_meta = rasterize(*args, 256, 256, backend="gsplat", rasterize_mode=mode, render_mode="RGB+ED")
    assert g_meta["backend"] == "gsplat"
    assert (t_img[..., :3] - g_img[..., :3]).abs().mean() < 1e-4
    assert (t_alpha - g_alpha).abs().mean() < 1e-4
    assert torch.equal(t_meta["radii"], g_meta["radii"].to(t_meta["radii"].dtype)) or \
        (t_meta["radii"] != g_meta["radii"]).float().mean() < 1e-3
