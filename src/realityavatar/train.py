"""Training entry point: `realityavatar-train [group=option ...] [key=value ...]` fits, tests, writes metrics.json."""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import hydra
import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf

from realityavatar.config import RAW_CONFIG_NAME, choices_of, config_dir, unresolved_copy

# Lightning notices that do not apply here: density control needs manual optimisation, and there is no val loop.
for _msg in (".*pre-optimization state.*", ".*`validation_step`.*", ".*LeafSpec.*", ".*is not empty.*", ".*litlogger.*",
             ".*does not have many workers.*", ".*overridden `on_after_batch_transfer`.*"):
    warnings.filterwarnings("ignore", message=_msg)


def run(cfg: DictConfig, choices: dict | None = None) -> dict:
    """Fit one avatar and evaluate it; returns the metrics that were written to <out_dir>/metrics.json."""
    from hydra.utils import instantiate

    from realityavatar.build import CKPT_NAME, build_data, build_module, git_commit, write_json
    from realityavatar.evaluate import evaluate_module, format_table
    from realityavatar.model.module import check_single_process

    pl.seed_everything(int(cfg.seed), workers=True)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # The resolved config beside the checkpoint is what evaluate/animate/export rebuild the run from.
    OmegaConf.save(cfg, out_dir / "config.yaml", resolve=True)
    OmegaConf.save(unresolved_copy(cfg), out_dir / RAW_CONFIG_NAME)  # what later key=value overrides apply to
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    module.run_info.update(num_train_frames=dm.num_train_frames, train_frame_ids=list(map(int, dm.train_frame_ids)))
    # Callbacks and loggers come from their config groups (conf/callbacks, conf/logger), one entry each.
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    check_single_process(trainer)  # before fit: a DDP launch would start the other ranks
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=dm, ckpt_path=cfg.get("ckpt_path"))
    train_seconds = time.perf_counter() - t0
    choices = choices if choices is not None else choices_of(cfg)
    header = {
        "config": choices,
        "overrides": list(cfg.get("_overrides", []) or []),
        "seed": int(cfg.seed),
        "commit": git_commit(),
        "scene": getattr(dm, "sequence", None),
        "train_seconds": train_seconds,
        "iterations": int(trainer.global_step),
        "num_gaussians": int(module.gaussians.num_points),
        "num_parameters": module.num_parameters(),
        "perceptual": getattr(module.loss_fn, "perceptual_kind", "unknown"),
        "lpips": module.lpips_status,
        # From a real training render: Lightning's teardown has moved the module back to the CPU by now, and gsplat
        # may have fallen back to torch.
        "device": module.run_info.get("render", {}).get("device", module.run_info.get("device", str(module.device))),
        "backend": module.run_info.get("render", {}).get("backend", "none (no training step ran)"),
        "backend_configured": cfg.render.get("backend", "auto"),
    }
    module.run_info["metrics_header"] = header
    trainer.save_checkpoint(out_dir / CKPT_NAME)
    metrics = dict(header)
    if cfg.get("test_after_fit", True):
        metrics.update(evaluate_module(module, dm, trainer, cfg, out_dir))
    write_json(out_dir / "metrics.json", metrics)
    print(format_table(metrics))
    print(f"run folder: {out_dir}  (metrics.json, {CKPT_NAME}, per_frame.csv, images/, videos/, logs/)")
    return metrics


@hydra.main(config_path=config_dir(), config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    OmegaConf.set_struct(cfg, False)
    cfg._overrides = list(hc.overrides.task)
    metrics = run(cfg, choices_of(cfg))
    return metrics.get("test/novel_view/psnr")


def main() -> None:
    try:
        _hydra_main()
    except KeyboardInterrupt:
        print("interrupted; the last checkpoint and logs are kept", file=sys.stderr)
        raise SystemExit(130)


if __name__ == "__main__":
    main()
