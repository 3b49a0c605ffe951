"""The LightningModule's wiring: posing end to end, optimizer groups, frozen metric networks, checkpoints."""

from __future__ import annotations

import contextlib

import pytest
import torch

from realityavatar.config import compose
from realityavatar.data.random_batch import make_batch_fn
from tests.helpers import NUM_POINTS, TRAINED_RUN, stepping_module


@pytest.fixture(scope="module")
def body():
    from realityavatar.body import build_body

    return build_body("mannequin")


@pytest.mark.slow
def test_canonical_gaussians_land_on_the_posed_body_after_skinning_prefit(body):
    """Posing end to end (module.avatar.deform -> skinning field -> canonical_transforms -> LBS, then render_batch): after
    the skinning pre-fit, the initial canonical Gaussians of a random pose lie on that pose's body surface and
    render where the posed mesh projects."""
    from realityavatar.build import build_module

    cfg = compose(["gaussians.num_points=3000", "silhouette=none"])
    module = build_module(cfg, body, num_train_frames=2, scene_extent=1.0)
    module.on_fit_start()  # the skinning pre-fit (schedule.skin_pretrain_steps)
    g = torch.Generator().manual_seed(7)
    pose = torch.randn(24, 3, generator=g) * 0.35
    pose[0] = torch.tensor([0.3, 2.0, -0.2])  # turned and tilted root
    transl = torch.tensor([0.4, -0.1, 0.7])
    verts = body.posed_vertices(pose, transl)  # [V,3] ground truth: the body's own LBS
    poses = torch.stack([0.2 * pose, 0.5 * pose, pose])[None]  # a window ending in the pose: its current frame
    transls = torch.stack([transl - 0.3, transl - 0.1, transl])[None]
    with torch.no_grad():
        posed = module.avatar.deform(module.avatar.pose_inputs(poses, transls))
    d_canon = torch.cdist(module.avatar.gaussians.means, body.canonical_vertices()).min(-1).values  # [N]
    d_posed = torch.cdist(posed["means"][0], verts).min(-1).values
    # distance gained by posing: 0 for a perfect LBS; the learnt weights blur near joints (measured: median ~0,
    # 95% 1.1 cm, max 9 cm). A wrong bone transform or an unfitted field moves limbs by tens of centimetres.
    excess = (d_posed - d_canon).detach()
    q50, q95, top = float(excess.median()), float(torch.quantile(excess, 0.95)), float(excess.max())
    assert q50 < 0.003 and q95 < 0.02 and top < 0.15, (q50, q95, top)
    # render_batch from a camera 3 m in front of the posed body: the alpha covers the posed mesh's projection
    centre = verts.mean(0)
    R = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # OpenCV camera on the +z side looking back along -z, y up
    E = torch.eye(4)
    E[:3, :3], E[:3, 3] = R, -R @ (centre + torch.tensor([0.0, 0.0, 3.0]))
    S = 64
    K = torch.tensor([[60.0, 0, S / 2], [0, 60.0, S / 2], [0, 0, 1]])
    batch = {**module.avatar.pose_inputs(poses, transls), "frame_idx": torch.tensor([0]), "viewmat": E[None], "K": K[None],
             "width": torch.tensor([S]), "height": torch.tensor([S])}
    with torch.no_grad():
        _, alpha, _, _ = module.avatar.render_batch(batch)
    cam = verts @ R.T + E[:3, 3]
    uv = (cam[:, :2] / cam[:, 2:] * 60.0 + S / 2).long().clamp(0, S - 1)
    hit = alpha[0, uv[:, 1], uv[:, 0], 0]
    assert (hit > 0.3).float().mean() > 0.9, float((hit > 0.3).float().mean())
    covered = torch.zeros(S, S, dtype=torch.bool)
    covered[uv[:, 1], uv[:, 0]] = True
    assert (alpha[0, ..., 0] > 0.5)[~covered].float().sum() < 0.15 * covered.sum()  # little alpha off the body


def test_module_wiring_optimizer_groups_decoder_box_and_sh_export(body, tmp_path):
    """The module takes its optimizer groups from the components' param_groups(), fits the decoder's box to the
    initial Gaussians when built, and the SH colour model exports its own coefficients."""
    from realityavatar.build import build_module
    from realityavatar.export import export_gaussians, read_ply
    from realityavatar.render import eval_sh

    # shading=none: the plain 3DGS colour exports its SH coefficients (with the world-lit shading it exports rgb)
    cfg = compose(["gaussians.num_points=500", "color=sh", "skinning=mlp", "shading=none"])
    module = build_module(cfg, body, num_train_frames=2, scene_extent=2.0)
    groups = {g["name"]: g for g in module.param_groups()}
    assert set(groups) == {"means", "log_scales", "quats", "opacity_logits", "features", "encoder", "temporal",
                           "deformer", "skinning"}  # SH colour has no weights: no group
    # the skinning grid as built (learnable: false) has no trainable weights either; learnable, it has its group
    for learnable in (False, True):
        grid = build_module(compose(["gaussians.num_points=200", "skinning=grid", f"skinning.learnable={learnable}"]),
                            body, num_train_frames=2, scene_extent=2.0)
        names = {g["name"] for g in grid.param_groups()}
        assert ("skinning" in names) == learnable, names
    assert groups["deformer"]["lr"] == cfg.optim.lr.deformer and groups["means"]["lr"] == 2.0 * cfg.optim.lr.means
    ids = [id(p) for g in groups.values() for p in g["params"]]
    assert sorted(ids) == sorted(id(p) for p in module.parameters() if p.requires_grad)  # each exactly once
    # decoder box: fitted now, around the initial canonical Gaussians (not at its first forward, at deform_start)
    m = module.avatar.gaussians.means.detach()
    assert bool(module.avatar.deformer.bounds_fitted)
    assert (module.avatar.deformer.bbox_min <= m.min(0).values).all() and (module.avatar.deformer.bbox_max >= m.max(0).values).all()
    assert (module.avatar.deformer.bbox_max - module.avatar.deformer.bbox_min).max() < 1.3 * (m.max(0).values - m.min(0).values).max()
    # SH export writes the model's coefficients: the PLY's colour along any direction is the model's colour
    with torch.no_grad():
        module.avatar.gaussians.features.normal_(0, 0.3)
    ply = read_ply(export_gaussians(module.avatar, tmp_path / "sh.ply"))
    sh = torch.from_numpy(ply["sh"])  # [N,16,3]
    assert sh.shape == (500, 16, 3) and sh[:, 1:].abs().sum() > 0
    d = torch.nn.functional.normalize(torch.randn(1, 500, 3), dim=-1)
    with torch.no_grad():
        ref = module.avatar.color(module.avatar.gaussians.features, d, None, torch.tensor([0]))
    assert torch.allclose(torch.clamp_min(eval_sh(3, sh[None], d) + 0.5, 0.0), ref, atol=1e-5)


def test_frozen_metric_networks_stay_out_of_the_checkpoint(body, tmp_path):
    """LPIPS and the VGG19 perceptual loss come from weight files: a run trained without them evaluates with them
    (strict load), and their weights are never written into a checkpoint."""
    from realityavatar.build import build_module
    from realityavatar.metrics import vgg_features

    torch.manual_seed(0)
    torch.save({f"features.{k}": v for k, v in vgg_features("vgg16").state_dict().items()}, tmp_path / "vgg16-397923af.pth")
    torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate((64, 128, 256, 512, 512))},
               tmp_path / "vgg.pth")
    torch.save({f"features.{k}": v for k, v in vgg_features("vgg19").state_dict().items()}, tmp_path / "vgg19.pth")
    small = ["gaussians.num_points=200", "silhouette=none"]
    plain = build_module(compose(small), body, num_train_frames=2, scene_extent=1.0)
    with_nets = build_module(compose([*small, f"metrics.lpips_weights={tmp_path}", "loss=vgg19",
                                      f"loss.perceptual.vgg19_weights={tmp_path / 'vgg19.pth'}"]),
                             body, num_train_frames=2, scene_extent=1.0)
    assert with_nets.lpips is not None and with_nets.losses["perceptual"].vgg is not None
    sd_plain, sd_nets = plain.state_dict(), with_nets.state_dict()
    assert set(sd_plain) == set(sd_nets) and not any(k.startswith(("lpips", "losses")) for k in sd_nets)
    with_nets.load_state_dict(sd_plain)  # strict: evaluate ... metrics.lpips_weights=... on a run trained without
    plain.load_state_dict({**sd_plain, "lpips.lins.0.weight": torch.zeros(1, 64, 1, 1)})  # an older checkpoint


def test_checkpoint_with_refined_gaussians_restores_model_and_optimizer(trained_run, body):
    """The resume path without Lightning's loop: a module built at the configured count takes the checkpoint of a
    run whose density control changed the count (parameters resize first), then the optimizer state loads onto
    it and steps."""
    from realityavatar.build import build_module

    out, metrics = trained_run
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=True)
    cfg = compose(TRAINED_RUN)
    module = build_module(cfg, body, state["realityavatar"]["num_train_frames"], state["realityavatar"]["scene_extent"])
    assert module.avatar.gaussians.num_points == NUM_POINTS != metrics["num_gaussians"]
    module.load_state_dict(state["state_dict"])
    module.on_load_checkpoint(state)
    assert module.avatar.gaussians.num_points == metrics["num_gaussians"]
    opt = module.configure_optimizers()["optimizer"]
    opt.load_state_dict(state["optimizer_states"][0])
    for p in module.parameters():
        if p.requires_grad:
            p.grad = torch.zeros_like(p)
    opt.step()  # a size mismatch between the restored Adam rows and the parameters raises here
    g = module.avatar.gaussians
    assert all(opt.state[getattr(g, n)]["exp_avg"].shape == getattr(g, n).shape for n in ("means", "features"))
    assert module.density.grad2d is None or module.density.grad2d.shape[0] == g.num_points


def test_views_of_one_frame_pose_it_once_and_render_as_separate_samples(body, monkeypatch):
    """data.views_per_step: a batch of V cameras of one frame (views_per_frame) runs the networks for one frame,
    rasterizes its cameras in one call and renders what the same batch renders sample by sample, gradients
    included."""
    module, _ = stepping_module(body, monkeypatch)
    make = make_batch_fn(module.avatar.body, 32, int(compose([]).data.window_len), views=3)
    batch = make()
    assert batch["views_per_frame"] == 3
    shapes = []
    module.avatar.deformer.register_forward_hook(lambda m, args, out: shapes.append(tuple(args[1].shape)))
    rgb, alpha, metas, posed = module.avatar.render_batch(batch)
    assert shapes == [(1, module.avatar.deformer.in_h.in_features)] and posed["B"] == 3
    assert len(metas) == 1 and metas[0]["means2d"].shape[0] == 3  # one rasterizer call for the frame's 3 cameras
    g = torch.autograd.grad(rgb.square().sum() + alpha.sum(), module.avatar.deformer.out.weight)[0]
    separate = {k: v for k, v in batch.items() if k != "views_per_frame"}
    rgb1, alpha1, _, _ = module.avatar.render_batch(separate)
    assert shapes[1] == (3, module.avatar.deformer.in_h.in_features)
    torch.testing.assert_close(rgb, rgb1, atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, alpha1, atol=1e-5, rtol=0)
    g1 = torch.autograd.grad(rgb1.square().sum() + alpha1.sum(), module.avatar.deformer.out.weight)[0]
    torch.testing.assert_close(g, g1, atol=1e-4, rtol=1e-4)
    assert not torch.allclose(rgb[0], rgb[1])  # three different cameras


def test_views_of_two_frames_in_one_batch(body, monkeypatch):
    """batch_size 2 x views_per_step 2: each frame's pose inputs are read once (every V-th sample) and its images come
    from its own pose, as when every sample is rendered on its own."""
    module, _ = stepping_module(body, monkeypatch)
    make = make_batch_fn(module.avatar.body, 32, int(compose([]).data.window_len), views=2)
    a, b = make(), make()  # two pose windows, two cameras each
    batch = {k: torch.cat([a[k], b[k]]) if torch.is_tensor(a[k]) else a[k] for k in a}
    batch.update(width=a["width"] + b["width"], height=a["height"] + b["height"])
    shapes = []
    module.avatar.deformer.register_forward_hook(lambda m, args, out: shapes.append(tuple(args[1].shape)))
    with torch.no_grad():
        rgb, alpha, metas, posed = module.avatar.render_batch(batch)
        rgb1, alpha1, _, _ = module.avatar.render_batch({k: v for k, v in batch.items() if k != "views_per_frame"})
    assert shapes[0][0] == 2 and shapes[1][0] == 4 and len(metas) == 2 and posed["B"] == 4
    torch.testing.assert_close(rgb, rgb1, atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, alpha1, atol=1e-5, rtol=0)
    assert not torch.allclose(rgb[0], rgb[2], atol=1e-3)  # the two frames differ


def test_a_supersampled_image_is_the_larger_image_averaged(body, monkeypatch):
    """eval.supersample k renders each image as the same camera framed at k x the size would (intrinsics from the
    step benchmark's own framing at 128 px) and averages k x k pixels. Rendered directly at 32 px instead, the
    rasterizer's 2D filter (0.3 px^2) widens the sub-pixel Gaussians: the silhouette grows by over 10 %."""
    import torch.nn.functional as F

    module, make = stepping_module(body, monkeypatch)
    batch = make()  # 32 px
    big = make_batch_fn(module.avatar.body, 128, int(compose([]).data.window_len))()
    at128 = {**batch, "K": big["K"], "width": big["width"], "height": big["height"]}
    with torch.no_grad():
        rgb, alpha, _, _ = module.avatar.render_batch(batch)
        rgb4, alpha4, _, _ = module.avatar.render_batch(batch, supersample=4)
        rgb_big, alpha_big, _, _ = module.avatar.render_batch(at128)

    def pooled(x):
        return F.avg_pool2d(x.permute(0, 3, 1, 2), 4).permute(0, 2, 3, 1)

    assert rgb4.shape == rgb.shape and alpha4.shape == alpha.shape
    torch.testing.assert_close(rgb4, pooled(rgb_big), atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha4, pooled(alpha_big), atol=1e-5, rtol=0)
    assert float(alpha.sum()) > 1.1 * float(alpha4.sum()) > 50, (float(alpha.sum()), float(alpha4.sum()))


def test_a_training_step_reads_the_device_only_on_log_steps(body, monkeypatch):
    """No scalar read (.item(), float(), bool() of a tensor) and no data-dependent shape (nonzero, boolean-mask
    indexing) in a training step but every `log_every` steps: on a GPU each would wait for the device. Counted on the
    CPU with OpCount. A non-finite loss between log steps stops the run at the next log step, naming the steps."""
    from realityavatar.runtime import OpCount

    module, make_batch = stepping_module(body, monkeypatch)
    module._test_step = 1
    module.training_step(make_batch(), 0)  # one-time set-up reads (e.g. the skinning loss's surface sample pool)
    for s in range(2, 4):
        module._test_step = s
        batch = make_batch()
        with OpCount() as c:
            module.training_step(batch, 0)
        assert c.reads == 0, {k: v for k, v in c.ops.items() if k in ("_local_scalar_dense", "nonzero",
                                                                        "boolean_mask_index")}
    module._test_step = 4  # a log step ((step + 1) % log_every == 0): logging and the input checks read the device
    batch = make_batch()
    logged = {}
    module.log = lambda name, value, **kwargs: logged.update({name: (value, kwargs.get("prog_bar", False))})
    with OpCount() as c:
        module.training_step(batch, 0)
    assert c.reads > 0
    # Logged as host tensors: Lightning reads the progress bar's values after every step, and turns a number into a
    # tensor on the module's device.
    assert {"train/loss", "train/num_gaussians"} <= {k for k, (_, bar) in logged.items() if bar}
    assert all(torch.is_tensor(v) and v.device.type == "cpu" and v.dim() == 0 for v, _ in logged.values()), logged
    with torch.no_grad():
        module.avatar.gaussians.features[0, 0] = float("nan")
    module._test_step = 5
    module.training_step(make_batch(), 0)  # not a log step: nothing read, the flag is kept on the device
    module._test_step = 9
    with pytest.raises(FloatingPointError, match="non-finite between steps 5 and 8"):
        module.training_step(make_batch(), 0)


def test_no_step_reads_an_output_of_the_compiled_functions_of_an_earlier_step(body, monkeypatch):
    """compile=reduce-overhead replays `deform`, `shade` and `loss` as CUDA graphs, each replay over the memory of the
    last one's outputs, and reading an overwritten output raises. So no step reads what they returned in an earlier
    step: every tensor operation of steps 5 to 7 is checked against the storages they returned in steps 4 (a log
    step: log_every 5) and 5 (the loss sum once kept step 5's loss and added step 6's to it). Outputs that alias a
    parameter or the batch are not the graphs' memory and are left out."""
    from torch.multiprocessing.reductions import StorageWeakRef
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_leaves

    module, make_batch = stepping_module(body, monkeypatch)
    static = {StorageWeakRef(t.untyped_storage()) for t in (*module.parameters(), *module.buffers())}
    batches = {s: make_batch() for s in range(1, 8)}
    static |= {StorageWeakRef(t.untyped_storage()) for b in batches.values() for t in b.values() if torch.is_tensor(t)}
    returned: dict = {}  # storage -> the step that returned it

    def recorded(f):
        def call(*args, **kwargs):
            out = f(*args, **kwargs)
            if module._test_step in (4, 5):
                returned.update({StorageWeakRef(t.untyped_storage()): module._test_step
                                 for t in tree_leaves(out) if torch.is_tensor(t)})
            return out
        return call

    for owner, name in ((module.avatar, "deform"), (module.avatar, "shade"), (module, "loss")):  # compile_path's
        setattr(owner, name, recorded(getattr(owner, name)))
    reads: list = []

    class Reads(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            for t in tree_leaves((args, kwargs)):
                if torch.is_tensor(t) and t.device.type != "meta":
                    ref = StorageWeakRef(t.untyped_storage())
                    if returned.get(ref, module._test_step) < module._test_step and ref not in static:
                        reads.append(f"step {module._test_step}: {func}")
            return func(*args, **(kwargs or {}))

    for s in range(1, 8):
        module._test_step = s
        with (Reads() if s > 4 else contextlib.nullcontext()):
            module.training_step(batches[s], 0)
    assert len(returned) > 10 and not reads, reads


@pytest.mark.gpu
def test_a_training_step_on_a_gpu_does_not_synchronise(body, monkeypatch):
    """The same on CUDA under torch.cuda.set_sync_debug_mode("warn"): no synchronising call in a non-log step (each
    warns, named by file and line), except those inside gsplat's rasterizer (its tile intersection sizes its buffers
    from the data)."""
    import warnings

    from realityavatar.render.splat import gsplat_status

    if not torch.cuda.is_available() or gsplat_status() != "ok":
        pytest.skip("needs CUDA and gsplat")
    module, make_batch = stepping_module(body, monkeypatch, "cuda", 5, "render.backend=gsplat")
    module._test_step = 1
    module.training_step(make_batch(), 0)  # warm-up: one-time set-up (caches, kernels) may read the device
    module._test_step = 2
    batch = make_batch()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            module.training_step(batch, 0)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()  # outside the mode: this synchronize is the test's own (it failed the test on an H100)
    ours = [f"{w.filename}:{w.lineno}: {w.message}" for w in caught
            if "synchroniz" in str(w.message).lower() and "gsplat" not in w.filename]
    assert not ours, ours


@pytest.mark.gpu
def test_compiled_steps_on_a_gpu_replay_cuda_graphs(body, monkeypatch):
    """compile=reduce-overhead: `deform`, `shade` and `loss` replay as CUDA graphs over advancing steps (the decoder's
    window opening). Inductor skips a graph with a host input, and `cudagraph_or_error` makes a skip an error:
    module-level constant tensors and the window's alpha were such inputs
    (docs/research/2026-11-27-compiled-graph-host-constants.md)."""
    from torch._dynamo.utils import counters

    from realityavatar.render.splat import gsplat_status

    if not torch.cuda.is_available() or gsplat_status() != "ok":
        pytest.skip("needs CUDA and gsplat")
    module, make_batch = stepping_module(body, monkeypatch, "cuda", 50, "render.backend=gsplat")
    torch._dynamo.reset()
    counters.clear()
    module.compile_path("reduce-overhead")
    try:
        with torch._inductor.config.patch({"triton.cudagraph_or_error": True}):
            for s in range(1, 7):
                module._test_step = s
                module.training_step(make_batch(), 0)
            torch.cuda.synchronize()
    finally:
        torch._dynamo.reset()
    assert counters["inductor"]["cudagraph_skips"] == 0
    assert 0 < module.avatar.deformer.encoding.alpha < module.avatar.deformer.encoding.num_freqs  # the window moved every step


def test_a_compiled_run_traces_each_graph_once(body, monkeypatch):
    """compile=...: `deform`, `shade` and `loss` are traced once for a whole run, across the skinning term's weight
    switch, density refinements that change the Gaussians' count and the decoder's window opening fully. Each of
    those recompiled the graphs, ~110 s of paper_scale's 387 s on an H100
    (docs/research/2026-11-28-h100-cuda-graphs.md). Dynamo's guards do not depend on the backend: its eager one
    traces without compiling."""
    import functools

    from torch._dynamo.utils import counters

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="eager"))
    module, make_batch = stepping_module(
        body, monkeypatch, "cpu", 5, "iterations=20", "density=default", "density.refine_start=4",
        "density.refine_every=4", "density.grad_threshold=1e-12",  # skinning switch at 2, window open from 10
        "skinning=mlp", "loss=learnt_skinning")  # a skinning term with its weight switch
    torch._dynamo.reset()
    counters.clear()
    module.compile_path("default")
    counts, graphs = [], []
    try:
        for s in range(14):
            module._test_step = s
            module.training_step(make_batch(), 0)
            counts.append(module.avatar.gaussians.num_points)
            graphs.append(counters["stats"]["unique_graphs"])
    finally:
        torch._dynamo.reset()
    assert len(set(counts)) >= 3, counts  # two refinements changed the count
    assert module.losses["skinning"].switch == 2 and module.avatar.deformer.encoding.alpha == module.avatar.deformer.encoding.num_freqs
    assert graphs[0] == 3 and graphs[-1] == graphs[0], graphs


def test_a_loss_term_that_is_not_a_loss_term_is_named(body):
    """A configured loss that is not a losses.LossTerm (it could not bind to the avatar) stops the build, naming it."""
    from realityavatar.build import build_module

    cfg = compose(["gaussians.num_points=200", "+loss.extra={_target_:torch.nn.Identity}"])
    with pytest.raises(TypeError, match=r"loss\.extra: Identity is not a realityavatar\.losses\.LossTerm"):
        build_module(cfg, body, num_train_frames=2, scene_extent=1.0)
