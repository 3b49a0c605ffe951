"""End-to-end: configs compose and instantiate, a short run trains/evaluates/resumes, bad input fails clearly, PLY export."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import open_dict

from realityavatar.config import CONFIG_DIR, compose, prepare_run

SMALL = ["trainer=ci", "gaussians.num_points=1500", "eval.save_video=false", "eval.fps_frames=2", "eval.fps_warmup=1"]
COMPONENT_GROUPS = ("gaussians", "encoder", "temporal", "deformer", "skinning", "color", "density", "loss",
                    "silhouette")


_prepare = prepare_run  # compose() result -> (cfg, choices) for train.run


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


@pytest.fixture(scope="module")
def body():
    from realityavatar.body import build_body

    return build_body("mannequin")


@pytest.mark.parametrize("group", COMPONENT_GROUPS + ("render", "optim", "trainer", "body", "data", "callbacks", "logger"))
def test_every_option_composes(group):
    opts = _options(group)
    assert opts, f"conf/{group} has no options"
    for opt in opts:
        cfg = compose([f"{group}={opt}"])
        assert cfg.hydra.runtime.choices[group] == opt


def _forward(group: str, obj, cfg, body) -> None:
    """Run the built component on inputs sized from the composed config and check what it promises."""
    B, T, N = 2, 3, 300
    gen = torch.Generator().manual_seed(0)
    x = body.canonical_vertices().detach()[torch.randint(0, body.rest_vertices.shape[0], (N,), generator=gen)]  # [N,3]
    if group == "gaussians":
        assert obj.num_points == N and obj.features.shape == (N, cfg.color.feature_dim)
        d = torch.cdist(obj.means.detach(), body.canonical_vertices().detach()).min(-1).values
        assert d.max() < 0.05, "canonical Gaussians do not start on the body surface"
        assert ((obj.opacities() > 0) & (obj.opacities() < 1)).all()
    elif group == "encoder":
        f = obj(torch.randn(B, T, 24, 3, generator=gen) * 0.3, torch.randn(B, T, 3, generator=gen))
        assert f.shape == (B, T, cfg.encoder.out_dim) == (B, T, cfg.temporal.in_dim)
        f.square().sum().backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in obj.parameters())
    elif group == "temporal":
        h = obj(torch.randn(B, T, cfg.temporal.in_dim, generator=gen))
        assert h.shape == (B, cfg.deformer.cond_dim)
    elif group == "deformer":
        out = obj(x, torch.randn(B, cfg.deformer.cond_dim, generator=gen))
        assert out["dx"].shape == (B, N, 3) and out["dq"].shape == (B, N, 4)
        assert out["f_mt"].shape == (B, N, cfg.color.get("fmt_dim", cfg.deformer.feature_dim))
        assert out["dx"].abs().max() < 1e-5 and out["ds"].abs().max() < 1e-5  # starts at the identity
        sum(v.square().sum() for v in out.values()).backward()
    elif group == "skinning":
        w = obj(x.expand(B, -1, -1))
        assert w.shape == (B, N, 24) and torch.allclose(w.sum(-1), torch.ones(B, N), atol=1e-5)
    elif group == "color":
        feats = torch.randn(N, cfg.color.feature_dim, generator=gen)
        f_mt = torch.randn(B, N, cfg.deformer.feature_dim, generator=gen)
        rgb = obj(feats, torch.nn.functional.normalize(torch.randn(B, N, 3), dim=-1), f_mt, torch.tensor([0, -1]))
        assert rgb.shape == (B, N, 3) and (rgb >= 0).all() and torch.isfinite(rgb).all()
    elif group == "density":
        g = instantiate(cfg.gaussians, body=body, num_points=N)
        opt = torch.optim.Adam([{"params": ps, "name": n} for n, ps in g.param_groups().items()], lr=1e-3)
        for p in g.parameters():
            p.grad = torch.ones_like(p)
        opt.step()
        means2d = torch.zeros(1, N, 2, requires_grad=True)
        means2d.grad = torch.full((1, N, 2), 1.0)  # every Gaussian over the threshold
        meta = [{"means2d": means2d, "radii": torch.ones(1, N, dtype=torch.int32)}]
        on = "refine_every" in cfg.density  # density=off is a strategy with no settings
        step = int(cfg.density.refine_start) + int(cfg.density.refine_every) if on else 10
        obj.step_post_backward(g, opt, meta, step - 1, (64, 64))  # accumulate
        stats = obj.step_post_backward(g, opt, meta, step, (64, 64))
        assert (g.num_points > N) == on, stats
        assert all(opt.state[p]["exp_avg"].shape == p.shape for p in g.parameters())
    elif group == "loss":  # the terms, summed in order (the silhouette group's term is checked below)
        from types import SimpleNamespace

        from realityavatar.losses import TrainingRender, total_loss

        rgb, gt = torch.rand(B, 16, 16, 3, generator=gen, requires_grad=True), torch.rand(B, 16, 16, 3, generator=gen)
        alpha, mask = torch.rand(B, 16, 16, 1, generator=gen), (torch.rand(B, 16, 16, 1, generator=gen) > 0.5).float()
        avatar = SimpleNamespace(body=body, skinning=instantiate(cfg.skinning))
        total, terms = total_loss(obj, TrainingRender(rgb, alpha, {"image": gt, "mask": mask}, {}, avatar, 0))
        assert {"l1", "mask", "perceptual", "skin"} <= set(terms) and torch.isfinite(total)
        total.backward()
        assert rgb.grad.abs().sum() > 0
    elif group == "silhouette":
        if not cfg.silhouette:  # silhouette=none: no term at all
            assert not obj
            return
        from realityavatar.losses import TrainingRender

        K = torch.tensor([[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]])
        E = torch.eye(4)
        E[2, 3] = 3.0
        mask = torch.zeros(1, 32, 32, 1)
        mask[0, 8:24, 12:20] = 1
        means = (x + torch.tensor([1.0, 0.0, 0.0])).requires_grad_()  # partly outside the mask
        batch = {"viewmat": E[None], "K": K[None], "mask": mask}
        total, terms = obj(TrainingRender(torch.zeros(1, 32, 32, 3), torch.zeros(1, 32, 32, 1), batch,
                                          {"means": means[None]}, None, 0))
        assert torch.isfinite(total) and total.dim() == 0 and {"sil_outside", "sil_coverage"} <= set(terms)
        total.backward()
        assert means.grad.abs().sum() > 0
    else:
        raise AssertionError(f"no forward check written for group {group}")


@pytest.mark.parametrize("group,opt", [(g, o) for g in COMPONENT_GROUPS for o in _options(g)])
def test_every_component_option_builds_and_runs(group, opt, body):
    """Every option file of every component group, composed as the command line does, instantiates and runs a
    forward pass with inputs sized from the config."""
    cfg = compose([f"{group}={opt}", "gaussians.num_points=300"])
    kwargs = {"body": body} if group == "gaussians" else {"num_frames": 4} if group == "color" else {}
    torch.manual_seed(0)
    _forward(group, instantiate(cfg[group], **kwargs), cfg, body)


def test_callbacks_and_loggers_come_from_their_groups(tmp_path):
    from pytorch_lightning.callbacks import ModelCheckpoint
    from pytorch_lightning.loggers import CSVLogger

    cfg, _ = _prepare(compose(["iterations=40"]), tmp_path)
    ckpt = instantiate(cfg.callbacks.checkpoint)
    assert isinstance(ckpt, ModelCheckpoint) and ckpt.dirpath == str(tmp_path) and ckpt._every_n_train_steps == 10
    assert isinstance(instantiate(cfg.logger.csv), CSVLogger)
    cfg, _ = _prepare(compose(["logger=none", "callbacks.checkpoint=null"]), tmp_path)
    assert not cfg.logger and cfg.callbacks.checkpoint is None


@pytest.mark.parametrize("group,option,base,differs", [
    ("encoder", "no_split", "latentbone", {"part_split"}),
    ("encoder", "no_zc", "latentbone", {"clothes_latent_dim"}),
])
def test_ablation_options_differ_from_their_base_only_where_they_say(group, option, base, differs):
    """An ablation option is its base with a few keys changed (a copied file drifts when the base changes)."""
    a = compose([f"{group}={option}"])[group]
    b = compose([f"{group}={base}"])[group]
    changed = {k for k in set(a) | set(b) if a.get(k) != b.get(k)}
    assert changed == differs


def test_unknown_option_names_the_group():
    with pytest.raises(Exception) as e:
        compose(["temporal=transformer"])
    assert "temporal" in str(e.value) and "transformer" in str(e.value)


@pytest.fixture(scope="module")
def trained_run(scenes_root, tmp_path_factory):
    from realityavatar.train import run

    out = tmp_path_factory.mktemp("run")
    # density.refine_every=15: refinement fires at steps 15 and 30 (window 6..42), so the run, its checkpoint and
    # every rebuild from it go through clone/split/prune and a changed Gaussian count.
    cfg, choices = _prepare(compose(["data=synthetic_ci", "iterations=60", "density.refine_every=15", *SMALL]), out)
    metrics = run(cfg, choices)
    return out, metrics


def test_density_control_fires_inside_the_training_loop(trained_run):
    """Clone/split/prune during a real fit: the Adam state, the parameters and the LR schedule stay consistent."""
    from realityavatar.model.gaussians import PARAM_NAMES

    out, metrics = trained_run
    with open(out / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    fired = {k: sum(float(r[k]) for r in rows if r.get(k)) for k in ("train/density_cloned", "train/density_split",
                                                                      "train/density_pruned")}
    assert sum(fired.values()) > 0, f"refinement never changed the Gaussians: {fired}"
    assert metrics["num_gaussians"] != 1500
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=False)
    N = metrics["num_gaussians"]
    assert state["state_dict"]["gaussians.means"].shape[0] == N
    opt = state["optimizer_states"][0]
    sched = state["lr_schedulers"][0]
    assert len(sched["base_lrs"]) == len(opt["param_groups"]) and sched["last_epoch"] == 60
    cfg = compose(["iterations=60"])
    for group, base in zip(opt["param_groups"], sched["base_lrs"]):
        if group["name"] not in PARAM_NAMES:
            continue
        (idx,) = group["params"]
        st = opt["state"][idx]
        shape = tuple(state["state_dict"][f"gaussians.{group['name']}"].shape)
        assert tuple(st["exp_avg"].shape) == shape == tuple(st["exp_avg_sq"].shape), group["name"]
        assert st["exp_avg_sq"].abs().sum() > 0, f"{group['name']}: Adam state lost at refinement"
        f = cfg.optim.final_factor.get(group["name"], cfg.optim.final_factor.default)
        assert group["lr"] == pytest.approx(base * f ** 1.0, rel=1e-6), f"{group['name']}: LR schedule lost"


def test_short_training_lowers_loss_and_writes_outputs(trained_run):
    out, _ = trained_run
    assert (out / "last.ckpt").is_file()
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("config", "seed", "commit", "train_seconds", "iterations", "num_gaussians", "num_parameters",
                "render_fps", "perceptual", "lpips", "test/novel_view/psnr", "test/novel_view/ssim",
                "test/novel_pose/psnr", "test/novel_view/psnr_masked"):
        assert key in saved, key
    assert saved["iterations"] == 60
    assert saved["config"]["temporal"] == "lstm"
    assert saved["lpips"].startswith("not computed") and "test/novel_view/lpips" not in saved
    with open(out / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    # The photometric term, not the total: the total also falls by itself when the skinning weight drops at
    # schedule.skin_switch, which would hide a model that learns nothing.
    l1 = [float(r["train/l1"]) for r in rows if r.get("train/l1")]
    assert len(l1) >= 4
    first, last = np.mean(l1[: len(l1) // 3]), np.mean(l1[-(len(l1) // 3):])
    assert last < 0.95 * first, f"photometric L1 did not decrease: {first:.4f} -> {last:.4f}"
    assert (out / "per_frame.csv").is_file() and (out / "images" / "novel_pose_grid.png").is_file()


def test_resume_continues_from_checkpoint_step(trained_run, tmp_path):
    from realityavatar.train import run

    out, _ = trained_run
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=False)
    assert state["global_step"] == 60
    cfg, choices = _prepare(
        compose(["data=synthetic_ci", "iterations=70", f"ckpt_path={out / 'last.ckpt'}", "test_after_fit=false", *SMALL]), tmp_path
    )
    metrics = run(cfg, choices)
    assert metrics["iterations"] == 70
    with open(tmp_path / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    steps = [int(r["step"]) for r in rows if r.get("train/loss")]
    # the rows before the checkpoint are carried over; a restart from step 0 would log those steps twice
    assert steps == sorted(set(steps)) and min(steps) < 60 <= max(steps), f"resumed run restarted from step 0: {steps}"


def test_evaluate_and_export_from_run_folder(trained_run):
    from realityavatar.evaluate import main as evaluate_main
    from realityavatar.export import main as export_main
    from realityavatar.export import read_ply

    out, metrics = trained_run
    assert evaluate_main([f"run_dir={out}", "eval.save_video=false"]) == 0
    again = json.loads((out / "eval" / "metrics.json").read_text())
    assert abs(again["test/novel_view/psnr"] - metrics["test/novel_view/psnr"]) < 1e-3
    assert export_main([f"run_dir={out}", f"out={out / 'c.ply'}"]) == 0
    ply = read_ply(out / "c.ply")
    assert ply["means"].shape == (metrics["num_gaussians"], 3)


def test_ply_round_trip(tmp_path):
    from realityavatar.export import read_ply, write_ply

    rng = np.random.default_rng(0)
    N = 50
    means, quats = rng.normal(size=(N, 3)), rng.normal(size=(N, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales, op = rng.uniform(0.01, 0.1, (N, 3)), rng.uniform(0.05, 0.95, N)
    sh = rng.normal(size=(N, 16, 3))
    write_ply(tmp_path / "g.ply", means, quats, scales, op, sh=sh)
    back = read_ply(tmp_path / "g.ply")
    for k, v in (("means", means), ("quats", quats), ("scales", scales), ("opacities", op), ("sh", sh)):
        np.testing.assert_allclose(back[k], v, rtol=1e-4, atol=1e-5, err_msg=k)
    with pytest.raises(ValueError, match="means"):
        write_ply(tmp_path / "bad.ply", means[:, :2], quats, scales, op, sh=sh)


def test_missing_scene_folder_is_named(tmp_path, body):
    cfg = compose(["data=synthetic_ci", f"data.root={tmp_path / 'nowhere'}"])
    with open_dict(cfg):
        cfg.data.build_preset = None
    dm = instantiate(cfg.data, body=body)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        dm.prepare_data()
        dm.setup("fit")


def test_nan_pose_gives_clear_error(body):
    from realityavatar.body.base import check_pose

    pose = torch.zeros(24, 3)
    pose[5, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        body(pose, torch.zeros(3))
    with pytest.raises(ValueError, match=r"\[\.\.\.,24,3\]"):
        check_pose(torch.zeros(23, 3), None)


def test_animate_writes_video_from_pose_file(trained_run, tmp_path):
    from realityavatar.animate import main as animate_main

    out, _ = trained_run
    poses = np.zeros((5, 24, 3), np.float32)
    poses[:, 16, 2] = np.linspace(0, 1.2, 5)  # raise the left arm
    np.savez(tmp_path / "wave.npz", poses=poses, transl=np.zeros((5, 3), np.float32))
    assert animate_main([f"run_dir={out}", f"poses={tmp_path / 'wave.npz'}", "views=0", f"out={tmp_path / 'wave.mp4'}"]) == 0
    assert (tmp_path / "wave.mp4").stat().st_size > 0
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((5, 23, 3), np.float32))
    with pytest.raises(ValueError, match="poses"):
        animate_main([f"run_dir={out}", f"poses={bad}"])


def test_animate_without_ffmpeg_fails_before_rendering_and_gif_needs_none(trained_run, tmp_path, monkeypatch):
    """No imageio-ffmpeg (a GPU image without it): a clear error naming the file before any frame is rendered
    (imageio otherwise picked its TIFF plugin and failed with `unexpected keyword 'fps'`); a .gif still works."""
    import sys

    import imageio.v2 as imageio

    import realityavatar.animate as anim

    out, _ = trained_run
    rendered = []
    real = anim.render_sequence
    monkeypatch.setattr(anim, "render_sequence", lambda *a, **k: rendered.append(1) or real(*a, **k))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(RuntimeError, match=r"a\.mp4: writing a video needs ffmpeg.*imageio-ffmpeg"):
        anim.main([f"run_dir={out}", "views=0", f"out={tmp_path / 'a.mp4'}"])
    assert not rendered and not (tmp_path / "a.mp4").exists()
    assert anim.main([f"run_dir={out}", "views=0", f"out={tmp_path / 'a.gif'}", "fps=10"]) == 0
    frames = imageio.mimread(tmp_path / "a.gif")
    assert rendered and len(frames) > 1 and frames[0].shape[0] > 0


@pytest.mark.slow
def test_canonical_gaussians_land_on_the_posed_body_after_skinning_prefit(body):
    """Posing end to end (module.deform -> skinning field -> canonical_transforms -> LBS, then render_batch): after
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
    poses, transls = pose.expand(1, 3, 24, 3), transl.expand(1, 3, 3)  # a window holding the pose
    with torch.no_grad():
        posed = module.deform(poses, transls)
    d_canon = torch.cdist(module.gaussians.means, body.canonical_vertices()).min(-1).values  # [N]
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
    batch = {"poses": poses, "transl": transls, "frame_idx": torch.tensor([0]), "viewmat": E[None], "K": K[None],
             "width": torch.tensor([S]), "height": torch.tensor([S])}
    with torch.no_grad():
        _, alpha, _, _ = module.render_batch(batch)
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
    m = module.gaussians.means.detach()
    assert bool(module.deformer.bounds_fitted)
    assert (module.deformer.bbox_min <= m.min(0).values).all() and (module.deformer.bbox_max >= m.max(0).values).all()
    assert (module.deformer.bbox_max - module.deformer.bbox_min).max() < 1.3 * (m.max(0).values - m.min(0).values).max()
    # SH export writes the model's coefficients: the PLY's colour along any direction is the model's colour
    with torch.no_grad():
        module.gaussians.features.normal_(0, 0.3)
    ply = read_ply(export_gaussians(module, tmp_path / "sh.ply"))
    sh = torch.from_numpy(ply["sh"])  # [N,16,3]
    assert sh.shape == (500, 16, 3) and sh[:, 1:].abs().sum() > 0
    d = torch.nn.functional.normalize(torch.randn(1, 500, 3), dim=-1)
    with torch.no_grad():
        ref = module.color(module.gaussians.features, d, None, torch.tensor([0]))
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
    with_nets = build_module(compose([*small, f"metrics.lpips_weights={tmp_path}",
                                      f"loss.perceptual.vgg19_weights={tmp_path / 'vgg19.pth'}"]),
                             body, num_train_frames=2, scene_extent=1.0)
    assert with_nets.lpips is not None and with_nets.losses["perceptual"].vgg is not None
    sd_plain, sd_nets = plain.state_dict(), with_nets.state_dict()
    assert set(sd_plain) == set(sd_nets) and not any(k.startswith(("lpips", "losses")) for k in sd_nets)
    with_nets.load_state_dict(sd_plain)  # strict: evaluate ... metrics.lpips_weights=... on a run trained without
    plain.load_state_dict({**sd_plain, "lpips.lins.0.weight": torch.zeros(1, 64, 1, 1)})  # an older checkpoint


def test_rebuild_overrides_move_interpolated_keys(trained_run):
    """evaluate/animate/export apply key=value overrides as train does: keys interpolated from them follow."""
    from realityavatar.build import load_run

    out, _ = trained_run
    cfg, _, _ = load_run(out, ["seed=5", "iterations=1000"])
    assert cfg.gaussians.seed == 5 and cfg.density.seed == 5  # ${seed}
    assert cfg.schedule.skin_switch == 100 and cfg.density.refine_start == 100  # ${int_mul:${iterations},0.1}
    assert cfg.data.root == load_run(out)[0].data.root  # environment values stay those of the run
    # Hydra's "+key=value" adds a key, as on the train command line (it used to land under a key named "+data").
    cfg, _, _ = load_run(out, ["+data.build_overrides={ambient: 1.0, diffuse: 0.0}"])
    assert cfg.data.build_overrides.ambient == 1.0 and "+data" not in cfg
    with pytest.raises(ValueError, match="key=value"):
        load_run(out, ["~data.root"])


def test_checkpoint_with_refined_gaussians_restores_model_and_optimizer(trained_run, body):
    """The resume path without Lightning's loop: a module built at the configured count takes the checkpoint of a
    run whose density control changed the count (parameters resize first), then the optimizer state loads onto
    it and steps."""
    from realityavatar.build import build_module

    out, metrics = trained_run
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=False)
    cfg = compose(["data=synthetic_ci", "iterations=60", "density.refine_every=15", *SMALL])
    module = build_module(cfg, body, state["realityavatar"]["num_train_frames"], state["realityavatar"]["scene_extent"])
    assert module.gaussians.num_points == 1500 != metrics["num_gaussians"]
    module.load_state_dict(state["state_dict"])
    module.on_load_checkpoint(state)
    assert module.gaussians.num_points == metrics["num_gaussians"]
    opt = module.configure_optimizers()["optimizer"]
    opt.load_state_dict(state["optimizer_states"][0])
    for p in module.parameters():
        if p.requires_grad:
            p.grad = torch.zeros_like(p)
    opt.step()  # a size mismatch between the restored Adam rows and the parameters raises here
    g = module.gaussians
    assert all(opt.state[getattr(g, n)]["exp_avg"].shape == getattr(g, n).shape for n in ("means", "features"))
    assert module.density.grad2d is None or module.density.grad2d.shape[0] == g.num_points


def test_spin_target_experiment_is_the_command_it_was_measured_with():
    """+experiment=spin_target composes exactly the command the README's 10,000-step spin numbers came from."""
    from omegaconf import OmegaConf

    a = compose(["+experiment=spin_target", "seed=0"])
    b = compose(["+ablation=paper", "+variant=full", "data=synthetic_sweep", "seed=0", "sheet=skirt", "sheet.basis=64",
                 "skinning.query_at=canonical", "iterations=10000"])
    A, B = (OmegaConf.to_container(c, resolve=False) for c in (a, b))
    A.pop("hydra", None)
    B.pop("hydra", None)
    assert A == B
    assert a.iterations == 10000 and a.sheet.basis == 64 and a.data.sequence == "skirt_spin_demo"
