"""Ablation table from a hydra multirun: mean ± std over seeds, averaged over scenes, as CSV, Markdown and LaTeX.

    python -m realityavatar.analysis.collect outputs/sweeps/paper/<timestamp> [more multirun dirs] \
        [--out ablations/results/paper]

Reading a sweep: find a multirun's metrics.json files, label runs by their swept axes, and average over seeds per
scene and then over scenes (docs/CONTRACTS.md "Runs"); pareto.py reads runs through the same functions.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from realityavatar.data.poses import PHASES

SPLITS = ("novel_view", "novel_pose")
METRICS = ("psnr", "ssim", "lpips", "psnr_masked", "ssim_masked", "lpips_masked")
# The garment's scores (synthetic scenes' labels; evaluate.METRIC_KEYS), reported per motion phase (PHASES).
GARMENT = ("psnr_garment", "ssim_garment", "flip_garment", "detail_garment")
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
        raise ValueError(f"{path}: expected a JSON object, got {type(m).__name__}")  # noqa: TRY004 -- one error type
    missing = [k for k in REQUIRED if k not in m]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing} (schema: docs/CONTRACTS.md 'Runs')")
    if not isinstance(m["config"], dict) or not isinstance(m["overrides"], list):
        raise ValueError(  # noqa: TRY004 -- every bad run file raises ValueError (one type for callers)
            f"{path}: 'config' must be an object of group choices and 'overrides' a list of strings")
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
    lpips_ok = row["lpips_status"].startswith("computed")  # "computed (<where the weights came from>)"
    keys = [metric_key(split, name) for split in SPLITS for name in (*METRICS, *GARMENT)]
    for key in dict.fromkeys(keys + [q for q in EXTRA if q.startswith("test/")]):
        v = _float(m.get(key), str(path), key)
        # a number next to a "not computed" status is not trusted: LPIPS is n/c, never a number
        row[key] = v if (lpips_ok or "/lpips" not in key) else math.nan
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
    lpips = sorted({s for s in runs.frame["lpips_status"] if not s.startswith("computed")})
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


SPLIT_SHORT = {"novel_view": "NV", "novel_pose": "NP"}
MARK = "†"          # difference from the reference row not larger than the seed spread
MARK_TEX = r"^{\dagger}"
SPREAD_RULE = "|Δmean| ≤ max(std of the row, std of the reference row)"


def _column(q, csv, header, tex, group=None, scale=1.0, dec=0, mark=False, lpips=False) -> dict:
    return {"q": q, "csv": csv, "header": header, "tex": tex, "group": group, "scale": scale, "dec": dec,
            "mark": mark, "lpips": lpips}


def _columns() -> list[dict]:
    """The table's columns: quantity key, CSV name, header, scale, decimals, whether the spread mark applies."""
    cols = []
    for split in SPLITS:
        for name, up, dec, scale in (("psnr", True, 2, 1.0), ("ssim", True, 4, 1.0), ("lpips", False, 2, 1000.0)):
            short = f"{split}_{name}" + ("_x1000" if scale != 1.0 else "")
            header = f"{SPLIT_SHORT[split]} {name.upper()}{'↑' if up else '↓'}"
            tex = f"{name.upper()}$\\{'uparrow' if up else 'downarrow'}$"
            cols.append(_column(metric_key(split, name), short, header, tex, split, scale, dec, True, name == "lpips"))
        # the garment where the scene labels it (n/a on real data): PSNR and the detail kept (1: all of it)
        for name, label in (("psnr_garment", "PSNR garm"), ("detail_garment", "detail garm")):
            cols.append(_column(metric_key(split, name), f"{split}_{name}", f"{SPLIT_SHORT[split]} {label}↑",
                                label.replace("garm", "garm.") + "$\\uparrow$", split, 1.0, 2, True))
    cols += [
        _column("train_seconds", "train_seconds", "Train time (s)", "Train (s)", dec=1),
        _column("num_gaussians", "num_gaussians", "Gaussians", "Gaussians"),
        _column("num_parameters", "num_parameters", "Parameters", "Params"),
    ]
    return cols


# Also in the CSV (not in the printed table): box metrics, FLIP, the garment's scores per motion phase, the spread of
# the garment's PSNR over the held-out cameras, render speed.
EXTRA = ([metric_key(s, n) for s in SPLITS for n in ("psnr_masked", "ssim_masked", "lpips_masked", "flip",
                                                        "flip_masked", "detail_masked", *GARMENT)]
         + [metric_key(s, f"{ph}/{n}") for s in SPLITS for ph in PHASES
            for n in ("psnr", "psnr_masked", "detail_masked", *GARMENT, "psnr_garment_camera_std")]
         + ["render_fps"])


def _num(x: float, dec: int) -> str:
    return f"{x:,.0f}" if dec == 0 else f"{x:.{dec}f}"


def _cell(mean: float, std: float, col: dict, latex: bool) -> str:
    if math.isnan(mean):
        return "n/c" if col["lpips"] else "n/a"
    m, s = mean * col["scale"], std * col["scale"]
    show_std = not math.isnan(s) and (col["mark"] or s > 0)   # counts that did not vary need no "± 0"
    if latex:
        body = _num(m, col["dec"]).replace(",", "{,}") + (rf" \pm {_num(s, col['dec'])}" if show_std else "")
        return f"${body}$"
    return _num(m, col["dec"]) + (f" ± {_num(s, col['dec'])}" if show_std else "")


def build_table(runs: Runs) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """(table with means/stds/marks per column, per-scene long table, formatted cells per output format)."""
    cols = _columns()
    quantities = [c["q"] for c in cols] + [q for q in EXTRA if q not in [c["q"] for c in cols]]
    table, per_scene = aggregate(runs, quantities)
    marks = {c["q"]: within_spread(table, c["q"], runs.reference) if c["mark"] else pd.Series(False, index=table.index)
             for c in cols}
    cells = {"md": [], "tex": []}
    for i, r in table.iterrows():
        for fmt in ("md", "tex"):
            row = []
            for c in cols:
                text = _cell(r[f"{c['q']}:mean"], r[f"{c['q']}:std"], c, fmt == "tex")
                if marks[c["q"]][i]:
                    text = text[:-1] + MARK_TEX + "$" if fmt == "tex" else text + " " + MARK
                row.append(text)
            cells[fmt].append(row)
    table = table.assign(**{f"{c['q']}:within_spread": marks[c["q"]] for c in cols})
    return table, per_scene, cells


def _footnotes(runs: Runs, table: pd.DataFrame, cells_md: list[list[str]], prov: dict, latex: bool) -> list[str]:
    seeds = sorted({int(s) for s in runs.frame["seed"]})
    ref = display_label(runs.reference, latex)
    scenes = f"{len(runs.scenes)} scene(s): {', '.join(runs.scenes)}"
    if len(seeds) > 1:
        notes = [
            (f"Mean ± std over seeds ({', '.join(map(str, seeds))}; sample std) per scene, then averaged over {scenes}."
            " LPIPS ×1000."),
            f"{MARK} difference from the reference row ({ref}) within the seed spread: {SPREAD_RULE}.",
        ]
    else:
        notes = [(f"One seed ({seeds[0]}): no seed spread, so no ± and no {MARK} marks; averaged over {scenes}."
                 " LPIPS ×1000.")]
    nc = any(math.isnan(r[f"{metric_key(s, 'lpips')}:mean"]) for _, r in table.iterrows() for s in SPLITS)
    if nc:
        why = "; ".join(prov["lpips_not_computed"]) or "LPIPS missing from metrics.json"
        notes.append(f"n/c: LPIPS not computed ({why}).")
    if any(c == "n/a" for row in cells_md for c in row):
        notes.append("n/a: metric absent from metrics.json.")
    if runs.problems:
        listed = "; ".join(f"{Path(p['job']).name} ({p['overrides']}): {p['reason']}" for p in runs.problems)
        notes.append(f"Missing or failed jobs, not in the table ({len(runs.problems)} of "
                     f"{len(runs.problems) + len(runs.frame)}): {listed}.")
    notes.append(f"Commit(s): {', '.join(prov['commits'])}.")
    notes.append("Command(s): " + "; ".join(prov["commands"]) + ".")
    if latex:
        notes = [latex_escape(n).replace("±", r"$\pm$").replace("×", r"$\times$").replace("Δ", r"$\Delta$").replace("≤", r"$\le$")
                 .replace(latex_escape(MARK), r"$^{\dagger}$").replace(MARK, r"$^{\dagger}$") for n in notes]
        notes = [n.replace(latex_escape(ref), ref) for n in notes]
    return notes


def write_markdown(path: Path, runs: Runs, cells: list[list[str]], notes: list[str], prov: dict) -> None:
    cols = _columns()
    lines = [
        "<!-- generated by python -m realityavatar.analysis.collect from " + ", ".join(prov["sweep_dirs"]) + " -->",
        f"<!-- commit(s): {', '.join(prov['commits'])} -->",
        "<!-- command(s): " + " ; ".join(prov["commands"]) + " -->",
        "",
        "| Variant | " + " | ".join(c["header"] for c in cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]
    for label, row in zip(runs.labels, cells):
        lines.append(f"| {display_label(label)} | " + " | ".join(row) + " |")
    lines += [""] + [f"{n}  " for n in notes]
    path.write_text("\n".join(lines).rstrip() + "\n")


def write_latex(path: Path, runs: Runs, cells: list[list[str]], notes: list[str], prov: dict, name: str) -> None:
    cols = _columns()
    n_q = sum(1 for c in cols if c["group"] == "novel_view")
    lines = [
        "% generated by python -m realityavatar.analysis.collect from " + ", ".join(prov["sweep_dirs"]),
        f"% commit(s): {', '.join(prov['commits'])}",
        "% command(s): " + " ; ".join(prov["commands"]),
        "% needs \\usepackage{booktabs}",
        "\\begin{table}[t]",
        "\\centering",
        f"\\caption{{Ablation ``{latex_escape(name)}'': mean $\\pm$ std over seeds, averaged over scenes.}}",
        f"\\label{{tab:ablation_{latex_escape(name)}}}",
        "\\resizebox{\\linewidth}{!}{%",
        "\\begin{tabular}{@{}l" + "c" * len(cols) + "@{}}",
        "\\toprule",
        f" & \\multicolumn{{{n_q}}}{{c}}{{Novel view}} & \\multicolumn{{{n_q}}}{{c}}{{Novel pose}} & & & \\\\",
        f"\\cmidrule(lr){{2-{1 + n_q}}} \\cmidrule(lr){{{2 + n_q}-{1 + 2 * n_q}}}",
        "Method & " + " & ".join(c["tex"] for c in cols) + " \\\\",
        "\\midrule",
    ]
    for label, row in zip(runs.labels, cells):
        lines.append(f"{display_label(label, latex=True)} & " + " & ".join(row) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}}", "\\par\\smallskip\\footnotesize"]
    lines += [n + " \\\\" for n in notes[:-1]] + [notes[-1]]
    lines.append("\\end{table}")
    path.write_text("\n".join(lines) + "\n")


def write_csv(path: Path, runs: Runs, table: pd.DataFrame) -> pd.DataFrame:
    """One row per table row; LPIPS columns hold "n/c" (never a number) where LPIPS was not computed."""
    out = pd.DataFrame({"label": table["label"], "name": [display_label(lab) for lab in table["label"]],
                        "reference": table["label"] == runs.reference, "n_runs": table["n_runs"],
                        "scenes": table["scenes"]})
    for c in _columns():
        q = c["q"]
        mean, std = table[f"{q}:mean"] * c["scale"], table[f"{q}:std"] * c["scale"]
        if c["lpips"]:
            mean = mean.map(lambda v: "n/c" if math.isnan(v) else v)
            std = std.map(lambda v: "n/c" if math.isnan(v) else v)
        out[f"{c['csv']}_mean"], out[f"{c['csv']}_std"] = mean, std
        out[f"{c['csv']}_n_seeds"] = table[f"{q}:n_seeds"]
        if c["mark"]:
            out[f"{c['csv']}_within_seed_spread"] = table[f"{q}:within_spread"]
    for q in EXTRA:
        short = q.replace("test/", "").replace("/", "_")
        if short.endswith("lpips_masked"):
            out[f"{short}_x1000_mean"] = (table[f"{q}:mean"] * 1000).map(lambda v: "n/c" if math.isnan(v) else v)
            out[f"{short}_x1000_std"] = (table[f"{q}:std"] * 1000).map(lambda v: "n/c" if math.isnan(v) else v)
        else:
            out[f"{short}_mean"], out[f"{short}_std"] = table[f"{q}:mean"], table[f"{q}:std"]
    out.to_csv(path, index=False)
    return out


def default_name(runs: Runs, dirs: list[Path]) -> str:
    names = {r.get("ablation") for r in runs.frame["config"]}
    if len(names) == 1 and None not in names:
        return str(names.pop())
    return Path(dirs[0]).resolve().name


def collect(dirs: list[str | Path] | str | Path, out: str | Path | None = None, reference: str | None = None,
            prefer: str = "eval", name: str | None = None) -> tuple[pd.DataFrame, Path]:
    """Write table.csv, table.md, table.tex, per_scene.csv and runs.csv to `out`; return (CSV table, out)."""
    dirs = [Path(dirs)] if isinstance(dirs, (str, Path)) else [Path(d) for d in dirs]
    runs = load_runs(dirs, prefer=prefer, reference=reference)
    name = name or default_name(runs, dirs)
    out = Path(out) if out is not None else Path("ablations/results") / name
    out.mkdir(parents=True, exist_ok=True)
    table, per_scene, cells = build_table(runs)
    prov = provenance(runs)
    csv = write_csv(out / "table.csv", runs, table)
    per_scene.to_csv(out / "per_scene.csv", index=False)
    keep = ["label", "scene", "seed", "commit", "lpips_status", *RUN_NUMBERS,
            *[c for c in runs.frame.columns if c.startswith("test/")], "file"]
    runs.frame[keep].assign(overrides=runs.frame["overrides"].map(" ".join)).to_csv(out / "runs.csv", index=False)
    write_markdown(out / "table.md", runs, cells["md"], _footnotes(runs, table, cells["md"], prov, False), prov)
    write_latex(out / "table.tex", runs, cells["tex"], _footnotes(runs, table, cells["md"], prov, True), prov, name)
    if runs.problems:
        pd.DataFrame(runs.problems).to_csv(out / "missing.csv", index=False)
    elif (out / "missing.csv").exists():
        (out / "missing.csv").unlink()
    csv.attrs["problems"] = runs.problems
    return csv, out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m realityavatar.analysis.collect", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", type=Path, help="multirun folder(s), e.g. outputs/sweeps/paper/<timestamp>")
    p.add_argument("--out", type=Path, default=None, help="output folder (default ablations/results/<sweep name>)")
    p.add_argument("--reference", default=None, help="row label to compare against (default: variant full, else first)")
    p.add_argument("--prefer", choices=("eval", "train"), default="eval",
                   help="per job, take <job>/eval/metrics.json from a re-evaluation (default) or the training one")
    p.add_argument("--name", default=None, help="table name (default: the ablation config name)")
    p.add_argument("--allow-missing", action="store_true",
                   help="exit 0 even when jobs are missing or failed (they are listed in the footnote either way)")
    a = p.parse_args(argv)
    table, out = collect(a.dirs, a.out, a.reference, a.prefer, a.name)
    print((out / "table.md").read_text())
    print(f"wrote {out}/table.csv, table.md, table.tex, per_scene.csv, runs.csv")
    problems = table.attrs.get("problems", [])
    if problems:
        print(f"collect: {len(problems)} job(s) missing or failed (listed in {out}/missing.csv and the footnote)"
              + ("" if a.allow_missing else "; the table is incomplete: exit 1 (--allow-missing to accept)"),
              file=sys.stderr)
        return 0 if a.allow_missing else 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
