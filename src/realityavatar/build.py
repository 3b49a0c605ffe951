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
from realityavatar.config import RAW_CONFIG_NAME, check_settings, compose
from realityavatar.metrics import build_lpips
from realityavatar.model.module import AvatarModule, Schedule
from realityavatar.runs import CKPT_NAME, read_checkpoint


def build_module(cfg: DictConfig, body, num_train_frames: int, scene_extent: float, data=None) -> AvatarModule:
    """Instantiate every component from its config group and hand them to the LightningModule.

    data: the set-up DataModule, for components laid out from the training data (sheet.profile=rest: the rest
    frame's masks); None when a run is rebuilt from its checkpoint.
    """
    # The order of construction is the order of the global random draws: it fixes every run's initial weights.
    gaussians = instantiate(cfg.gaussians, body=body)
    encoder = instantiate(cfg.encoder)
    temporal = instantiate(cfg.temporal)
    deformer = instantiate(cfg.deformer)
    skinning = instantiate(cfg.skinning)
    color = instantiate(cfg.color, num_frames=max(int(num_train_frames), 1))  # the per-frame latent table Z_r
    density = instantiate(cfg.density)
    losses = build_losses(cfg)
    shading = instantiate(cfg.shading)
    sheet = instantiate(cfg.sheet, body=body, data=data)
    m = cfg.get("metrics", {}) or {}
    lpips, lpips_status = build_lpips("vgg", m.get("lpips_backbone_weights"), m.get("lpips_weights"))
    module = AvatarModule(
        body=body,
        gaussians=gaussians,
        encoder=encoder,
        temporal=temporal,
        deformer=deformer,
        skinning=skinning,
        color=color,
        shading=shading,
        sheet=sheet,
        density=density,
        losses=losses,
        optimizer=instantiate(cfg.optim.optimizer),
        lr=OmegaConf.to_container(cfg.optim.lr, resolve=True),
        final_factor=OmegaConf.to_container(cfg.optim.final_factor, resolve=True),
        render=OmegaConf.to_container(cfg.render, resolve=True),
        schedule=Schedule.from_config(OmegaConf.to_container(cfg.schedule, resolve=True)),
        grad_clip=cfg.optim.get("grad_clip"),
        max_steps=int(cfg.iterations),
        scene_extent=scene_extent,
        lpips=lpips,
        eval_supersample=int((cfg.get("eval") or {}).get("supersample", 1)),  # run folders from before it: 1
    )
    module.lpips_status = lpips_status  # "computed (<weights' source>)" or why not, recorded in metrics.json
    # where the perceptual loss's VGG19 came from (None: not used)
    module.perceptual_weights = next((t.weights_from for t in losses.values() if t.weights_from), None)
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


def load_run(run_dir: str | Path, overrides: list[str] | None = None, ckpt: str | Path | None = None):
    """Rebuild (cfg, module, run_info) from a run folder written by `realityavatar-train`."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path} not found: expected a run folder written by realityavatar-train")
    raw_path = run_dir / RAW_CONFIG_NAME
    if overrides and raw_path.is_file():
        # Overrides go into the run's unresolved config, so keys interpolated from them follow (as in train).
        cfg = OmegaConf.load(raw_path)
        overrides = _dotlist(overrides, cfg)
        cfg.merge_with_dotlist(overrides)
        OmegaConf.resolve(cfg)
    else:
        cfg = OmegaConf.load(cfg_path)
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
    body = instantiate(cfg.body)
    try:
        module = build_module(cfg, body, info["num_train_frames"], info["scene_extent"])
    except InstantiationException as e:  # a config.yaml of another version (an option or key since removed)
        raise ValueError(f"{cfg_path} does not build with this version of realityavatar ({e}): an option it sets was "
                         f"removed (docs/research/removed-options.md). It loads with the commit that trained it: "
                         f"git checkout {_trained_at(run_dir)}") from e
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
