"""The gsplat path without a GPU (a fake gsplat: build failures fall back once, other errors surface, float64 is
decided before the call), the host reads of the input checks; plus `gpu` tests that run where CUDA is."""

from __future__ import annotations

import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

import realityavatar.render.splat as rast_mod
from realityavatar.render import rasterize
from realityavatar.render.reference import human_scene
from tests.render.scenes import random_scene


def _scene(n=30, dtype=torch.float32):
    return human_scene(n, 32, dtype=dtype)


def _fake_gsplat(root: Path, kernels: bool = True) -> None:
    """A package named gsplat: imports like the real one, `cuda._backend._C` is None when the 'build' failed."""
    pkg = root / "gsplat"
    (pkg / "cuda").mkdir(parents=True)
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        __version__ = "1.5.3"
        calls = []
        raise_on_call = None


        def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                          packed, **kw):
            calls.append(means.dtype)
            if raise_on_call is not None:
                raise raise_on_call
            from gsplat.cuda._backend import _C
            _C.fully_fused_projection_fwd  # no toolkit: AttributeError on NoneType, as in gsplat 1.5.3
            from realityavatar.render.splat import _rasterize_torch
            kw.pop("sh_degree")
            opts = dict(alpha_max=0.999, chunk_elements=1 << 18, tile_cull=True)
            img, alpha, meta = _rasterize_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                                sh_degree=None, near=near_plane, far=far_plane, **kw, **opts)
            vis = meta["visible"]
            info = {k: meta[k].clone() for k in ("depths", "conics", "opacities")}
            info["means2d"] = meta["means2d"]
            info["radii"] = meta["radii_xy"]
            for k in ("depths", "conics", "opacities"):  # gsplat leaves culled entries uninitialised
                info[k][~vis] = float("nan")
            return img, alpha, info
    '''))
    (pkg / "cuda" / "__init__.py").write_text("")
    (pkg / "cuda" / "_backend.py").write_text(textwrap.dedent(f'''
        import fcntl, os
        lock = os.path.join(os.environ["TORCH_EXTENSIONS_DIR"], "realityavatar-gsplat.lock")
        held_during_build = False
        os.makedirs(os.path.dirname(lock), exist_ok=True)
        try:
            with open(lock, "a") as f:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            held_during_build = True  # another open file description holds it: our build lock
        _C = {"type('C', (), {'fully_fused_projection_fwd': 1})()" if kernels else "None"}
    '''))


@pytest.fixture
def fake_gsplat(tmp_path, monkeypatch):
    def make(kernels: bool = True):
        _fake_gsplat(tmp_path / "pkgs", kernels)
        monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
        monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
        for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
            monkeypatch.delitem(sys.modules, name)
        monkeypatch.setattr(rast_mod, "_gsplat_failure", None)
        monkeypatch.setattr(rast_mod, "_gsplat_module", None)
        monkeypatch.setattr(rast_mod, "_gsplat_ran", False)
        monkeypatch.setattr(rast_mod, "_on_cuda", lambda t: True)  # the fake stands in for CUDA
        import gsplat

        return gsplat

    yield make
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        sys.modules.pop(name, None)


@pytest.mark.parametrize("broken", ["no_kernels", "first_call"])
def test_gsplat_without_toolkit_falls_back_once(fake_gsplat, broken):
    # `import gsplat` works without nvcc; gsplat 1.5.3's first kernel call then raises AttributeError on NoneType
    gs = fake_gsplat(kernels=broken != "no_kernels")
    if broken == "first_call":
        gs.raise_on_call = AttributeError("'NoneType' object has no attribute 'fully_fused_projection_fwd' (CUDA "
                                          "kernels not built: is nvcc installed?)")
    args = _scene()
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        _, _, meta = rasterize(*args, 32, 32, backend="gsplat")
        _, _, meta2 = rasterize(*args, 32, 32, backend="gsplat")
    assert meta["backend"] == meta2["backend"] == "torch"
    msgs = [str(r.message) for r in rec if "gsplat" in str(r.message)]
    assert len(msgs) == 1 and "CUDA" in msgs[0] and "nvcc" in msgs[0]
    assert len(gs.calls) <= 1


def test_gsplat_runtime_errors_surface_and_do_not_switch_it_off(fake_gsplat):
    gs = fake_gsplat()
    args = _scene()
    _, _, meta = rasterize(*args, 32, 32, backend="gsplat")
    assert meta["backend"] == "gsplat"
    gs.raise_on_call = RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB")
    with pytest.raises(RuntimeError, match="out of memory"):
        rasterize(*args, 32, 32, backend="gsplat")
    gs.raise_on_call = None
    _, _, meta = rasterize(*args, 32, 32, backend="auto")
    assert meta["backend"] == "gsplat", "one error switched gsplat off for the whole process"


def test_gsplat_float64_is_decided_before_the_call(fake_gsplat):
    gs = fake_gsplat()
    args64 = _scene(dtype=torch.float64)
    _, _, meta = rasterize(*args64, 32, 32, backend="auto")  # auto: the backend that can take float64
    assert meta["backend"] == "torch" and not gs.calls
    with pytest.raises(ValueError, match="float32"):
        rasterize(*args64, 32, 32, backend="gsplat")
    _, _, meta = rasterize(*_scene(), 32, 32, backend="auto")
    assert meta["backend"] == "gsplat"


def test_gsplat_meta_masks_culled_entries_and_rejects_packed(fake_gsplat):
    fake_gsplat()
    means, *rest = _scene()
    means = means.clone()
    means[:5, 1] = -10.0  # behind the camera: culled
    _, _, meta = rasterize(means, *rest, 32, 32, backend="gsplat")
    assert meta["backend"] == "gsplat" and not meta["visible"][0, :5].any()
    for k in ("depths", "conics", "opacities"):
        assert torch.isfinite(meta[k]).all(), k
    with pytest.raises(ValueError, match="packed"):
        rasterize(*_scene(), 32, 32, backend="gsplat", packed=True)


def test_gsplat_build_holds_a_lock(fake_gsplat):
    """Concurrent first-time JIT builds (array jobs) take turns: the kernels load under an inter-process lock."""
    fake_gsplat()
    rasterize(*_scene(), 32, 32, backend="gsplat")
    import gsplat.cuda._backend as backend

    assert backend.held_during_build


def test_check_finite_reads_the_device_once(monkeypatch):
    """Each host read of a CUDA tensor is a sync; the input checks do one, not one per tensor."""
    reads = []
    for name in ("__bool__", "item"):
        orig = getattr(torch.Tensor, name)

        def counted(self, _orig=orig):
            reads.append(1)
            return _orig(self)

        monkeypatch.setattr(torch.Tensor, name, counted)
    args = _scene()
    rast_mod._check_inputs(*args, 32, 32, None, None, 0.01, 1e10, "RGB", "classic", True)
    assert len(reads) <= 1


def _gsplat_usable() -> bool:
    return torch.cuda.is_available() and rast_mod.gsplat_status() == "ok"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_torch_backend_forward_and_backward_on_cuda_match_cpu():
    a = random_scene(200, seed=1, cams=2, dtype=torch.float32)
    out = {}
    for dev in ("cpu", "cuda"):
        # fresh leaves per device: .to('cpu') of a CPU tensor is the tensor itself, and requires_grad_ on it would
        # make the CUDA copies non-leaves (grad None)
        params = [t.detach().clone().to(dev).requires_grad_() for t in a[:5]]
        img, alpha, meta = rasterize(*params, *[t.to(dev) for t in a[5:7]], *a[7:], backend="torch")
        (img.square().sum() + alpha.sum()).backward()
        out[dev] = [img, alpha, meta["means2d"].grad, *[p.grad for p in params]]
    for c, g in zip(out["cpu"], out["cuda"]):
        assert torch.allclose(c, g.cpu(), atol=1e-4, rtol=1e-3)


@pytest.mark.gpu
@pytest.mark.skipif(not _gsplat_usable(), reason="needs CUDA and a working gsplat")
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gsplat_matches_torch_images_alphas_and_means2d_grads(mode):
    args = human_scene(5000, 256, device="cuda")
    gout = torch.rand(1, 256, 256, 3, device="cuda")
    res = {}
    for backend in ("torch", "gsplat"):
        params = [t.clone().requires_grad_() for t in args[:5]]
        img, alpha, meta = rasterize(*params, *args[5:], 256, 256, backend=backend, rasterize_mode=mode)
        assert meta["backend"] == backend
        ((img * gout).sum() + alpha.sum()).backward()
        res[backend] = (img, alpha, meta["means2d"].grad, meta["visible"], params[0].grad)
    (ti, ta, tg, tv, tm), (gi, ga, gg, gv, gm) = res["torch"], res["gsplat"]
    assert (ti - gi).abs().mean() < 1e-4 and (ta - ga).abs().mean() < 1e-4
    both = tv & gv
    assert (tv != gv).float().mean() < 1e-3
    rel = (tg[both] - gg[both]).norm() / gg[both].norm()
    assert rel < 1e-2, f"means2d gradients differ by {float(rel):.3g} (relative)"
    assert (tm - gm).norm() / gm.norm() < 1e-2
