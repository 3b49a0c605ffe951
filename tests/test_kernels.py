"""The fused CPU kernels (realityavatar.kernels) equal the reference paths they replace, in values and gradients."""
from __future__ import annotations

import pytest
import torch
from kornia.losses import ssim_loss

from realityavatar import kernels
from realityavatar.geometry import axis_angle_to_matrix, matrix_to_quat, quat_to_matrix
from realityavatar.kernels import dssim, polar_rotation

needs_numba = pytest.mark.skipif(kernels.NUMBA_ERROR is not None, reason=f"numba: {kernels.NUMBA_ERROR}")


@needs_numba
@pytest.mark.parametrize("shape", [(1, 3, 64, 64), (2, 3, 37, 23), (1, 1, 12, 80)])
@pytest.mark.parametrize("near", [False, True])
def test_dssim_numba_equals_kornia(shape, near):
    g = torch.Generator().manual_seed(1)
    y = torch.rand(*shape, generator=g)
    x = torch.rand(*shape, generator=g)
    if near:  # the regime of training: prediction close to the target, SSIM near 1
        x = 0.9 * y + 0.1 * x
    x_ref = x.clone().requires_grad_()
    ref = ssim_loss(x_ref, y, window_size=11)
    (g_ref,) = torch.autograd.grad(ref, x_ref)
    x_new = x.clone().requires_grad_()
    out = dssim(x_new, y, backend="numba")
    (g_new,) = torch.autograd.grad(out * 3.0, x_new)  # upstream gradient scales the saved one
    torch.testing.assert_close(out, ref.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g_new, 3.0 * g_ref, rtol=1e-4, atol=1e-4 * float(g_ref.abs().max()))


@needs_numba
def test_dssim_numba_on_a_permuted_view_and_without_grad():
    """Training passes pred.permute(0, 3, 1, 2): a non-contiguous view; evaluation calls it without a graph."""
    g = torch.Generator().manual_seed(2)
    pred = torch.rand(1, 30, 40, 3, generator=g, requires_grad=True)
    gt = torch.rand(1, 30, 40, 3, generator=g)
    out = dssim(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2), backend="numba")
    out.backward()
    ref_pred = pred.detach().clone().requires_grad_()
    ssim_loss(ref_pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2), 11).backward()
    torch.testing.assert_close(pred.grad, ref_pred.grad, rtol=1e-4, atol=1e-8)
    with torch.no_grad():
        torch.testing.assert_close(dssim(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2)), out.detach())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dssim_torch_path_equals_kornia_in_fewer_operations(dtype):
    """The path without Numba (a GPU's): kornia's D-SSIM with its five blurs stacked into one, equal in value and
    gradient, in fewer than half of kornia's forward operations (each a kernel launch on a GPU)."""
    from realityavatar.runtime import OpCount

    g = torch.Generator().manual_seed(3)
    y = torch.rand(2, 3, 37, 23, generator=g, dtype=dtype)
    x = (0.9 * y + 0.1 * torch.rand(2, 3, 37, 23, generator=g, dtype=dtype)).requires_grad_()
    ref = ssim_loss(x, y, window_size=11)
    (g_ref,) = torch.autograd.grad(ref, x)
    with OpCount() as ours:
        out = dssim(x, y, backend="torch")
    with OpCount() as theirs:
        ssim_loss(x, y, window_size=11)
    (g_new,) = torch.autograd.grad(out, x)
    tol = 1e-6 if dtype == torch.float32 else 1e-9  # the taps are float32 (as the Numba kernel's)
    torch.testing.assert_close(out, ref.detach(), rtol=tol, atol=tol)
    torch.testing.assert_close(g_new, g_ref, rtol=1e-4, atol=1e-5 * float(g_ref.abs().max()))
    assert ours.total < theirs.total / 2, (ours.total, theirs.total)


def test_dssim_falls_back_and_refuses_clearly():
    x = torch.rand(1, 3, 16, 16, requires_grad=True)
    y = torch.rand(1, 3, 16, 16, requires_grad=True)
    # y needing a gradient: the fused kernel only differentiates x, so auto takes the torch path and both get
    # gradients
    dssim(x, y).backward()
    assert y.grad is not None and x.grad is not None
    with pytest.raises(RuntimeError, match="backend=numba"):
        dssim(x, y, backend="numba")
    with pytest.raises(ValueError, match="dssim backend"):
        dssim(x, y.detach(), backend="fast")


def _svd_polar(M: torch.Tensor) -> torch.Tensor:
    U, _, Vh = torch.linalg.svd(M)
    return U @ Vh


def _newton_polar(M: torch.Tensor) -> torch.Tensor:
    """Autograd through Newton's iteration run to convergence (float64): the reference gradient. (The SVD's
    gradient is NaN here: a blend of two rotations has two equal singular values; the polar factor's is not.)"""
    return kernels._polar_newton_torch(M, 30)


def _blends(n: int, seed: int) -> torch.Tensor:
    """Blends of two bone rotations (what LBS produces): shrunk, non-orthogonal, det > 0."""
    g = torch.Generator().manual_seed(seed)
    Ra = axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=torch.float64) * 1.2)
    Rb = axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=torch.float64) * 1.2)
    w = torch.rand(n, 1, 1, generator=g, dtype=torch.float64) * 0.8 + 0.1
    M = w * Ra + (1 - w) * Rb
    return M[torch.linalg.det(M) > 0.05]


@pytest.mark.parametrize("numba_path", [True, False])
def test_polar_rotation_values_and_gradient_equal_the_converged_reference(numba_path, monkeypatch):
    if numba_path and kernels.NUMBA_ERROR is not None:
        pytest.skip(f"numba: {kernels.NUMBA_ERROR}")
    if not numba_path:
        monkeypatch.setattr(kernels, "NUMBA_ERROR", "forced torch path")
    M = _blends(200, 0)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    Mr = M.clone().requires_grad_()
    ref = _newton_polar(Mr)
    (g_ref,) = torch.autograd.grad((ref * G).sum(), Mr)
    torch.testing.assert_close(ref.detach(), _svd_polar(M), rtol=0, atol=1e-9)
    Mn = M.clone().requires_grad_()
    R = polar_rotation(Mn)
    (g_new,) = torch.autograd.grad((R * G).sum(), Mn)
    torch.testing.assert_close(R, ref.detach(), rtol=0, atol=1e-9)
    torch.testing.assert_close(g_new, g_ref, rtol=1e-6, atol=1e-8)


def test_polar_torch_path_converges_on_blends_far_from_a_rotation(monkeypatch):
    """The torch path (a GPU's: 6 Newton steps, the first scaled by |det|^(-1/3)) on blends of two rotations 150-175
    degrees apart, det below 0.05: the converged rotation to float32 precision (the plain iteration is ~5e-3 off
    after 6 steps there)."""
    monkeypatch.setattr(kernels, "NUMBA_ERROR", "forced torch path")
    g = torch.Generator().manual_seed(7)
    n = 4000
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = (150 + 25 * torch.rand(n, 1, generator=g, dtype=torch.float64)) * torch.pi / 180
    Ra = axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=torch.float64))
    M = 0.5 * (Ra + Ra @ axis_angle_to_matrix(axis * angle))
    M = M[torch.linalg.det(M) < 0.05]
    assert len(M) > 100
    R = polar_rotation(M.float())
    torch.testing.assert_close(R.double(), _newton_polar(M), rtol=0, atol=2e-6)


def test_polar_rotation_gradcheck_and_float32():
    M = _blends(12, 4).requires_grad_()
    assert torch.autograd.gradcheck(polar_rotation, (M,))
    M32 = _blends(50, 5).float()
    R = polar_rotation(M32)
    assert R.dtype == torch.float32
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3).expand_as(R), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="polar_rotation backend"):
        polar_rotation(M32, backend="svd")


def test_matrix_to_quat_round_trip_and_gradient_over_all_branches():
    """Rotations near each of the four branches (w, x, y, z largest), including angles near 180 degrees."""
    g = torch.Generator().manual_seed(6)
    aa = torch.randn(400, 3, generator=g, dtype=torch.float64)
    aa = aa / aa.norm(dim=-1, keepdim=True) * torch.rand(400, 1, generator=g, dtype=torch.float64) * 3.1
    R = axis_angle_to_matrix(aa)
    q = matrix_to_quat(R)
    torch.testing.assert_close(quat_to_matrix(q), R, atol=1e-9, rtol=0)
    assert (q[:, 0] >= 0).all()
    Rg = R[:8].clone().requires_grad_()
    assert torch.autograd.gradcheck(matrix_to_quat, (Rg,))


def test_decoder_condition_as_first_layer_bias_equals_the_concatenated_input():
    """The decoder adds h_t's projection as the first layer's bias per sample: same as x-part + h-part, for B = 2."""
    from realityavatar.model.deform import MotionTrendDecoder

    torch.manual_seed(0)
    dec = MotionTrendDecoder(cond_dim=8, hidden_dim=16, num_layers=3, feature_dim=4, num_freqs=2,
                             bbox_min=(-1.2, -1.5, -1.2), bbox_max=(1.2, 1.0, 1.2), auto_bounds=True, activation="silu")
    x = torch.rand(50, 3)
    h = torch.randn(2, 8)
    out = dec(x, h)
    u = (x - dec.bbox_min) / (dec.bbox_max - dec.bbox_min) * 2 - 1
    z = torch.nn.functional.silu(dec.in_x(dec.encoding(u))[None] + dec.in_h(h)[:, None])
    o = dec.out(dec.hidden(z))
    torch.testing.assert_close(out["dx"], o[..., :3])
    torch.testing.assert_close(out["f_mt"], o[..., 10:])


def test_the_networks_and_losses_compile_whole(monkeypatch):
    """torch.compile of Avatar.deform and .shade and of the losses (benchmarks/step.py --compile, the GPU's lever
    against its launch count): dynamo breaks the networks' graph only at the LSTM, which it runs eagerly by default
    (with compile_path's settings it traces the LSTM too: one graph), and traces every loss term as one graph. The polar rotation's numba call, the device-constant cache (runtime.constant), the
    D-SSIM's numba call and the silhouette's k-d tree each broke them before; a break costs a graph and a round of
    launches. The skinning term drew its surface pool at the first call until e57a89a: in training that call broke the
    graph inside total_loss's loop, and dynamo ran total_loss eagerly from then on (LossTerm.bind draws it now).
    No graph takes a module-level host tensor as an input: twelve did until runtime.Table, each copied to the GPU
    with a wait at every call (the compiled step's 13 syncs on an H200), and CUDA graphs skip such a graph."""
    module, make_batch = _model_at_fit_start(monkeypatch)
    batch = make_batch()

    def networks(b):
        posed = module.avatar.deform(b)
        return module.avatar.shade(posed, b["viewmat"], b["frame_idx"]), posed["means"]

    from realityavatar.model.module import DYNAMO_CONFIG

    torch._dynamo.reset()
    with torch._dynamo.config.patch(allow_rnn=False):  # dynamo's default
        ex = torch._dynamo.explain(networks)(batch)
    reasons = [str(r.reason).splitlines()[0] for r in ex.break_reasons]
    assert reasons and all("LSTM" in r for r in reasons), reasons  # dynamo's default: the LSTM eager
    assert ex.graph_count <= 3, (ex.graph_count, reasons)
    torch._dynamo.reset()
    with torch._dynamo.config.patch(**DYNAMO_CONFIG):  # compile_path's settings: the LSTM traced too
        ex = torch._dynamo.explain(networks)(batch)
    assert ex.graph_count == 1 and not ex.break_reasons, [str(r.reason).splitlines()[0] for r in ex.break_reasons]
    assert not _global_inputs(ex)

    from realityavatar.losses import TrainingRender

    rgb, alpha, _, posed = module.avatar.render_batch(batch)
    out = TrainingRender(rgb, alpha, batch, posed, module)
    ex = torch._dynamo.explain(module.loss)(out)  # the first call, as in training: nothing drawn while tracing
    assert ex.graph_count == 1 and not ex.break_reasons, [str(r.reason).splitlines()[0] for r in ex.break_reasons]
    assert not _global_inputs(ex)


def _global_inputs(ex) -> list[str]:
    """The inputs of explain's graphs that dynamo took from a module's globals (it names them g_...): a module-level
    tensor, which a GPU copies from the host at every call (with a wait) and which makes CUDA graphs skip the graph
    (runtime.Table holds such constants)."""
    return [n.name for g in ex.graphs for n in g.graph.nodes if n.op == "placeholder" and n.name.startswith("g_")]


def _model_at_fit_start(monkeypatch):
    """The default model as training starts it (its body grids built, on_fit_start), stepping without a Trainer
    (tests/helpers.py stepping_module; log steps every 25), and its batch maker."""
    from realityavatar.body import build_body
    from tests.helpers import stepping_module

    module, make_batch = stepping_module(build_body("mannequin"), monkeypatch, "cpu", 25, "gaussians.num_points=300",
                                         "render.backend=numba", "skinning.voxel_size=0.1", "shading.voxel_size=0.1")
    module.on_fit_start()
    return module, make_batch


def test_compiled_graphs_take_no_host_scalars_as_training_steps_advance(monkeypatch):
    """In training the step changes every call: the decoder's coarse-to-fine window and the loss terms' scheduled
    weights follow it (set_progress). No compiled graph may take a Python number or a 0-d host tensor as an input
    for it: dynamo made the window's alpha such an input after its first change (a host scalar per call; CUDA graphs
    skip the graph). The window's weights and the skinning term's weight are device buffers set outside the graphs."""
    from realityavatar.model.module import DYNAMO_CONFIG

    module, make_batch = _model_at_fit_start(monkeypatch)
    graphs: dict[str, list[list[str]]] = {}

    def recording(name):
        def backend(gm, inputs):
            names = [n.name for n in gm.graph.nodes if n.op == "placeholder"]
            graphs.setdefault(name, []).append(
                [n for n, x in zip(names, inputs)  # a module's buffer moves with the module: on a GPU it is there
                 if (not torch.is_tensor(x) or x.dim() == 0) and "_buffers_" not in n])
            return gm.forward
        return backend

    torch._dynamo.reset()
    with torch._dynamo.config.patch(**DYNAMO_CONFIG):
        for owner, name in ((module.avatar, "deform"), (module.avatar, "shade"), (module, "loss")):
            setattr(owner, name, torch.compile(getattr(owner, name), backend=recording(name)))
        for s in range(2, 6):  # the window opens a little at every step (schedule.deform_anneal); no log step
            module._test_step = s
            module.training_step(make_batch(), 0)
    torch._dynamo.reset()
    assert 0 < module.avatar.deformer.encoding.alpha < module.avatar.deformer.encoding.num_freqs
    assert len(graphs["deform"]) == 1 and len(graphs["shade"]) == 1, {k: len(v) for k, v in graphs.items()}
    assert all(not scalars for g in graphs.values() for scalars in g), graphs
