"""A run folder belongs to one run: claiming it (refuse / resume / overwrite), reading checkpoints with clear errors,
carrying the training log across a resume. Without Lightning: export, view and animate read run folders through it
(the callback that keeps run state exact across a resume, RunState, is train.py's)."""

from __future__ import annotations

import csv
import os
import pickle
import shutil
from contextlib import contextmanager
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from realityavatar.config import upgrade_run_config

CKPT_NAME = "last.ckpt"
# What a finished or checkpointed run leaves; a folder holding any of the first two belongs to that run.
RUN_MARKERS = (CKPT_NAME, "metrics.json")
RUN_OUTPUTS = (*RUN_MARKERS, "config.yaml", "per_frame.csv", "logs", "images", "videos", "eval", "animations", "export")
LOG_CSV = Path("logs") / "csv" / "metrics.csv"
# Keys a resume may change: the run length (values interpolated from it are compared at the saved length) and its
# time limit (a job's wall time: trainer.max_time counts the time of the runs before), where the run and its data
# live, threads, profiling, compiling, evaluation settings.
RESUMABLE_CHANGES = ("iterations", "trainer.max_time", "trainer.profiler", "compile", "trainer.enable_progress_bar",
                     "trainer.default_root_dir", "data.root", "ckpt_path", "resume", "overwrite", "out_dir",
                     "_overrides", "_choices", "threads", "test_after_fit", "eval.", "metrics.")


def read_checkpoint(path: str | Path) -> dict:
    """torch.load a Lightning checkpoint as data only (tensors and plain types); a missing, truncated or foreign file,
    or one that holds anything else, raises an error naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    try:
        # Run folders are shared: unpickling an arbitrary object runs code its author chose, so only data is read.
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if "Weights only load failed" not in str(e):
            raise ValueError(f"checkpoint {path} is truncated or corrupt and cannot be read ({e})") from e
        found = next((ln.split("GLOBAL", 1)[1].split()[0] for ln in str(e).splitlines() if "GLOBAL" in ln), "an object")
        raise ValueError(
            f"checkpoint {path} refused: it holds {found}, which is neither a tensor nor a plain type, and loading it "
            "would run code the file names. realityavatar-train writes only tensors and plain types, so this file "
            "was written or changed by something else; use a checkpoint you trained or trust"
        ) from None
    except Exception as e:
        raise ValueError(
            f"checkpoint {path} is truncated or corrupt and cannot be read ({type(e).__name__}: {str(e).splitlines()[0]}); "
            "an interrupted copy or a full disk does this: use an intact copy, or start the run again"
        ) from e
    if not isinstance(state, dict) or "state_dict" not in state:
        raise ValueError(f"checkpoint {path}: not a Lightning checkpoint (no 'state_dict')")
    return state


def _flat(d, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def config_changes(saved: DictConfig | dict, current: DictConfig) -> list[str]:
    """Settings that differ between a run's config.yaml and the resuming config, beyond RESUMABLE_CHANGES."""
    a = _flat(OmegaConf.to_container(saved, resolve=True) if isinstance(saved, DictConfig) else saved)
    # More steps are allowed, and so is a run folder moved or copied elsewhere; what derives from them (schedules and
    # LR decay, the checkpoint and log folders) is compared as saved.
    current = current.copy()
    for key in ("iterations", "out_dir"):
        if key in a:
            current[key] = a[key]
    b = _flat(OmegaConf.to_container(current, resolve=True))
    keys = sorted(set(a) | set(b))
    return [f"{k}: {a.get(k, '<absent>')!r} -> {b.get(k, '<absent>')!r}" for k in keys
            if a.get(k) != b.get(k) and not any(k == p or (p.endswith(".") and k.startswith(p)) for p in RESUMABLE_CHANGES)]


def claim_run_dir(out_dir: Path, cfg: DictConfig) -> Path | None:
    """Decide what this run does with `out_dir` before anything is written; returns the checkpoint to resume from.

    - a folder without a run (no last.ckpt, no metrics.json): a new run (or `ckpt_path` continues another folder's run);
    - `resume=true`: continue the run in this folder from its last.ckpt, with the same settings (RESUMABLE_CHANGES aside);
    - `overwrite=true`: replace the run in this folder (its outputs are removed once the new run is valid);
    - otherwise a folder holding a run refuses, naming both ways out.
    """
    resume, overwrite = bool(cfg.get("resume", False)), bool(cfg.get("overwrite", False))
    ckpt_path = cfg.get("ckpt_path")
    held = [m for m in RUN_MARKERS if (out_dir / m).exists()]
    if resume and overwrite:
        raise ValueError("resume=true and overwrite=true contradict each other: choose one")
    if resume:
        own = out_dir / CKPT_NAME
        if ckpt_path and Path(ckpt_path).resolve() != own.resolve():
            raise ValueError(f"resume=true continues {own}; ckpt_path={ckpt_path} names another checkpoint "
                             "(use one of them)")
        if not own.is_file():
            raise FileNotFoundError(f"resume=true: {own} not found, so there is no run to continue in {out_dir} "
                                    "(a run writes last.ckpt every quarter of its iterations)")
        saved = out_dir / "config.yaml"
        if saved.is_file():
            changes = config_changes(upgrade_run_config(OmegaConf.load(saved)), cfg)
            if changes:
                restore_hydra_record(out_dir)
                raise ValueError(f"resume=true: the settings differ from the run in {out_dir} ({'; '.join(changes)}); "
                                 "resume with the same settings, or start a new run (overwrite=true or another "
                                 "hydra.run.dir) with ckpt_path= to start from its checkpoint")
        return own
    if held and not overwrite:
        same = ckpt_path and Path(ckpt_path).resolve() == (out_dir / CKPT_NAME).resolve()
        hint = "pass resume=true to continue it" + (" (instead of ckpt_path=)" if same else "")
        restore_hydra_record(out_dir)
        raise FileExistsError(
            f"{out_dir} already holds a run ({', '.join(held)}): {hint}, overwrite=true to replace it, or choose "
            "another folder (hydra.run.dir=...)"
        )
    return Path(ckpt_path) if ckpt_path else None


HYDRA_COPY = ".hydra-run"  # the owning run's copy of hydra's .hydra/, which hydra rewrites before a run starts


def keep_hydra_record(out_dir: Path) -> None:
    """Copy .hydra/ (written by hydra for this run) to .hydra-run/ once the run owns the folder."""
    src = out_dir / ".hydra"
    if src.is_dir():
        shutil.rmtree(out_dir / HYDRA_COPY, ignore_errors=True)
        shutil.copytree(src, out_dir / HYDRA_COPY)


def restore_hydra_record(out_dir: Path) -> None:
    """Undo hydra's rewrite of .hydra/ by a run that was refused, so the folder's record stays the owner's."""
    src = out_dir / HYDRA_COPY
    if src.is_dir():
        shutil.rmtree(out_dir / ".hydra", ignore_errors=True)
        shutil.copytree(src, out_dir / ".hydra")


def clear_run_outputs(out_dir: Path) -> list[str]:
    """Remove the outputs of the run this folder held (overwrite=true); hydra's .hydra/ stays."""
    removed = []
    for name in RUN_OUTPUTS:
        p = out_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
        else:
            continue
        removed.append(name)
    return removed


@contextmanager
def run_lock(out_dir: Path):
    """One live process per run folder: a second concurrent run into the folder refuses (a stale lock is taken over)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    lock = out_dir / ".run.lock"
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and pid_alive(pid):
                raise FileExistsError(f"{out_dir} is in use by another run (process {pid}); wait for it or choose "
                                      "another folder (hydra.run.dir=...)") from None
            lock.unlink(missing_ok=True)  # left by a run that was killed
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        break
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def previous_log_rows(ckpt: Path | None, step: int) -> list[dict]:
    """Training-log rows the resumed checkpoint already covers (steps < its global step), from the run folder that
    wrote it; rows after the checkpoint were lost with the interrupted process and are logged again."""
    if ckpt is None:
        return []
    path = Path(ckpt).parent / LOG_CSV
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return [r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) < step]


def seed_csv_log(logger, rows: list[dict]) -> None:
    """Start a CSVLogger's metrics.csv with `rows` so the resumed run appends to the earlier log (Lightning's writer
    deletes an existing metrics.csv when it starts)."""
    exp = logger.experiment  # creating the writer removes the old file
    if not rows:
        return
    keys = sorted({k for r in rows for k in r})
    Path(exp.metrics_file_path).parent.mkdir(parents=True, exist_ok=True)
    with open(exp.metrics_file_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    exp.metrics_keys = keys
