"""Builds a run's components from a composed config (hydra instantiate) and restores them from a run folder."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

# importing config also registers the resolvers
from realityavatar.config import RAW_CONFIG_NAME, check_settings, compose, upgrade_run_config
from realityavatar.metrics import build_lpips
from realityavatar.model.avatar import Avatar, Schedule
from realityavatar.runs import CKPT_NAME, read_checkpoint


def build_avatar(cfg: DictConfig, body, num_train_frames: int, data=None, training: dict | None = None) -> Avatar:
    """Instantiate the avatar's components from their config groups (model/avatar.py), without Lightning.

    data: the set-up DataModule, for components laid out from the training data (sheet.profile=rest: the rest
    frame's masks); None when a run is rebuilt from its checkpoint. training (build_module): a dict that receives
    the density control and the loss terms, built where they always were, between colour and shading.
    """
    # The order of construction is the order of the global random draws: it fixes every run's initial weights
    # (loss=vgg19's layers draw before sheet=skirt's motion basis).
    gaussians = instantiate(cfg.gaussians, body=body)
    encoder = instantiate(cfg.encoder)
    temporal = instantiate(cfg.temporal)
    deformer = instantiate(cfg.deformer)
    skinning = instantiate(cfg.skinning)
    color = instantiate(cfg.color, num_frames=max(int(num_train_frames), 1))  # the per-frame latent table Z_r
    if training is not None:
        training.update(density=instantiate(cfg.density), losses=build_losses(cfg))
    shading = instantiate(cfg.shading)
    sheet = instantiate(cfg.sheet, body=body, data=data)
    if training is not None:
        training["losses"].update(sheet.loss_terms())  # a component's own terms (SlidingSheet's smoothness)
    return Avatar(body, gaussians, encoder, temporal, deformer, skinning, color, shading, sheet,
                  render=OmegaConf.to_container(cfg.render, resolve=True))


def build_module(cfg: DictConfig, body, num_train_frames: int, scene_extent: float, data=None):
    """`build_avatar` and the training around it (model/module.py AvatarModule): loss terms, density control,
    optimizer, schedule, evaluation metrics."""
    from realityavatar.model.module import AvatarModule  # Lightning: only where a module is built

    training: dict = {}
    avatar = build_avatar(cfg, body, num_train_frames, data, training)
    m = cfg.get("metrics", {}) or {}
    lpips, lpips_status = build_lpips("vgg", m.get("lpips_backbone_weights"), m.get("lpips_weights"))
    module = AvatarModule(
        avatar,
        **training,
        optimizer=instantiate(cfg.optim.optimizer),
        lr=OmegaConf.to_container(cfg.optim.lr, resolve=True),
        final_factor=OmegaConf.to_container(cfg.optim.final_factor, resolve=True),
        schedule=Schedule.from_config(OmegaConf.to_container(cfg.schedule, resolve=True)),
        grad_clip=cfg.optim.get("grad_clip"),
        max_steps=int(cfg.iterations),
        scene_extent=scene_extent,
        lpips=lpips,
        eval_supersample=int((cfg.get("eval") or {}).get("supersample", 1)),  # run folders from before it: 1
    )
    module.lpips_status = lpips_status  # "computed (<weights' source>)" or why not, recorded in metrics.json
    # where the perceptual loss's VGG19 came from (None: not used)
    module.perceptual_weights = next((t.weights_from for t in training["losses"].values() if t.weights_from), None)
    return module


def build_losses(cfg: DictConfig) -> dict:
    """The loss terms, summed in this order: conf/loss's, then the silhouette group's."""
    return {**{name: instantiate(term) for name, term in cfg.loss.items()}, "silhouette": instantiate(cfg.silhouette)}


def build_data(cfg: DictConfig, body):
    dm = instantiate(cfg.data, body=body)
    dm.prepare_data()
    dm.setup("fit")
    return dm


def _dotlist(overrides: list[str] | None, cfg: DictConfig) -> list[str]:
    """Command-line overrides for a saved run's config `cfg`. As in hydra, `key=value` sets a key the config has (or
    that today's defaults have: a run from before the key existed) and `+key=value` / `++key=value` adds one; a key in
    neither is a typo (`eval.supersampl=2` would evaluate at the default, without a word) and is refused, naming it.
    Hydra's `~key` (delete) has no meaning for a trained run and is refused, as is an override without `=`."""
    out, defaults, absent = [], None, object()
    for o in overrides or []:
        if o.startswith("~") or "=" not in o:
            raise ValueError(f"override {o!r}: expected key=value (or +key=value) for a saved run's config")
        key = o.split("=", 1)[0]
        if not o.startswith("+") and OmegaConf.select(cfg, key, default=absent, throw_on_resolution_failure=False) is absent:
            defaults = defaults if defaults is not None else compose([])
            if OmegaConf.select(defaults, key, default=absent, throw_on_resolution_failure=False) is absent:
                raise ValueError(f"override {o!r}: the run's config has no key {key!r} (to add one: +{o})")
        out.append(o.lstrip("+"))
    return out


def _read_run(run_dir: str | Path, overrides: list[str] | None, ckpt: str | Path | None):
    """A run folder's config (with `overrides`), checkpoint and run_info block, and its body model."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path} not found: expected a run folder written by realityavatar-train")
    raw_path = run_dir / RAW_CONFIG_NAME
    if overrides and raw_path.is_file():
        # Overrides go into the run's unresolved config, so keys interpolated from them follow (as in train).
        cfg = upgrade_run_config(OmegaConf.load(raw_path))
        overrides = _dotlist(overrides, cfg)
        cfg.merge_with_dotlist(overrides)
        OmegaConf.resolve(cfg)
    else:
        cfg = upgrade_run_config(OmegaConf.load(cfg_path))
        overrides = _dotlist(overrides, cfg)
        if overrides:  # a run folder from before config_unresolved.yaml existed
            cfg.merge_with_dotlist(overrides)
    if overrides:
        check_settings(cfg)  # a bad value names its key before anything is built from it
    ckpt = Path(ckpt) if ckpt else run_dir / CKPT_NAME
    if not ckpt.is_file():
        raise FileNotFoundError(f"checkpoint {ckpt} not found in run folder {run_dir}")
    state = read_checkpoint(ckpt)
    info = state.get("realityavatar", {})
    if not info:
        raise KeyError(f"{ckpt}: checkpoint has no 'realityavatar' block (not written by realityavatar-train)")
    return cfg, state, info, instantiate(cfg.body)


def _rebuild(build, run_dir: str | Path):
    """build() of a run folder's components; a config.yaml of another version names the commit that trained it."""
    try:
        return build()
    except InstantiationException as e:  # a config.yaml of another version (an option or key since removed)
        raise ValueError(f"{Path(run_dir) / 'config.yaml'} does not build with this version of realityavatar ({e}): an "
                         f"option it sets was removed (docs/research/removed-options.md). It loads with the commit that "
                         f"trained it: git checkout {_trained_at(Path(run_dir))}") from e


def load_avatar(run_dir: str | Path, overrides: list[str] | None = None, ckpt: str | Path | None = None):
    """Rebuild (cfg, avatar, run_info) from a run folder written by `realityavatar-train`: the trained Avatar alone
    (model/avatar.py; no loss terms, optimizer or Lightning module), in eval mode, as export, view and animate use it."""
    cfg, state, info, body = _read_run(run_dir, overrides, ckpt)
    avatar = _rebuild(lambda: build_avatar(cfg, body, info["num_train_frames"]), run_dir)
    avatar.load_state_dict({k.removeprefix("avatar."): v for k, v in state["state_dict"].items()
                            if k.startswith("avatar.")})
    # step-dependent state: the decoder's coarse-to-fine window where the checkpoint's step had it
    schedule = Schedule.from_config(OmegaConf.to_container(cfg.schedule, resolve=True))
    avatar.deformer.set_window(schedule.deform_window(state.get("global_step")))
    return cfg, avatar.eval(), info


def load_run(run_dir: str | Path, overrides: list[str] | None = None, ckpt: str | Path | None = None):
    """Rebuild (cfg, module, run_info) from a run folder written by `realityavatar-train`: the AvatarModule that
    trained (evaluation's trainer.test, the probes), in eval mode."""
    cfg, state, info, body = _read_run(run_dir, overrides, ckpt)
    module = _rebuild(lambda: build_module(cfg, body, info["num_train_frames"], info["scene_extent"]), run_dir)
    module.load_state_dict(state["state_dict"])
    module.set_progress(state.get("global_step"))  # step-dependent state (the decoder's coarse-to-fine window)
    module.eval()
    return cfg, module, info


def _trained_at(run_dir: Path) -> str:
    """The commit a run folder's metrics.json records (without -dirty); c46aa26 where it records none (runs from
    before the consolidation, or a run that stopped before writing it)."""
    try:
        commit = str(json.loads((run_dir / "metrics.json").read_text())["commit"]).removesuffix("-dirty")
    except (OSError, ValueError, KeyError):
        return "c46aa26"
    return commit if commit and commit != "unknown" else "c46aa26"


def run_device(cfg: DictConfig, override: str | None = None) -> torch.device:
    """The device a trained run renders on: `override` if given, else CUDA when the run's trainer asked for a GPU
    (accelerator gpu/cuda/auto) and one is present, else the CPU."""
    if override:
        return torch.device(override)
    acc = str(cfg.get("trainer", {}).get("accelerator", "cpu"))
    return torch.device("cuda" if acc in ("gpu", "cuda", "auto") and torch.cuda.is_available() else "cpu")


def git_commit() -> str:
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             check=False)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                               timeout=5, check=False)
        sha = out.stdout.strip() or "unknown"
        return sha + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):  # no git, or not a checkout: the commit is unknown
        return "unknown"


def write_json(path: Path, data: dict) -> None:
    """Write through a temporary file so an interrupted write never leaves a truncated metrics file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=float))
    tmp.replace(path)
