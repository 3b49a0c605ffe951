"""Training entry point: `realityavatar-train [group=option ...] [key=value ...]` fits, tests, writes metrics.json."""

from __future__ import annotations

import logging
import os
import random
import signal
import sys
import time
import warnings
from pathlib import Path

import hydra
import numpy as np
import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf

from realityavatar.config import RAW_CONFIG_NAME, choices_of, config_dir, unresolved_copy

log = logging.getLogger(__name__)

# Lightning notices that do not apply here: density control needs manual optimisation, and there is no val loop.
for _msg in (".*pre-optimization state.*", ".*`validation_step`.*", ".*LeafSpec.*", ".*is not empty.*", ".*litlogger.*",
             ".*does not have many workers.*", ".*overridden `on_after_batch_transfer`.*"):
    warnings.filterwarnings("ignore", message=_msg)


def run(cfg: DictConfig, choices: dict | None = None) -> dict:
    """Fit one avatar and evaluate it; returns the metrics that were written to <out_dir>/metrics.json.

    Order, so that a failure loses nothing that exists: settings are checked, the run folder is claimed (a folder
    holding another run refuses unless resume=true or overwrite=true), data and images are validated, and only then
    is config.yaml written and training started. After training, last.ckpt and metrics.json (training facts) are
    written first; evaluation adds to metrics.json and its failures are recorded there and raised at the end.
    """
    from realityavatar.config import check_settings
    from realityavatar.runs import claim_run_dir, read_checkpoint, restore_hydra_record, run_lock

    check_settings(cfg)
    check_accelerator(cfg)
    out_dir = Path(cfg.out_dir)
    owned = {"folder": False}
    with run_lock(out_dir):
        try:
            resume_from = claim_run_dir(out_dir, cfg)
            prior = read_checkpoint(resume_from) if resume_from is not None else None
            return _run(cfg, choices, out_dir, resume_from, prior, owned)
        except BaseException:
            if not owned["folder"]:  # failed before taking the folder: leave the previous run's record as it was
                restore_hydra_record(out_dir)
            raise


def check_accelerator(cfg: DictConfig) -> None:
    """A GPU trainer where torch sees no CUDA device stops here, before the scene is built (minutes at 512²), with what
    to run instead; Lightning would say so only when the trainer is made."""
    acc = str(OmegaConf.select(cfg, "trainer.accelerator", default="cpu"))
    if acc in ("gpu", "cuda") and not torch.cuda.is_available():
        why = (f"torch {torch.__version__} is a CPU build" if torch.version.cuda is None
               else f"torch {torch.__version__} (CUDA {torch.version.cuda}) sees no CUDA device")
        raise RuntimeError(f"trainer.accelerator={acc} (trainer=gpu, e.g. from +experiment=paper_scale): {why}. "
                           "Train on the CPU with trainer=cpu render.backend=numba, or install a CUDA build of torch "
                           "(README, GPU)")


def _run(cfg: DictConfig, choices: dict | None, out_dir: Path, resume_from: Path | None, prior: dict | None,
         owned: dict) -> dict:
    from hydra.utils import instantiate

    from realityavatar.build import CKPT_NAME, build_data, build_module, git_commit, write_json
    from realityavatar.data.lightning import TrainingData
    from realityavatar.evaluate import evaluate_module, format_table
    from realityavatar.model.module import check_single_process
    from realityavatar.runs import (
        clear_run_outputs,
        keep_hydra_record,
        previous_log_rows,
        seed_csv_log,
    )
    from realityavatar.runtime import set_threads, tune_malloc

    pl.seed_everything(int(cfg.seed), workers=True)
    set_threads(cfg.get("threads"))

    log.info("allocator: %s", tune_malloc())  # ~10% of a CPU step went to page faults of freshly mapped tensors
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)  # checks every image and mask of the selected splits
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    module.compile_path(str(cfg.get("compile", "none")))
    module.run_info.update(num_train_frames=dm.num_train_frames, train_frame_ids=list(map(int, dm.train_frame_ids)))
    # The run is valid: take the folder. The resolved config beside the checkpoint is what evaluate/animate/export
    # rebuild the run from.
    if cfg.get("overwrite") and resume_from is None:
        removed = clear_run_outputs(out_dir)
        if removed:
            log.warning("overwrite=true: removed the previous run's %s from %s", ", ".join(removed), out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out_dir / "config.yaml", resolve=True)
    OmegaConf.save(unresolved_copy(cfg), out_dir / RAW_CONFIG_NAME)  # what later key=value overrides apply to
    keep_hydra_record(out_dir)
    owned["folder"] = True
    # Callbacks and loggers come from their config groups (conf/callbacks, conf/logger), one entry each; RunState
    # (random states and training seconds across resumes) belongs to every run.
    state = RunState()
    callbacks = [state] + [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    for lg in loggers:
        if isinstance(lg, pl.loggers.CSVLogger):  # a resumed run appends to the log rows before its checkpoint
            seed_csv_log(lg, previous_log_rows(resume_from, int(prior["global_step"])) if prior else [])
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    check_single_process(trainer)  # before fit: a DDP launch would start the other ranks
    try:
        # data only, as read_checkpoint read it above
        trainer.fit(module, datamodule=TrainingData(dm), ckpt_path=str(resume_from) if resume_from else None,
                    weights_only=True)
    except SystemExit:
        if trainer.interrupted:  # Lightning turns a KeyboardInterrupt inside a step into exit(1)
            _interrupted(out_dir, trainer, saved=False)
        raise
    if state.interrupted:  # Ctrl-C: stopped cleanly after a step
        trainer.save_checkpoint(out_dir / CKPT_NAME, weights_only=False)
        _interrupted(out_dir, trainer, saved=True)
    choices = choices if choices is not None else choices_of(cfg)
    header = {
        "config": choices,
        "overrides": list(cfg.get("_overrides", []) or []),
        "seed": int(cfg.seed),
        "commit": git_commit(),
        "scene": getattr(dm, "sequence", None),
        "training_set": getattr(dm, "training_set", "host"),  # kept on the GPU (data.device_cache) or on the host
        "train_seconds": state.train_seconds(),
        "iterations": int(trainer.global_step),
        # training's peak of allocated GPU memory (null on a CPU)
        "peak_gpu_memory_gb": torch.cuda.max_memory_allocated() / 2**30 if torch.cuda.is_initialized() else None,
        "num_gaussians": int(module.avatar.gaussians.num_points),  # the free Gaussians (density control's)
        "num_sheet_gaussians": int(module.avatar.sheet.num_points),  # sheet=skirt's (none: 0)
        "sheet": module.run_info.get("sheet", {}),
        "num_parameters": module.avatar.num_parameters(),
        "perceptual": module.losses["perceptual"].kind if "perceptual" in module.losses else "none",
        "perceptual_weights": getattr(module, "perceptual_weights", None),  # where its VGG19 came from
        "lpips": module.lpips_status,
        # From a real training render: Lightning's teardown has moved the module back to the CPU by now, and gsplat
        # may have fallen back to torch.
        "device": module.run_info.get("render", {}).get("device", module.run_info.get("device", str(module.device))),
        "backend": module.run_info.get("render", {}).get("backend", "none (no training step ran)"),
        "backend_configured": cfg.render.get("backend", "auto"),
    }
    if prior is not None:
        header["resumed_from"] = {"checkpoint": str(resume_from), "step": int(prior["global_step"])}
    module.run_info["metrics_header"] = header
    trainer.save_checkpoint(out_dir / CKPT_NAME, weights_only=False)  # the whole state, to resume from
    # Training results first: whatever happens during evaluation, the run's facts are on disk.
    metrics = dict(header)
    metrics["evaluation"] = "pending" if cfg.get("test_after_fit", True) else "skipped (test_after_fit=false)"
    write_json(out_dir / "metrics.json", metrics)
    if cfg.get("test_after_fit", True):
        try:
            metrics.update(evaluate_module(module, dm, trainer, cfg, out_dir))
        except Exception as e:  # noqa: BLE001 - recorded, then raised below
            metrics.setdefault("evaluation_errors", {})["evaluate"] = f"{type(e).__name__}: {e}"
        metrics["evaluation"] = "failed" if metrics.get("evaluation_errors") else "done"
        write_json(out_dir / "metrics.json", metrics)
    print(format_table(metrics))
    print(f"run folder: {out_dir}  (metrics.json, {CKPT_NAME}, per_frame.csv, images/, videos/, logs/)")
    if metrics.get("evaluation_errors"):
        errs = "; ".join(f"{k}: {v}" for k, v in metrics["evaluation_errors"].items())
        raise EvaluationError(f"training finished but evaluation failed ({errs}); the training results are kept in "
                              f"{out_dir / 'metrics.json'} and {out_dir / CKPT_NAME}; re-evaluate with "
                              f"`realityavatar-evaluate run_dir={out_dir}`")
    return metrics


class EvaluationError(RuntimeError):
    """Evaluation after training failed; metrics.json holds the training facts and whatever evaluation produced."""


def _interrupted(out_dir: Path, trainer, saved: bool) -> None:
    from realityavatar.build import CKPT_NAME

    ckpt = out_dir / CKPT_NAME
    if ckpt.is_file():
        from realityavatar.runs import read_checkpoint

        step = read_checkpoint(ckpt)["global_step"] if not saved else trainer.global_step
        print(f"interrupted at step {trainer.global_step}; checkpoint kept: {ckpt} (step {step}). Continue with "
              f"`realityavatar-train hydra.run.dir={out_dir} resume=true` and the same settings", file=sys.stderr)
    else:
        print(f"interrupted at step {trainer.global_step}, before the first checkpoint: nothing to resume in {out_dir}",
              file=sys.stderr)
    raise SystemExit(130)


class RunState(pl.Callback):
    """Run state that Lightning does not checkpoint, so that a resumed run continues exactly where it stopped:
    the global RNG states (torch, numpy, python) at the checkpoint, the training seconds of every earlier part of
    the run, and a first Ctrl-C that stops at the end of the current step (a second one interrupts at once)."""

    def __init__(self) -> None:
        self.seconds_before = 0.0  # training seconds of the run's earlier parts (from the checkpoint)
        self._t0: float | None = None
        self._rng: dict | None = None
        self.interrupted = False
        self._old_handler = None

    def train_seconds(self) -> float:
        return self.seconds_before + (time.perf_counter() - self._t0 if self._t0 is not None else 0.0)

    # -- checkpoint
    def state_dict(self) -> dict:
        return {
            "train_seconds": self.train_seconds(),
            # plain types only, so Lightning's weights_only checkpoint loading accepts them
            "rng": {"torch": torch.get_rng_state(), "numpy": _np_state(), "python": random.getstate()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.seconds_before = float(state.get("train_seconds", 0.0))
        self._rng = state.get("rng")

    # -- hooks
    def on_fit_start(self, trainer, pl_module) -> None:
        self._t0 = time.perf_counter()

    def on_train_start(self, trainer, pl_module) -> None:
        # Restored here, after set-up, so nothing between this point and the next step draws from the global RNG.
        if self._rng is not None:
            torch.set_rng_state(self._rng["torch"])
            name, keys, pos, has_gauss, cached = self._rng["numpy"]
            np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
            random.setstate(self._rng["python"])
            self._rng = None
        if _main_thread():
            self._old_handler = signal.signal(signal.SIGINT, self._on_sigint)

    def _on_sigint(self, signum, frame) -> None:
        if self.interrupted:  # a second Ctrl-C: stop now
            raise KeyboardInterrupt
        self.interrupted = True
        print("\ninterrupt: stopping after this step and saving the checkpoint (Ctrl-C again to stop at once)",
              flush=True)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.interrupted:
            trainer.should_stop = True

    def on_fit_end(self, trainer, pl_module) -> None:
        self._restore_handler()

    def on_exception(self, trainer, pl_module, exception) -> None:
        self._restore_handler()

    def _restore_handler(self) -> None:
        if self._old_handler is not None and _main_thread():
            signal.signal(signal.SIGINT, self._old_handler)
        self._old_handler = None


def _np_state() -> tuple:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return (str(name), [int(k) for k in keys], int(pos), int(has_gauss), float(cached))


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


@hydra.main(config_path=config_dir(), config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    OmegaConf.set_struct(cfg, False)
    cfg._overrides = list(hc.overrides.task)
    try:
        metrics = run(cfg, choices_of(cfg))
    except people_errors() as e:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"realityavatar-train: {e}  (HYDRA_FULL_ERROR=1 shows the trace)", file=sys.stderr)
        raise SystemExit(1) from None
    return metrics.get("test/novel_view/psnr")


def people_errors() -> tuple[type[BaseException], ...]:
    """The project's own errors about a user's data and config, each naming the file or key and the field: training
    ends on them with their message alone, as hydra ends on a config it cannot compose."""
    from hydra.errors import InstantiationException

    from realityavatar.config import ConfigError
    from realityavatar.data.records import SceneFormatError

    return ConfigError, SceneFormatError, FileNotFoundError, InstantiationException


def main() -> None:
    try:
        _hydra_main()
    except KeyboardInterrupt:  # outside a training step (set-up, evaluation)
        print("interrupted; the last checkpoint and logs are kept", file=sys.stderr)
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
