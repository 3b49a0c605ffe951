"""Rebuilding a run from its folder: overrides move the keys interpolated from them."""

from __future__ import annotations

import pytest
from hydra.errors import InstantiationException


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


def test_an_override_of_a_key_the_run_has_not_is_refused_unless_added_or_a_default(trained_run, tmp_path):
    """A typo (`eval.supersampl=2`) is refused naming the key: merged, it was added to the config unread, and the run
    evaluated at the default without a word. `+key=value` adds a key; a key of today's defaults that the run's config
    predates (its config without `eval.supersample`) may be set."""
    import shutil

    from omegaconf import OmegaConf

    from realityavatar.build import load_run

    out, _ = trained_run
    with pytest.raises(ValueError, match=r"no key 'eval\.supersampl' \(to add one: \+eval\.supersampl=2\)"):
        load_run(out, ["eval.supersampl=2"])
    assert load_run(out, ["+eval.supersampl=2"])[0].eval.supersampl == 2
    old = tmp_path / "old_run"
    shutil.copytree(out, old)
    for name in ("config.yaml", "config_unresolved.yaml"):
        cfg = OmegaConf.load(old / name)
        del cfg.eval["supersample"]
        OmegaConf.save(cfg, old / name)
    assert load_run(old, ["eval.supersample=2"])[0].eval.supersample == 2


def test_perceptual_loss_finds_vgg19_in_torch_hub_cache(tmp_path, monkeypatch):
    """loss=vgg19 with vgg19_weights unset takes torchvision's vgg19 from torch's hub cache, and says where it came
    from; the default loss is D-SSIM whatever the cache holds (a run's loss does not depend on the machine)."""
    from realityavatar.build import build_losses
    from realityavatar.config import compose
    from tests.helpers import plant_found_weights

    with pytest.raises(InstantiationException, match="vgg19_weights: expected a torchvision vgg19"):
        build_losses(compose(["loss=vgg19"]))  # nothing found (tests/conftest.py)
    found = plant_found_weights(tmp_path, monkeypatch, lin=False, vgg16=False, vgg19=True)
    losses = build_losses(compose())
    assert list(losses) == ["rgb", "mask", "perceptual", "silhouette"] and losses["perceptual"].kind == "dssim"
    assert not any(t.weights_from for t in losses.values())
    losses = build_losses(compose(["loss=vgg19"]))
    assert losses["perceptual"].kind == "vgg19" and losses["perceptual"].weights_from == f"torch hub {found['vgg19']}"
    losses = build_losses(compose(["loss=vgg19", f"loss.perceptual.vgg19_weights={found['vgg19']}"]))
    assert losses["perceptual"].weights_from == f"loss.perceptual.vgg19_weights {found['vgg19']}"
    (tmp_path / "torch_home" / "hub" / "checkpoints" / "vgg19-dcbb9e9d.pth").write_bytes(b"\0" * 64)  # truncated
    with pytest.raises(InstantiationException, match=f"'{found['vgg19']}': not a torch state dict file"):
        build_losses(compose(["loss=vgg19"]))


def test_a_run_folder_from_before_the_reader_components_still_serves_its_data(trained_run, tmp_path):
    """evaluate / animate / posed export / the probes rebuild the data of a run trained before data.reader was a
    component (its config.yaml and config_unresolved.yaml: `reader: i3d`, `frame_interval`, the samplers named in
    data/datamodule.py), with overrides or without, and resume=true finds its settings unchanged."""
    import shutil

    from realityavatar.build import build_data, load_avatar
    from realityavatar.data.i3d import I3DReader

    out, _ = trained_run
    old = tmp_path / "old_run"
    shutil.copytree(out, old)
    for name in ("config.yaml", "config_unresolved.yaml"):
        text = (old / name).read_text()
        assert "    _target_: realityavatar.data.i3d.I3DReader\n    frame_interval: 1\n" in text
        text = text.replace("  reader:\n    _target_: realityavatar.data.i3d.I3DReader\n    frame_interval: 1\n",
                            "  reader: i3d\n  frame_interval: 1\n")
        (old / name).write_text(text.replace("data.samplers.", "data.datamodule."))
    for overrides in ([], ["data.val_items=1"]):
        cfg, avatar, _ = load_avatar(old, overrides)
        dm = build_data(cfg, avatar.body)
        assert isinstance(dm.reader, I3DReader) and dm.reader.frame_interval == 1 and dm.num_train_frames > 0
    # resume=true compares today's settings with the folder's: the same run, not a changed one
    from omegaconf import OmegaConf

    from realityavatar.runs import claim_run_dir

    today = OmegaConf.load(out / "config.yaml")
    today.resume = True
    assert claim_run_dir(old, today) == old / "last.ckpt"
