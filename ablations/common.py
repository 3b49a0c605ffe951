"""Shared reading code for the sweep collectors: find a multirun's metrics.json files, label runs by their
swept axes, and average over seeds per scene and then over scenes (docs/CONTRACTS.md "Runs")."""

from __future__ import annotations

import json
import math
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

SPLITS = ("novel_view", "novel_pose")
METRICS = ("psnr", "ssim", "lpips", "psnr_masked", "ssim_masked", "lpips_masked")
# Keys every run file must carry; the rest (render_fps, metric keys) may be absent or null.
REQUIRED = ("config", "overrides", "seed", "commit", "train_seconds", "num_gaussians", "num_parameters")
RUN_NUMBERS = ("train_seconds", "iterations", "num_gaussians", "num_parameters", "render_fps")
# Override keys that never define a table row: the seed is averaged over, `data` is the scene axis.
NOT_AXES = ("seed", "data")
# Human names of the `variant` options (paper Table 3 rows); LaTeX spelling second.
VARIANT_NAMES = {
    "full": ("Full model", "Full model"),
    "no_zc": ("w/o latent code Z_c", r"w/o latent code $\mathcal{Z}_c$"),
    "no_lstm": ("w/o LSTM", "w/o LSTM"),
    "no_split": ("w/o part segmentation", "w/o part segmentation"),
}


def metric_key(split: str, name: str) -> str:
    return f"test/{split}/{name}"


def _natural_key(path: Path) -> list:
    # job folders are 0, 1, ..., 10: sort numerically so rows keep the sweep's order
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(path))]


def _job_dir(metrics_file: Path) -> Path:
    """The hydra job folder a metrics.json belongs to (the nearest folder with .hydra/), else its folder."""
    for d in [metrics_file.parent, *metrics_file.parent.parents][:3]:
        if (d / ".hydra").is_dir():
            return d
    return metrics_file.parent


def find_metrics_files(root: Path, prefer: str = "eval") -> list[Path]:
    """One metrics.json per job under `root`. A job re-evaluated with `realityavatar-evaluate` has a second
    file in <job>/eval/; `prefer="eval"` takes that newer one (e.g. with LPIPS added), `"train"` the original."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"multirun folder {root} does not exist")
    by_job: dict[Path, list[Path]] = {}
    for f in sorted(root.rglob("metrics.json"), key=_natural_key):
        by_job.setdefault(_job_dir(f), []).append(f)
    chosen = []
    for job, files in by_job.items():
        evals = [f for f in files if f.parent.name == "eval"]
        trains = [f for f in files if f.parent.name != "eval"]
        pick = (evals or trains) if prefer == "eval" else (trains or evals)
        if len(pick) > 1:
            raise ValueError(f"job folder {job} holds several metrics.json files: {', '.join(map(str, pick))}")
        chosen.append(pick[0])
    return chosen


def _expected_jobs(root: Path) -> list[list[str]] | None:
    """The job override lists the sweep in `root` expands to (hydra's basic sweeper over multirun.yaml's sweeper
    params and command-line overrides), or None when multirun.yaml is absent or cannot be expanded."""
    mr = root / "multirun.yaml"
    if not mr.is_file():
        return None
    try:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser

        h = (yaml.safe_load(mr.read_text()) or {}).get("hydra", {}) or {}
        params = [f"{k}={v}" for k, v in ((h.get("sweeper") or {}).get("params") or {}).items()]
        task = list((h.get("overrides") or {}).get("task") or [])
        parsed = OverridesParser.create().parse_overrides(params + task)
        return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]
    except Exception:  # noqa: BLE001 - a sweep we cannot expand: report the job folders only
        return None


def job_problems(root: Path, prefer: str = "eval") -> list[dict]:
    """Jobs of the multirun in `root` without a usable result, each {"job", "overrides", "reason"}: a job folder
    (with .hydra/) without metrics.json (failed or still running), a metrics.json whose evaluation failed or never
    finished, and jobs the sweep expands to that never got a folder (the launcher stopped first)."""
    root = Path(root)
    problems, seen = [], []
    for hyd in sorted(root.rglob(".hydra"), key=_natural_key):
        job = hyd.parent
        if job == root or not (hyd / "overrides.yaml").is_file():
            continue
        overrides = [str(o) for o in (yaml.safe_load((hyd / "overrides.yaml").read_text()) or [])]
        seen.append(overrides)
        files = [job / "eval" / "metrics.json", job / "metrics.json"]
        files = files if prefer == "eval" else files[::-1]
        f = next((f for f in files if f.is_file()), None)
        reason = None
        if f is None:
            reason = "no metrics.json (the job failed, was killed or is still running)"
        else:
            try:
                m = json.loads(f.read_text())
            except (OSError, json.JSONDecodeError):
                m = {}
            if isinstance(m, dict) and (m.get("evaluation_errors") or m.get("evaluation") in ("pending", "failed")):
                errs = m.get("evaluation_errors") or {}
                reason = "evaluation " + ("did not finish" if m.get("evaluation") == "pending" and not errs else
                                          "failed: " + "; ".join(f"{k}: {v}" for k, v in errs.items()))
        if reason:
            problems.append({"job": str(job), "overrides": " ".join(overrides), "reason": reason})
    expected = _expected_jobs(root)
    if expected is not None:
        have = [sorted(o) for o in seen]
        if all(sorted(o) in [sorted(e) for e in expected] for o in seen):  # a sweep that matches its folders
            for i, job in enumerate(expected):
                if sorted(job) not in have:
                    problems.append({"job": f"{root}/<job {i}>", "overrides": " ".join(job),
                                     "reason": "never started (no job folder)"})
    return problems


def _sweep_root(path: Path) -> Path | None:
    for d in path.parents:
        if (d / "multirun.yaml").is_file():
            return d
    return None


def parse_override(text: str) -> tuple[str, str]:
    """'+variant=full' -> ('variant', 'full'); '~key' -> ('key', '~')."""
    text = text.strip()
    if text.startswith("~"):
        return text.lstrip("~").split("=", 1)[0], "~"
    if "=" not in text:
        raise ValueError(f"override {text!r} is not of the form key=value")
    key, value = text.split("=", 1)
    return key.lstrip("+"), value


def _float(value, source: str, key: str) -> float:
    if value is None:
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{source}: field {key!r} must be a number or null, got {value!r}") from None


def read_run(path: Path) -> dict:
    """One run as a flat dict: identity (seed, scene, commit, overrides), run numbers and every test metric."""
    path = Path(path)
    try:
        m = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(m, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(m).__name__}")
    missing = [k for k in REQUIRED if k not in m]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing} (schema: docs/CONTRACTS.md 'Runs')")
    if not isinstance(m["config"], dict) or not isinstance(m["overrides"], list):
        raise ValueError(f"{path}: 'config' must be an object of group choices and 'overrides' a list of strings")
    config = {str(k): str(v) for k, v in m["config"].items()}
    scene = m.get("scene") or config.get("data")
    if not scene:
        raise ValueError(f"{path}: neither 'scene' nor config['data'] names the scene")
    job = _job_dir(path)
    row = {
        "file": str(path),
        "job_dir": str(job),
        "sweep_dir": str(_sweep_root(path) or job.parent),
        "seed": int(m["seed"]),
        "scene": str(scene),
        "commit": str(m["commit"]),
        "overrides": list(map(str, m["overrides"])),
        "config": config,
        "lpips_status": str(m.get("lpips", "not computed: no 'lpips' status in metrics.json")),
    }
    for k in RUN_NUMBERS:
        row[k] = _float(m.get(k), str(path), k)
    lpips_ok = row["lpips_status"] == "computed"
    for split in SPLITS:
        for name in METRICS:
            key = metric_key(split, name)
            v = _float(m.get(key), str(path), key)
            # a number next to a "not computed" status is not trusted: LPIPS is n/c, never a number
            row[key] = v if (lpips_ok or not name.startswith("lpips")) else math.nan
    return row


@dataclass
class Runs:
    """All runs of one or more multirun folders, labelled by the swept axes."""

    frame: pd.DataFrame                # one row per run
    axes: list[str]                    # override keys that vary between runs (seed and scene excluded)
    labels: list[str] = field(default_factory=list)   # row labels in sweep order, reference first
    reference: str | None = None
    problems: list[dict] = field(default_factory=list)  # jobs missing or failed (job_problems), not in `frame`

    @property
    def scenes(self) -> list[str]:
        return sorted(self.frame["scene"].unique())

    @property
    def seeds(self) -> list[int]:
        return sorted(self.frame["seed"].unique())


def label_of(values: dict[str, str], axes: list[str]) -> str:
    """Row label: the variant name when `variant` is the only axis, else 'key=value, ...' of the axes."""
    if not axes:
        return values.get("variant") or "all runs"
    if axes == ["variant"]:
        return values["variant"]
    return ", ".join(f"{a}={values.get(a, '-')}" for a in axes)


def load_runs(dirs: list[str | Path] | str | Path, prefer: str = "eval", reference: str | None = None) -> Runs:
    """Read every run under `dirs` and label it. The reference row is `reference` if given, else the `full`
    variant when present, else the first row in sweep order."""
    dirs = [dirs] if isinstance(dirs, (str, Path)) else list(dirs)
    problems = [p for d in dirs for p in job_problems(Path(d), prefer)]
    failed = {p["job"] for p in problems}
    rows = [read_run(f) for d in dirs for f in find_metrics_files(Path(d), prefer) if str(_job_dir(f)) not in failed]
    if not rows:
        why = f" ({len(problems)} job(s) missing or failed: {problems[0]['reason']})" if problems else ""
        raise FileNotFoundError(f"no usable metrics.json under {', '.join(map(str, dirs))}{why}")
    parsed = [dict(parse_override(o) for o in r["overrides"] if not o.lstrip("+~").startswith("hydra")) for r in rows]
    keys: list[str] = []
    for p in parsed:
        keys += [k for k in p if k not in keys and k not in NOT_AXES]
    axes = [k for k in keys if len({p.get(k) for p in parsed}) > 1]
    for r, p in zip(rows, parsed):
        r["axes"] = {a: p.get(a, "-") for a in axes}
        r["variant"] = p.get("variant") or r["config"].get("variant")
        r["label"] = label_of({**p, "variant": r["variant"] or "-"}, axes)
    frame = pd.DataFrame(rows)
    dup = frame[frame.duplicated(["label", "scene", "seed"], keep=False)]
    if len(dup):
        first = dup.iloc[0]
        files = dup[(dup.label == first.label) & (dup.scene == first.scene) & (dup.seed == first.seed)].file
        raise ValueError(
            f"two runs share row {first.label!r}, scene {first.scene!r}, seed {first.seed}: {', '.join(files)} "
            "(collect one sweep at a time, or remove the stale run)"
        )
    labels = list(dict.fromkeys(frame["label"]))
    if reference is None:
        full = frame[frame["variant"] == "full"]["label"].unique()
        reference = full[0] if len(full) == 1 else labels[0]
    if reference not in labels:
        raise ValueError(f"reference row {reference!r} is not one of the rows {labels}")
    labels = [reference] + [lab for lab in labels if lab != reference]
    return Runs(frame=frame, axes=axes, labels=labels, reference=reference, problems=problems)


def _clean(x: float) -> float:
    return x if math.isnan(x) else float(f"{x:.10g}")


def aggregate(runs: Runs, quantities: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Average per scene over seeds, then over scenes.

    Returns (table, per_scene). `table` has one row per label and columns `<q>:mean`, `<q>:std`, `<q>:n_seeds`:
    mean = mean over scenes of the per-scene seed means (every scene weighs the same, as the paper averages
    sequences); std = sample std (ddof=1) over seeds of the scene-averaged value, using the seeds present in every
    scene of that row (NaN with fewer than 2 such seeds). A quantity missing (null/not computed) in any run of a
    row is NaN for the whole row: never an average over a subset. `per_scene` is the long per-scene table.
    """
    f = runs.frame
    table_rows, scene_rows = [], []
    for label in runs.labels:
        g = f[f["label"] == label]
        scenes = sorted(g["scene"].unique())
        row = {"label": label, "n_runs": len(g), "scenes": " ".join(scenes)}
        for q in quantities:
            wide = g.pivot(index="seed", columns="scene", values=q)    # [seeds, scenes]; NaN = missing/null
            present = g.groupby("scene")["seed"].apply(set)
            complete = sorted(set.intersection(*present.tolist()))
            has_null = bool(g[q].isna().any())
            for s in scenes:
                v = g[g["scene"] == s][q]
                scene_rows.append({
                    "label": label, "scene": s, "quantity": q,
                    "mean": math.nan if v.isna().any() else _clean(float(v.mean())),
                    "std": math.nan if (v.isna().any() or len(v) < 2) else _clean(float(v.std(ddof=1))),
                    "n_seeds": len(v),
                })
            if has_null:
                mean = std = math.nan
            else:
                mean = float(np.mean([g[g["scene"] == s][q].mean() for s in scenes]))
                per_seed = wide.loc[complete, scenes].mean(axis=1)
                std = float(per_seed.std(ddof=1)) if len(per_seed) >= 2 else math.nan
            # rounding drops float noise (a std of 1e-15 where all seeds agree) that would decide the spread mark
            row[f"{q}:mean"], row[f"{q}:std"] = _clean(mean), _clean(std)
            row[f"{q}:n_seeds"] = len(complete)
        table_rows.append(row)
    return pd.DataFrame(table_rows), pd.DataFrame(scene_rows)


def within_spread(table: pd.DataFrame, q: str, reference: str) -> pd.Series:
    """True where |mean - reference mean| <= max(std of the row, std of the reference row): the difference from
    the reference is not larger than the seed spread. False for the reference itself and where no std exists
    (one seed) or a mean is missing."""
    ref = table[table["label"] == reference].iloc[0]
    out = []
    for _, r in table.iterrows():
        stds = [s for s in (r[f"{q}:std"], ref[f"{q}:std"]) if not math.isnan(s)]
        if r["label"] == reference or not stds or math.isnan(r[f"{q}:mean"]) or math.isnan(ref[f"{q}:mean"]):
            out.append(False)
        else:
            out.append(abs(r[f"{q}:mean"] - ref[f"{q}:mean"]) <= max(stds) + 1e-12)
    return pd.Series(out, index=table.index)


def provenance(runs: Runs) -> dict:
    """Commits and the commands that produced the runs (from each sweep's multirun.yaml, else each job's
    .hydra/overrides.yaml)."""
    commits = list(dict.fromkeys(runs.frame["commit"]))
    commands = []
    for sweep in dict.fromkeys(runs.frame["sweep_dir"]):
        mr = Path(sweep) / "multirun.yaml"
        if mr.is_file():
            h = (yaml.safe_load(mr.read_text()) or {}).get("hydra", {})
            ov = h.get("overrides", {}) or {}
            args = list(ov.get("task") or []) + [a for a in (ov.get("hydra") or []) if a != "hydra.mode=MULTIRUN"]
            commands.append("realityavatar-train -m " + " ".join(shlex.quote(a) for a in args))
    if not commands:
        for job in dict.fromkeys(runs.frame["job_dir"]):
            ovf = Path(job) / ".hydra" / "overrides.yaml"
            args = yaml.safe_load(ovf.read_text()) if ovf.is_file() else None
            if args is None:
                args = runs.frame[runs.frame["job_dir"] == job].iloc[0]["overrides"]
            commands.append("realityavatar-train " + " ".join(shlex.quote(a) for a in args))
    lpips = sorted({s for s in runs.frame["lpips_status"] if s != "computed"})
    return {"commits": commits, "commands": list(dict.fromkeys(commands)),
            "sweep_dirs": list(dict.fromkeys(runs.frame["sweep_dir"])), "lpips_not_computed": lpips}


def display_label(label: str, latex: bool = False) -> str:
    if label in VARIANT_NAMES:
        return VARIANT_NAMES[label][1 if latex else 0]
    return latex_escape(label) if latex else label


def latex_escape(text: str) -> str:
    repl = {"\\": r"\textbackslash{}", "_": r"\_", "%": r"\%", "&": r"\&", "#": r"\#", "$": r"\$",
            "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
            "<": r"\textless{}", ">": r"\textgreater{}", "|": r"\textbar{}"}
    return "".join(repl.get(c, c) for c in text)
