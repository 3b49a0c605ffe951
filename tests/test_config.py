"""Configs: every option composes and builds and runs, ablation options differ only where they say, clear errors."""

from __future__ import annotations

import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import CONFIG_DIR, compose, prepare_run
from realityavatar.model.encoders import pose_features

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
        f = obj(pose_features(torch.randn(B, T, 24, 3, generator=gen) * 0.3, torch.randn(B, T, 3, generator=gen)))
        assert f.shape == (B, T, cfg.encoder.out_dim) == (B, T, cfg.temporal.in_dim)
        f.square().sum().backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in obj.parameters() if p.numel())  # no_zc: Z_c empty
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
        # loss=learnt_skinning's λ3 term needs a skinning field that trains
        skinning = instantiate(compose(["skinning=mlp"]).skinning) if "skinning" in obj else instantiate(cfg.skinning)
        avatar = SimpleNamespace(body=body, skinning=skinning)
        for term in obj.values():
            term.bind(avatar)  # as AvatarModule does when it is built
        total, terms = total_loss(obj, TrainingRender(rgb, alpha, {"image": gt, "mask": mask}, {}, avatar))
        assert {"l1", "mask", "perceptual"} <= set(terms) and torch.isfinite(total)
        total.backward()
        assert rgb.grad.abs().sum() > 0
    elif group == "silhouette":
        from realityavatar.losses import TrainingRender

        K = torch.tensor([[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]])
        E = torch.eye(4)
        E[2, 3] = 3.0
        mask = torch.zeros(1, 32, 32, 1)
        mask[0, 8:24, 12:20] = 1
        means = (x + torch.tensor([1.0, 0.0, 0.0])).requires_grad_()  # partly outside the mask
        from realityavatar.data.records import mask_distance

        batch = {"viewmat": E[None], "K": K[None], "mask": mask, "mask_dist": mask_distance(mask[0, ..., 0])[None]}
        total, terms = obj(TrainingRender(torch.zeros(1, 32, 32, 3), torch.zeros(1, 32, 32, 1), batch,
                                          {"means": means[None]}, None))
        assert torch.isfinite(total) and total.dim() == 0
        if cfg.silhouette._target_.endswith("NoLoss"):  # silhouette=none: a term that adds nothing
            assert float(total) == 0.0 and not terms and not total.requires_grad
            return
        assert {"sil_outside", "sil_coverage"} <= set(terms)
        total.backward()
        assert means.grad.abs().sum() > 0
    else:
        raise AssertionError(f"no forward check written for group {group}")


@pytest.mark.parametrize("group,opt", [(g, o) for g in COMPONENT_GROUPS for o in _options(g)])
def test_every_component_option_builds_and_runs(group, opt, body, tmp_path, monkeypatch):
    """Every option file of every component group, composed as the command line does, instantiates and runs a
    forward pass with inputs sized from the config."""
    if (group, opt) == ("loss", "vgg19"):  # its weights, where a user keeps them (torch's hub cache)
        from tests.helpers import plant_found_weights

        plant_found_weights(tmp_path, monkeypatch, lin=False, vgg16=False, vgg19=True)
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
    ("encoder", "no_split", "latentbone", {"_target_"}),
    ("encoder", "no_zc", "latentbone", {"_target_", "clothes_latent_dim", "latent_init_std"}),
    ("loss", "learnt_skinning", "default", {"skinning"}),
    ("loss", "vgg19", "default", {"perceptual"}),
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


def test_every_shipped_composition_passes_the_settings_check():
    """Each option of each group, and each experiment, preset, variant and ablation, passes check_settings."""
    from realityavatar.config import check_settings

    for group in sorted(p.name for p in CONFIG_DIR.iterdir() if p.is_dir() and p.name != "hydra"):
        plus = "+" if group in ("experiment", "preset", "variant", "ablation") else ""
        for opt in _options(group):
            check_settings(compose([f"{plus}{group}={opt}"]))


def test_bad_network_sizes_weights_rates_and_density_settings_name_their_keys():
    """Sizes torch cannot make, negative loss weights and learning rates, density thresholds: one ValueError naming
    every key as typed (`*` keys by their own name, e.g. optim.lr.deformer), before anything is built. Before the
    check, a negative learning rate or loss weight trained without a word, and a width of -1 failed in torch
    ("negative dimension") without the key."""
    from realityavatar.config import check_settings

    bad = {"deformer.hidden_dim": 0, "encoder.out_dim": -1, "temporal.num_layers": 0, "color.hidden_dim": -1,
           "encoder.clothes_latent_dim": -1, "optim.lr.deformer": -1e-3, "optim.final_factor.means": -0.5,
           "loss.mask.weight": -1, "loss.perceptual.weight": -1,
           "silhouette.max_pixels": 0, "silhouette.covered_alpha": 2, "density.refine_every": 0,
           "density.prune_opacity": 1.0, "trainer.log_every_n_steps": 0, "trainer.precision": 16}
    with pytest.raises(ValueError) as e:
        check_settings(compose([f"{k}={v}" for k, v in bad.items()]))
    named = [k for k in bad if f"{k}=" in str(e.value)]
    assert named == list(bad), str(e.value)
    skin = {"loss.skinning.weight_after": float("nan"), "loss.skinning.samples": 0}
    with pytest.raises(ValueError) as e:
        check_settings(compose(["loss=learnt_skinning", *(f"{k}={v}" for k, v in skin.items())]))
    assert [k for k in skin if f"{k}=" in str(e.value)] == list(skin), str(e.value)
    check_settings(compose(["encoder=no_zc", "optim.lr.deformer=0", "deformer.num_freqs=0", "density=off"]))
    sheet = {"sheet.hull_voxel": 0, "sheet.normal_scale": -1, "sheet.max_stretch": -1, "sheet.top_offset": float("nan")}
    with pytest.raises(ValueError) as e:  # each failed in numpy or math without the key ("math domain error")
        check_settings(compose(["sheet=skirt", *(f"{k}={v}" for k, v in sheet.items())]))
    assert [k for k in sheet if f"{k}=" in str(e.value)] == list(sheet), str(e.value)


def test_spin_target_experiment_is_the_command_it_was_measured_with():
    """+experiment=spin_target composes exactly the command the README's 10,000-step spin numbers came from."""
    from omegaconf import OmegaConf

    a = compose(["+experiment=spin_target", "seed=0"])
    b = compose(["+ablation=paper", "+variant=full", "data=synthetic_sweep", "seed=0", "sheet=skirt", "sheet.basis=64",
                 "skinning.query._target_=realityavatar.model.skinning.AtCanonical", "iterations=10000"])
    A, B = (OmegaConf.to_container(c, resolve=False) for c in (a, b))
    A.pop("hydra", None)
    B.pop("hydra", None)
    assert A == B
    assert a.iterations == 10000 and a.sheet.basis == 64 and a.data.sequence == "skirt_spin_demo"


def test_silhouette_chamfer_pulls_a_centre_outside_the_mask_and_none_adds_nothing():
    """silhouette=chamfer: a projected centre outside the mask is pulled towards it, one inside is left alone;
    silhouette=none: the same render adds 0 with no gradient."""
    from realityavatar.data.records import mask_distance
    from realityavatar.losses import TrainingRender

    S = 32
    mask = torch.zeros(1, S, S, 1)
    mask[:, 8:24, 8:20] = 1.0
    # an OpenCV camera at the origin looking down +z, focal S: (0, 0, 2) projects to pixel (16, 16), inside the mask;
    # (0.5, 0, 2) to (24, 16), 5 columns right of it
    means = torch.tensor([[[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]]], requires_grad=True)  # [B=1,N=2,3]
    batch = {"image": mask.expand(-1, -1, -1, 3), "mask": mask, "mask_dist": mask_distance(mask[0, ..., 0])[None],
             "viewmat": torch.eye(4)[None], "K": torch.tensor([[[S, 0.0, S / 2], [0.0, S, S / 2], [0.0, 0.0, 1.0]]])}
    out = TrainingRender(mask.expand(-1, -1, -1, 3), mask.clone(), batch, {"means": means}, None)  # alpha covers the mask
    chamfer = instantiate(compose(["silhouette=chamfer"]).silhouette)
    value, logs = chamfer(out)
    assert float(logs["sil_outside"]) > 0 and float(logs["sil_coverage"]) == 0
    (grad,) = torch.autograd.grad(value, means)
    assert torch.equal(grad[0, 0], torch.zeros(3))  # inside: no pull
    assert float(grad[0, 1, 0]) > 0  # right of the mask: a descent step moves it left, towards the mask
    with torch.no_grad():
        stepped = TrainingRender(out.rgb, out.alpha, batch, {"means": means - 0.1 * grad / grad.norm()}, None)
        assert float(chamfer(stepped)[0]) < float(value)
    none = instantiate(compose(["silhouette=none"]).silhouette)
    value, logs = none(out)
    assert float(value) == 0 and logs == {} and not value.requires_grad


def test_skinning_grid_is_built_from_the_body_and_frozen_and_the_mlp_trains(body):
    """skinning=grid (the default): weights diffused from the body's, close to them on its surface, and nothing in it
    trains (the λ3 term would have no gradient); skinning=mlp: every parameter gets a gradient from the weights."""
    vertices, sampled = body.canonical_vertices().detach(), slice(None, None, 97)
    grid = instantiate(compose(["skinning=grid", "skinning.voxel_size=0.05"]).skinning)
    grid.init_from_body(vertices, body.faces, body.skin_weights)
    w = grid(vertices[sampled])  # [V/97,24]
    assert torch.allclose(w.sum(-1), torch.ones(len(w)), atol=1e-5)
    ref = body.skin_weights[sampled]
    assert float(((w - ref) ** 2).sum(-1).mean()) < 0.3  # 0.22; the body's weights of other vertices: 1.5
    assert float((w.argmax(-1) == ref.argmax(-1)).float().mean()) > 0.75  # 0.83 (a coarse grid at joints)
    assert not any(p.requires_grad for p in grid.parameters()) and w.grad_fn is None
    mlp = instantiate(compose(["skinning=mlp"]).skinning)
    w = mlp(vertices[sampled])
    assert torch.allclose(w.sum(-1), torch.ones(len(w)), atol=1e-5)
    grads = torch.autograd.grad((w * torch.rand_like(w)).sum(), list(mlp.parameters()))
    assert all(g.abs().sum() > 0 for g in grads)


def test_a_missing_setting_is_named_unless_its_option_has_no_such_argument():
    """A checked key missing from the config is an error naming it (it was skipped without a word); a key of another
    option of the group (the MLP's skinning.hidden_dim under the grid, sheet keys under sheet=none) is not missing."""
    from omegaconf import open_dict

    from realityavatar.config import check_settings

    cfg = compose(["density=default"])
    check_settings(cfg)  # skinning=grid has no hidden_dim, sheet=none no hull_voxel, and they are not asked for
    with open_dict(cfg):
        del cfg.density["reset_every"]
        del cfg.eval["supersample"]
        del cfg.encoder["part_dim"]
    with pytest.raises(ValueError) as e:
        check_settings(cfg)
    for key in ("density.reset_every", "eval.supersample", "encoder.part_dim"):
        assert f"{key}: missing" in str(e.value), str(e.value)


def test_an_unknown_eval_protocol_stops_the_run_before_training():
    """eval.protocol is checked with the other settings (before step 0, not after training), against the protocols
    metrics.py defines."""
    from realityavatar.config import EVAL_PROTOCOLS, check_settings, compose
    from realityavatar.metrics import PROTOCOLS

    assert set(EVAL_PROTOCOLS) == set(PROTOCOLS)
    check_settings(compose(["eval.protocol=dyco"]))
    with pytest.raises(ValueError, match="eval.protocol"):
        check_settings(compose(["eval.protocol=dycoo"]))


@pytest.mark.parametrize("data, feedback", [("synthetic_ci", "datamodule"), ("i3d_ID2_1", "datamodule"),
                                            ("zju_377_mono", "samplers")])
def test_a_run_folder_from_before_the_reader_components_reads_as_today(data, feedback):
    """config.yaml of a run trained before data.reader was a component (`reader: i3d | zju` with frame_interval or
    zju_*_frames beside it, the samplers in data/datamodule.py, I3DDataModule), or before SamplerFeedback moved from
    data/samplers.py to train.py, is read as today's config of the same settings (build._read_run, and resume's
    comparison)."""
    from omegaconf import OmegaConf, open_dict

    from realityavatar.config import upgrade_run_config

    today = compose([f"data={data}"])
    old = OmegaConf.create(OmegaConf.to_container(today))
    with open_dict(old):
        reader = old.data.pop("reader")
        if reader._target_.endswith("ZJUReader"):
            old.data.reader = "zju"
            for k in ("train_frames", "novel_view_frames", "novel_pose_frames"):
                old.data[f"zju_{k}"] = reader[k]
        else:
            old.data.reader, old.data.frame_interval = "i3d", reader.frame_interval
            if data.startswith("i3d"):
                old.data._target_ = "realityavatar.data.i3d.I3DDataModule"
        old.data.sampler._target_ = "realityavatar.data.datamodule.HardFrameSampler"
        old.callbacks.sampler_feedback._target_ = f"realityavatar.data.{feedback}.SamplerFeedback"
    assert OmegaConf.to_container(upgrade_run_config(old)) == OmegaConf.to_container(today)
    assert OmegaConf.to_container(upgrade_run_config(today.copy())) == OmegaConf.to_container(today)


@pytest.mark.parametrize("cell", ["lstm", "gru"])
def test_a_run_folder_from_before_the_temporal_classes_reads_as_today(cell):
    """temporal `_target_: ...RecurrentTemporal` with `kind: lstm | gru` (run folders before LSTMTemporal and
    GRUTemporal) is read as today's class, whose weights keep their names (rnn.*): old checkpoints load."""
    from omegaconf import OmegaConf, open_dict

    from realityavatar.config import upgrade_run_config

    today = compose([f"temporal={cell}"])
    old = OmegaConf.create(OmegaConf.to_container(today))
    with open_dict(old):
        old.temporal._target_, old.temporal.kind = "realityavatar.model.temporal.RecurrentTemporal", cell
    assert OmegaConf.to_container(upgrade_run_config(old)) == OmegaConf.to_container(today)
    module = instantiate(today.temporal)
    assert sorted(module.state_dict()) == ["rnn.bias_hh_l0", "rnn.bias_ih_l0", "rnn.weight_hh_l0", "rnn.weight_ih_l0"]
    assert type(module.rnn).__name__ == cell.upper()
