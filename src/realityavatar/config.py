"""Hydra/OmegaConf helpers shared by the entry points and the tests (resolvers, config root, choices)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

CONFIG_DIR = Path(__file__).resolve().parents[2] / "conf"


def _register() -> None:
    if not OmegaConf.has_resolver("int_mul"):
        OmegaConf.register_new_resolver("int_mul", lambda a, b: int(float(a) * float(b)))
    if not OmegaConf.has_resolver("int_max"):
        OmegaConf.register_new_resolver("int_max", lambda *a: max(int(float(x)) for x in a))


_register()


def config_dir() -> str:
    if not (CONFIG_DIR / "train.yaml").is_file():
        raise FileNotFoundError(
            f"config folder {CONFIG_DIR} with train.yaml not found: install the project editable "
            "(`pip install -e .` from the repository) so the conf/ folder beside src/ is used"
        )
    return str(CONFIG_DIR)


def choices_of(cfg: DictConfig) -> dict:
    """The chosen option of every config group (from hydra's runtime choices when available)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        ch = dict(HydraConfig.get().runtime.choices)
    except ValueError:  # composed outside @hydra.main (tests): HydraConfig is not set
        ch = dict(cfg.get("_choices", {}) or {})
    return {k: v for k, v in ch.items() if not k.startswith("hydra") and v is not None}


RAW_CONFIG_NAME = "config_unresolved.yaml"


def prepare_run(cfg: DictConfig, out_dir) -> tuple[DictConfig, dict]:
    """A `compose()` result made into what `train.run` takes, as @hydra.main hands it over: the hydra node dropped,
    out_dir set; returns it with the chosen option of every group."""
    from omegaconf import open_dict

    choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra") and v is not None}
    with open_dict(cfg):
        del cfg["hydra"]
        cfg.out_dir = str(out_dir)
    return cfg, choices


def unresolved_copy(cfg: DictConfig) -> DictConfig:
    """The config with its interpolations kept (`${seed}`, `${int_mul:...}`), so overrides applied to it later move
    every key derived from them; values read from the environment or from hydra's runtime are frozen to what
    they were for this run."""
    raw = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))

    def freeze(node, resolved):
        for key in list(node.keys() if isinstance(node, DictConfig) else range(len(node))):
            if OmegaConf.is_interpolation(node, key):
                if any(s in str(node._get_node(key)._value()) for s in ("${oc.env", "${hydra:")):
                    node[key] = resolved[key]
            elif isinstance(node[key], (DictConfig, ListConfig)):
                freeze(node[key], resolved[key])

    freeze(raw, cfg)
    return raw


# Run folders written before the readers became components (data.reader._target_), the samplers and the device
# cache left data/datamodule.py, the temporal module's cell became a class (temporal.kind) and the sampler feedback
# (a Lightning callback) moved to data/lightning.py: what their config.yaml named, and where it is now.
MOVED_TARGETS = {f"realityavatar.data.datamodule.{name}": f"realityavatar.data.samplers.{name}"
                 for name in ("EpochShuffle", "HardFrameSampler")}
MOVED_TARGETS.update({f"realityavatar.data.{where}.SamplerFeedback": "realityavatar.data.lightning.SamplerFeedback"
                      for where in ("datamodule", "samplers")})
MOVED_TARGETS["realityavatar.data.i3d.I3DDataModule"] = "realityavatar.data.datamodule.AvatarDataModule"


def upgrade_run_config(cfg: DictConfig) -> DictConfig:
    """A saved run's config (config.yaml) in today's form, in place: `data.reader: i3d | zju` with the layout's keys
    beside it (frame_interval, zju_*_frames) becomes the reader component, `temporal.kind: lstm | gru` the class of
    that cell, and moved classes are named where they are. A config already in today's form is returned unchanged."""
    from omegaconf import open_dict

    data = cfg.get("data")
    with open_dict(cfg):
        if isinstance(data, DictConfig) and isinstance(data.get("reader"), str):
            if data.pop("reader") == "zju":
                data.reader = {"_target_": "realityavatar.data.zju.ZJUReader",
                               "train_frames": data.pop("zju_train_frames", [0, 0, 1]),
                               **{k: data.pop(f"zju_{k}", None) for k in ("novel_view_frames", "novel_pose_frames")}}
            else:
                data.reader = {"_target_": "realityavatar.data.i3d.I3DReader",
                               "frame_interval": data.pop("frame_interval", 1)}
        temporal = cfg.get("temporal")
        if isinstance(temporal, DictConfig) and "kind" in temporal and temporal.get("_target_", "").endswith(".RecurrentTemporal"):
            temporal._target_ = f"realityavatar.model.temporal.{temporal.pop('kind').upper()}Temporal"
        for key in ("data", "data.sampler", "callbacks.sampler_feedback"):
            node = OmegaConf.select(cfg, key, default=None)
            if isinstance(node, DictConfig) and node.get("_target_") in MOVED_TARGETS:
                node._target_ = MOVED_TARGETS[node._target_]
    return cfg


def compose(overrides: list[str] | None = None, config_name: str = "train") -> DictConfig:
    """Compose the primary config exactly as `realityavatar-train <overrides>` would, hydra node included."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=list(overrides or []), return_hydra_config=True)


# Settings checked before anything is built: key -> (rule, what is expected). A key missing from the config is an
# error naming it, unless it sits in a component whose class does not take it (`skinning.hidden_dim` is the MLP's,
# not the grid's: `_applies`); interpolated keys derived from these are not checked separately.
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


RENDER_BACKENDS = ("auto", "numba", "torch", "gsplat")  # rasterize(backend=...) in render/splat.py


def _is_num(v) -> bool:
    import math

    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


EVAL_PROTOCOLS = ("ours", "dyco", "seqavatar")  # metrics.PROTOCOLS' names, checked before training starts
SETTINGS = {
    "iterations": (lambda v: _is_int(v) and v >= 1, "a whole number of training steps >= 1"),
    "seed": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "threads": (lambda v: v is None or (_is_int(v) and v >= 1), "null or a whole number >= 1"),
    "data.image_scale": (lambda v: _is_num(v) and 0 < v <= 8, "a number in (0, 8] (1.0 = full resolution)"),
    "data.batch_size": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "data.num_workers": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "data.window_len": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "data.window_step": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "data.max_train_frames": (lambda v: v is None or (_is_int(v) and v >= 1), "null or a whole number >= 1"),
    "data.frame_subsample": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "data.train_frame_subsample": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "data.val_items": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "gaussians.num_points": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "render.backend": (lambda v: v in RENDER_BACKENDS, f"one of {', '.join(RENDER_BACKENDS)} (conf/render/default.yaml)"),
    "schedule.skin_pretrain_steps": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "eval.max_frames_per_split": (lambda v: v is None or (_is_int(v) and v >= 1), "null (every frame) or a whole number >= 1"),
    "eval.supersample": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1 (1 = render at the images' size)"),
    "eval.save_images": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0 (0 = no image grids)"),
    "eval.save_video": (lambda v: isinstance(v, bool), "true or false"),
    "eval.fps_warmup": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    "eval.fps_frames": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "eval.protocol": (lambda v: v in EVAL_PROTOCOLS, f"one of {', '.join(EVAL_PROTOCOLS)} (metrics.PROTOCOLS)"),
    "resume": (lambda v: isinstance(v, bool), "true or false"),
    "overwrite": (lambda v: isinstance(v, bool), "true or false"),
    "trainer.log_every_n_steps": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "trainer.precision": (lambda v: v in (32, "32", "32-true"), ("32: the renderers, kernels and losses compute in "
                          "float32 (16 / bf16 stopped in the numba renderer with 'unsupported ScalarType BFloat16')")),
    "schedule.deform_start": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
    # the networks' sizes (a size torch cannot make fails deep in a constructor without the key's name)
    **{k: (lambda v: _is_int(v) and v >= 1, "a whole number >= 1") for k in (
        "encoder.part_dim", "encoder.hidden_dim", "encoder.out_dim", "temporal.hidden_dim", "temporal.num_layers",
        "deformer.hidden_dim", "deformer.num_layers", "skinning.hidden_dim", "skinning.num_layers", "color.hidden_dim")},
    **{k: (lambda v: _is_int(v) and v >= 0, "a whole number >= 0") for k in (
        "encoder.clothes_latent_dim", "deformer.feature_dim", "deformer.num_freqs", "skinning.num_freqs")},
    **{k: (lambda v: _is_num(v) and v >= 0, "a number >= 0") for k in (
        "gaussians.feature_init_std", "encoder.latent_init_std", "silhouette.near", "optim.grad_clip", "optim.lr.*",
        "loss.*.weight", "loss.*.weight_after", "density.grad_threshold")},
    "optim.final_factor.*": (lambda v: _is_num(v) and v > 0, "a number > 0 (the learning rate's factor at the last step)"),
    "loss.*.samples": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "silhouette.max_pixels": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "silhouette.covered_alpha": (lambda v: _is_num(v) and 0 <= v <= 1, "a number in [0, 1]"),
    "density.refine_every": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "density.reset_every": (lambda v: _is_int(v) and v >= 0, "a whole number >= 0 (0 = no opacity reset)"),
    "density.max_points": (lambda v: _is_int(v) and v >= 1, "a whole number >= 1"),
    "density.prune_opacity": (lambda v: _is_num(v) and 0 <= v < 1, "a number in [0, 1)"),
    **{k: (lambda v: _is_num(v) and v > 0, "a number > 0") for k in (
        "density.grow_scale3d", "density.prune_scale3d", "density.scene_scale", "optim.optimizer.eps",
        "sheet.hull_voxel", "sheet.normal_scale")},
    "sheet.max_stretch": (lambda v: _is_num(v) and v >= 0, "a number >= 0 (0: unbounded)"),
    **{k: (lambda v: _is_num(v), "a finite number (metres)") for k in (
        "sheet.top_offset", "sheet.bottom_offset", "sheet.margin")},
}


def _applies(cfg: DictConfig, key: str) -> bool:
    """False when `key` sits in a component node (one with `_target_`) whose class or function has no argument of
    that name: the option chosen for that group does not have this setting."""
    import inspect

    from hydra.utils import get_object

    head, _, name = key.rpartition(".")
    node = OmegaConf.select(cfg, head, default=None) if head else cfg
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return True
    try:
        params = inspect.signature(get_object(node._target_)).parameters
    except (ImportError, AttributeError, ValueError, TypeError):  # instantiate names a bad target when it builds
        return True
    return name in params and params[name].kind is not inspect.Parameter.VAR_KEYWORD


def _keys(cfg: DictConfig, key: str) -> list[str]:
    """A SETTINGS key, or for one with a `*` segment (`optim.lr.*`, `loss.*.weight`) every key of that node."""
    if "*" not in key:
        return [key]
    head, _, tail = key.partition(".*")
    node = OmegaConf.select(cfg, head, default=None)
    return [f"{head}.{k}{tail}" for k in node] if isinstance(node, DictConfig) else []


class ConfigError(ValueError):
    """A setting of the composed config is not what its key takes (the key named as typed on the command line)."""


def check_settings(cfg: DictConfig, prefix: str = "") -> None:
    """Raise ValueError naming the key as typed on the command line (`iterations=...`) for every bad setting in
    SETTINGS (all problems at once); `prefix` limits the check to one section, e.g. "eval."."""
    from omegaconf.errors import OmegaConfBaseException

    problems = []
    for key, (ok, expected) in ((k, rule) for pattern, rule in SETTINGS.items() if pattern.startswith(prefix)
                                for k in _keys(cfg, pattern)):
        try:
            value = OmegaConf.select(cfg, key, default="<absent>", throw_on_missing=True)
        except OmegaConfBaseException as e:
            problems.append(f"{key}: cannot be resolved ({e}); expected {expected}")
            continue
        if isinstance(value, str) and value == "<absent>":
            if _applies(cfg, key):
                problems.append(f"{key}: missing; expected {expected}")
            continue
        if not ok(value):
            problems.append(f"{key}={value!r}: expected {expected}")
    if problems:
        raise ConfigError("; ".join(problems))
