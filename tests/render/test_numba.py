"""The numba CPU backend against the torch backend (values, gradients, meta) and the dense reference."""
from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from realityavatar.render import rasterize
from realityavatar.render.reference import human_scene, rasterize_reference
from tests.render.scenes import CONF, F64, gradcheck_gaussians, look_at, random_scene, single_gaussian

nb = pytest.importorskip("realityavatar.render.numba_backend")
if nb.NUMBA_ERROR is not None:
    pytest.skip(f"numba unavailable: {nb.NUMBA_ERROR}", allow_module_level=True)


def _run(backend, args, w, h, seed=0, **kw):
    """Forward + backward of a random weighting of every output; returns outputs, input grads and meta."""
    params = [t.clone().requires_grad_() for t in args[:5]]
    img, alpha, meta = rasterize(*params, *args[5:7], w, h, backend=backend, **kw)
    g = torch.Generator().manual_seed(seed)
    loss = (img * torch.rand(img.shape, generator=g, dtype=img.dtype)).sum()
    loss = loss + (alpha * torch.rand(alpha.shape, generator=g, dtype=img.dtype)).sum()
    loss.backward()
    grads = {n: p.grad for n, p in zip(("means", "quats", "scales", "opacities", "colors"), params)}
    grads["means2d"] = meta["means2d"].grad
    return img, alpha, grads, meta


def _assert_same(a, b, tol_val, tol_grad):
    img_t, alpha_t, g_t, meta_t = a
    img_n, alpha_n, g_n, meta_n = b
    assert meta_n["backend"] == "numba" and meta_t["backend"] == "torch"
    assert (img_t - img_n).abs().max() <= tol_val
    assert (alpha_t - alpha_n).abs().max() <= tol_val
    for name in g_t:
        if g_t[name] is None:  # colours are unused in the depth-only modes
            assert g_n[name] is None
            continue
        scale = max(1.0, g_t[name].abs().max().item())
        err = (g_t[name] - g_n[name]).abs().max().item()
        assert err <= tol_grad * scale, f"{name}: {err:.3g} (scale {scale:.3g})"
    assert torch.equal(meta_t["radii"], meta_n["radii"])
    if meta_t["tile_size"] == meta_n["tile_size"]:  # defaults differ: 8 (torch), 32 (numba)
        assert meta_t["tile_pairs"] == meta_n["tile_pairs"]  # same exact tile-ellipse culling
    assert torch.equal(meta_t["visible"], meta_n["visible"])
    for k in ("means2d", "depths", "conics", "opacities"):  # projection: compiled, float64 inside
        ref = meta_t[k].detach()
        assert (ref - meta_n[k].detach()).abs().max() <= tol_val * max(1.0, ref.abs().max().item())


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("n,cams,w,h,tile_size,alpha_max", [
    (150, 2, 40, 32, 8, 0.999),  # multi-tile, edge tiles cut by the image border
    (300, 1, 64, 48, 16, 0.99),
    (60, 3, 23, 17, 8, 0.999),  # image not a multiple of the tile
    (1, 1, 8, 8, 8, 0.999),  # one tile
])
def test_numba_matches_torch_backend(mode, n, cams, w, h, tile_size, alpha_max):
    args = random_scene(n, seed=n + cams, cams=cams, w=w, h=h)
    bg = torch.rand(cams, 3, dtype=F64)
    kw = {"rasterize_mode": mode, "backgrounds": bg, "tile_size": tile_size, "alpha_max": alpha_max,
          "render_mode": "RGB+ED"}
    _assert_same(_run("torch", args, w, h, **kw), _run("numba", args, w, h, **kw), 1e-12, 1e-10)


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_numba_matches_dense_reference(mode):
    means, quats, scales, op, colors, vms, Ks, w, h = random_scene(150, seed=3, cams=2)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.5, 0.0]], dtype=F64)
    img, alpha, _ = rasterize(means, quats, scales, op, colors, vms, Ks, w, h, rasterize_mode=mode,
                              backgrounds=bg, backend="numba")
    ref, ref_alpha, _ = rasterize_reference(means, quats, scales, op, colors, vms, Ks, w, h,
                                            rasterize_mode=mode, backgrounds=bg)
    assert (img - ref).abs().max() < 1e-12 and (alpha - ref_alpha).abs().max() < 1e-12
    assert (1 - ref_alpha).min() < 1e-3  # early termination is exercised


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_numba_gradcheck(mode):
    means, quats, scales, op, colors = gradcheck_gaussians()

    vms = look_at((0, -3, 0), (0, 0, 0))[None]
    Ks = torch.tensor([[18.0, 0, 3.4], [0, 18.0, 2.9], [0, 0, 1]], dtype=F64)[None]

    def f(m, q, s, o, c):
        img, alpha, _ = rasterize(m, q, s, o, c, vms, Ks, 9, 6, rasterize_mode=mode, backend="numba",
                                  render_mode="RGB+ED", backgrounds=torch.tensor([[0.3, 0.1, 0.2]], dtype=F64))
        return img, alpha

    assert torch.autograd.gradcheck(f, (means, quats, scales, op, colors), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_numba_alpha_clamp_and_single_gaussian():
    means, quats, scales, _, colors, vms, Ks, w, h = single_gaussian(x=0.01, y=0.01)
    for amax in (0.99, 0.999):
        args = (means, quats, scales, torch.ones(1, dtype=F64), colors, vms, Ks)
        _, alpha, _ = rasterize(*args, w, h, alpha_max=amax, backend="numba")
        assert alpha.max().item() == pytest.approx(amax, abs=1e-12)
        _assert_same(_run("torch", args, w, h, alpha_max=amax), _run("numba", args, w, h, alpha_max=amax),
                     1e-12, 1e-10)


def test_numba_empty_and_culled_scenes():
    z = torch.zeros
    bg = torch.tensor([[0.2, 0.4, 0.6]])
    vms, Ks = torch.eye(4)[None], torch.tensor([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]])[None]
    img, alpha, meta = rasterize(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), vms, Ks, 16, 12, backgrounds=bg,
                                 backend="numba")
    assert meta["backend"] == "numba" and meta["tile_pairs"] == 0
    assert img.shape == (1, 12, 16, 3) and torch.allclose(img, bg.expand(12, 16, 3)[None]) and (alpha == 0).all()
    means = torch.tensor([[0.0, 0, -1]], requires_grad=True)
    img, alpha, _ = rasterize(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1), torch.ones(1),
                              torch.ones(1, 3), vms, Ks, 16, 12, background=[0.2, 0.4, 0.6], backend="numba")
    assert torch.allclose(img, bg.expand(12, 16, 3)[None]) and (alpha == 0).all()
    img.sum().backward()
    assert (means.grad == 0).all()


@pytest.mark.parametrize("mode", ["D", "ED", "RGB+D"])
def test_numba_depth_modes(mode):
    args = random_scene(50, seed=4)
    kw = {"render_mode": mode}
    _assert_same(_run("torch", args, 40, 32, **kw), _run("numba", args, 40, 32, **kw), 1e-12, 1e-10)


def test_numba_float32_human_scene_and_threads():
    args = human_scene(3000, 128)
    t = _run("torch", args, 128, 128)
    n1 = _run("numba", args, 128, 128)
    assert (t[0] - n1[0]).abs().max() < 1e-4 and (t[1] - n1[1]).abs().max() < 1e-4
    for name in t[2]:
        rel = (t[2][name] - n1[2][name]).norm() / t[2][name].norm()
        assert rel < 1e-4, name
    assert (t[3]["radii"] != n1[3]["radii"]).float().mean() < 1e-3
    # one tile per thread and per-slot gradients: bit-identical results with 2 threads
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        n2 = _run("numba", args, 128, 128)
    finally:
        torch.set_num_threads(old)
    assert torch.equal(n1[0], n2[0]) and all(torch.equal(n1[2][k], n2[2][k]) for k in n1[2])


def test_numba_config_and_auto():
    args = random_scene(20, seed=0, dtype=torch.float32)
    cfg = {**OmegaConf.to_container(OmegaConf.load(CONF / "default.yaml")), "backend": "numba"}
    img, _, meta = rasterize(*args, **cfg)
    assert meta["backend"] == "numba" and img.dtype == torch.float32
    assert math.isfinite(nb.warm_up())


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_numba_projection_matches_torch(mode):
    """Every projection output and its gradients, including compensations and Gaussians behind the camera."""
    from realityavatar.render.project import project_gaussians

    args = list(random_scene(200, seed=1, cams=3))
    args[0] = args[0].clone()
    args[0][:5, 1] = 4.0  # behind two of the cameras
    args[1] = args[1].clone()
    args[1][5] = 0.0  # a zero quaternion (F.normalize's eps branch)
    out = {}
    for name, fn in (("torch", project_gaussians), ("numba", nb.project_gaussians_numba)):
        p = [t.clone().requires_grad_() for t in args[:4]]
        pr = fn(*p, *args[5:7], args[7], args[8], 0.01, 1e10, antialiased=mode == "antialiased", radius_clip=0.5)
        g = torch.Generator().manual_seed(0)
        outs = [pr.means2d, pr.conics, pr.depths, pr.opacities] + ([pr.compensations] if mode == "antialiased" else [])
        sum((o * torch.rand(o.shape, generator=g, dtype=F64)).sum() for o in outs).backward()
        out[name] = (outs, pr.radii_xy, pr.visible, [x.grad for x in p])
    (o_t, r_t, v_t, g_t), (o_n, r_n, v_n, g_n) = out["torch"], out["numba"]
    assert torch.equal(r_t, r_n) and torch.equal(v_t, v_n) and (~v_t).any()
    for a, b in zip(o_t + g_t, o_n + g_n):
        assert (a - b).abs().max() <= 1e-12 * max(1.0, a.abs().max().item())


def test_numba_inline_exp_matches_libm():
    """The compositing kernels' inline exp (glibc's algorithm) against libm's, over the arguments they pass it; then
    _exp_sigma, which evaluates sigma and takes its exp in one loop: -1 where the sigma test fails, NaN passed on."""
    import numba
    import numpy as np

    @numba.njit
    def exp_core(v):
        out = np.empty_like(v)
        for i in range(v.shape[0]):
            out[i] = nb._exp_core(v[i])
        return out

    rng = np.random.default_rng(0)
    x = np.concatenate([np.linspace(-700.0, 0.0, 100_001), -rng.exponential(2.0, 200_000),
                        -rng.uniform(0.0, 1e-3, 10_000), [0.0, -0.0, -1e-300, -5e-324, -699.9]])
    ref = np.array([math.exp(v) for v in x])  # libm
    fast = exp_core(x)
    # glibc's x86-64 FMA build gives the same bits; other libms (or glibc without FMA) may round differently
    ulps = np.abs(fast - ref) / np.spacing(ref)
    assert ulps.max() <= 1.0 and (ulps == 0).mean() > 0.999

    A, B, Cc = 1.0, 3.0, 1.0  # not positive definite: sigma < 0 along dx = -dy
    dx = rng.uniform(-6.0, 6.0, 61)
    dy = rng.uniform(-6.0, 6.0, 61)
    dx[:3], dy[:3] = [1.0, np.nan, 0.0], [-1.0, 0.0, 0.0]
    sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy  # the kernels' expression, same rounding
    for thr in (20.0, 800.0):  # the inline exp (thr < 700) and libm's
        ev = np.full(64, 7.0)  # padded to whole 8-wide vectors
        nb._exp_sigma(np.append(dx, [9.0] * 3), np.append(dy, [9.0] * 3), 61, A, B, Cc, thr, ev)
        ok = (sigma >= 0.0) & (sigma <= thr)
        assert ok.any() and (~ok & ~np.isnan(sigma)).any() and (sigma < 0).any()
        assert np.allclose(ev[:61][ok], np.exp(-sigma[ok]), rtol=1e-15, atol=0.0)
        assert (ev[:61][~ok & ~np.isnan(sigma)] == -1.0).all() and np.isnan(ev[1])
