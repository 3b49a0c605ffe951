"""Speed-vs-accuracy chart from a hydra multirun: training time, render FPS and model size (final Gaussian count)
against novel-view PSNR of the whole image (top row) and of the garment's pixels (bottom row; the mask's box on data
without garment labels), marker area ∝ number of Gaussians, error bars = seed std, as PNG plus the CSV behind it.

    python -m realityavatar.analysis.pareto outputs/sweeps/speed/<timestamp> [more multirun dirs] \
        [--out ablations/results/speed]

With a `gaussians.num_points` axis (the `budget` sweep) it also picks the model a scene needs: the row with the
fewest final Gaussians whose novel-view PSNR is within --tolerance (0.2 dB) of the best row's, by the whole image and
by the garment, written to choice.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from realityavatar.analysis.collect import aggregate, display_label, load_runs, metric_key, provenance

PSNR = metric_key("novel_view", "psnr")
QUANTITIES = {"train_seconds": "train_seconds", "render_fps": "render_fps", PSNR: "novel_view_psnr",
              metric_key("novel_pose", "psnr"): "novel_pose_psnr", "num_gaussians": "num_gaussians",
              metric_key("novel_view", "psnr_garment"): "novel_view_psnr_garment",
              metric_key("novel_view", "detail_garment"): "novel_view_detail_garment",
              metric_key("novel_view", "psnr_masked"): "novel_view_psnr_masked"}
# the accuracies the charts and the budget choice read: (CSV column, axis label, frontier suffix)
WHOLE = ("novel_view_psnr_mean", "novel-view PSNR (dB) ↑", "")
GARMENT = ("novel_view_psnr_garment_mean", "novel-view garment PSNR (dB) ↑", "_garment")
BOX = ("novel_view_psnr_masked_mean", "novel-view PSNR in the mask's box (dB) ↑", "_box")
MAX_MARKER_AREA = 600.0   # points^2 of the row with the most Gaussians


def frontier(cost: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Rows no other row beats: none has cost <= and accuracy >= with one of them strict. NaN is never on it."""
    ok = ~(np.isnan(cost) | np.isnan(acc))
    on = np.zeros(len(cost), dtype=bool)
    for i in np.flatnonzero(ok):
        better = ok & (cost <= cost[i]) & (acc >= acc[i]) & ((cost < cost[i]) | (acc > acc[i]))
        on[i] = not better.any()
    return on


def _short(name: str) -> str:
    """Chart label: the budget sweep's long axis names shortened (N = gaussians.num_points)."""
    return name.replace("gaussians.num_points=", "N=").replace("density=default", "density on").replace("density=off", "density off")


def pareto_table(runs) -> pd.DataFrame:
    table, _ = aggregate(runs, list(QUANTITIES))
    out = pd.DataFrame({"label": table["label"], "name": [_short(display_label(lab)) for lab in table["label"]],
                        "n_runs": table["n_runs"], "scenes": table["scenes"]})
    for q, short in QUANTITIES.items():
        out[f"{short}_mean"], out[f"{short}_std"] = table[f"{q}:mean"], table[f"{q}:std"]
    for axis in runs.axes:  # the sweep's settings per row (e.g. gaussians.num_points, density)
        first = runs.frame.drop_duplicates("label").set_index("label")["axes"]
        out[axis] = [first[lab].get(axis, "-") for lab in table["label"]]
    for col, _, suffix in (WHOLE, GARMENT, BOX):
        acc = out[col].to_numpy(float)
        out[f"pareto_time{suffix}"] = frontier(out["train_seconds_mean"].to_numpy(float), acc)
        out[f"pareto_fps{suffix}"] = frontier(-out["render_fps_mean"].to_numpy(float), acc)   # more FPS = cheaper
        out[f"pareto_size{suffix}"] = frontier(out["num_gaussians_mean"].to_numpy(float), acc)
    return out


def local_accuracy(df: pd.DataFrame) -> tuple[str, str, str]:
    """The garment's accuracy where the runs scored it (synthetic scenes), else the mask box's."""
    return GARMENT if np.isfinite(df[GARMENT[0]].to_numpy(float)).any() else BOX


def smallest_within(df: pd.DataFrame, tolerance: float = 0.2, accuracy: str = WHOLE[0]) -> dict:
    """The row with the fewest final Gaussians whose mean `accuracy` (a PSNR column: the whole image's by default)
    is within `tolerance` dB of the best row's."""
    acc = df[accuracy].to_numpy(float)
    if not np.isfinite(acc).any():
        raise ValueError(f"no row has a {accuracy}: nothing to choose from")
    best = int(np.nanargmax(acc))
    ok = df[np.isfinite(acc) & (acc >= acc[best] - tolerance)]
    pick = ok.sort_values(["num_gaussians_mean", accuracy], ascending=[True, False]).iloc[0]
    keep = [c for c in df.columns if not c.startswith("pareto_")]
    row = {k: (v.item() if hasattr(v, "item") else v) for k, v in pick[keep].items()}
    best_row = {k: (v.item() if hasattr(v, "item") else v) for k, v in df.iloc[best][keep].items()}
    return {"tolerance_db": tolerance, "choice": row, "best": best_row,
            "rule": f"fewest final Gaussians with mean {accuracy} >= best - tolerance"}


def _panel(ax, df: pd.DataFrame, x: str, xlabel: str, front_col: str, higher_x_better: bool,
           accuracy: tuple[str, str, str] = WHOLE) -> None:
    y, ylabel, suffix = accuracy
    front_col += suffix
    g = df["num_gaussians_mean"].to_numpy(float)
    area = MAX_MARKER_AREA * g / np.nanmax(g) if np.isfinite(g).any() and np.nanmax(g) > 0 else np.full(len(df), 60.0)
    xs, ys = df[f"{x}_mean"].to_numpy(float), df[y].to_numpy(float)
    xe = np.nan_to_num(df[f"{x}_std"].to_numpy(float))
    ye = np.nan_to_num(df[y.removesuffix("_mean") + "_std"].to_numpy(float))
    colors = plt.cm.tab10(np.arange(len(df)) % 10)
    ax.errorbar(xs, ys, xerr=xe, yerr=ye, fmt="none", ecolor="0.5", elinewidth=1, capsize=3, zorder=1)
    ax.scatter(xs, ys, s=area, c=colors, alpha=0.8, edgecolors="k", linewidths=0.5, zorder=2)
    for xi, yi, name in zip(xs, ys, df["name"]):
        if np.isfinite(xi) and np.isfinite(yi):
            ax.annotate(name, (xi, yi), xytext=(6, 6), textcoords="offset points", fontsize=8)
    front = df[df[front_col]].sort_values(f"{x}_mean")
    if len(front) > 1:
        ax.plot(front[f"{x}_mean"], front[y], "--", color="0.3", lw=1, zorder=0,
                label="Pareto front")
        ax.legend(loc="lower right" if not higher_x_better else "lower left", fontsize=8)
    finite = xs[np.isfinite(xs) & (xs > 0)]
    if len(finite) > 1 and finite.max() / finite.min() > 20:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)


def pareto(dirs, out: str | Path | None = None, prefer: str = "eval", name: str | None = None) -> pd.DataFrame:
    """Write pareto.png and pareto.csv to `out` (default ablations/results/<sweep name>); return the CSV table."""
    dirs = [Path(dirs)] if isinstance(dirs, (str, Path)) else [Path(d) for d in dirs]
    runs = load_runs(dirs, prefer=prefer)
    if name is None:
        names = {c.get("ablation") for c in runs.frame["config"]}
        name = str(names.pop()) if len(names) == 1 and None not in names else dirs[0].resolve().name
    out = Path(out) if out is not None else Path("ablations/results") / name
    out.mkdir(parents=True, exist_ok=True)
    df = pareto_table(runs)
    df.to_csv(out / "pareto.csv", index=False)

    prov = provenance(runs)
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.2), layout="constrained")
    fig.get_layout_engine().set(rect=(0, 0.03, 1, 0.97))   # room for the provenance line at the bottom
    for row, accuracy in zip(axes, (WHOLE, local_accuracy(df))):
        _panel(row[0], df, "train_seconds", "training time (s) ↓", "pareto_time", False, accuracy)
        _panel(row[1], df, "render_fps", "render speed (FPS) ↑", "pareto_fps", True, accuracy)
        _panel(row[2], df, "num_gaussians", "Gaussians at the end of training ↓", "pareto_size", False, accuracy)
    seeds = sorted({int(s) for s in runs.frame["seed"]})
    fig.suptitle(f"{name}: speed vs accuracy — mean ± std over seeds {seeds}, averaged over "
                 f"{', '.join(runs.scenes)}; marker area ∝ Gaussians", fontsize=10)
    fig.text(0.01, 0.005, f"commit(s) {', '.join(prov['commits'])} · " + " ; ".join(prov["commands"]),
             fontsize=6, color="0.4", va="bottom")
    fig.savefig(out / "pareto.png", dpi=150)
    plt.close(fig)
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m realityavatar.analysis.pareto", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", type=Path, help="multirun folder(s)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default ablations/results/<sweep name>)")
    p.add_argument("--prefer", choices=("eval", "train"), default="eval",
                   help="per job, take <job>/eval/metrics.json from a re-evaluation (default) or the training one")
    p.add_argument("--name", default=None, help="chart name (default: the ablation config name)")
    p.add_argument("--tolerance", type=float, default=0.2,
                   help="dB below the best row that still counts as as good (the smallest such row is chosen)")
    a = p.parse_args(argv)
    df = pareto(a.dirs, a.out, a.prefer, a.name)
    print(df.to_string(index=False))
    if "gaussians.num_points" in df.columns:
        choices = {}
        for name, (col, _, _) in (("whole_image", WHOLE), ("local", local_accuracy(df))):
            choice = choices[name] = smallest_within(df, a.tolerance, col)
            c, b = choice["choice"], choice["best"]
            print(f"\nchoice by {col} (fewest Gaussians within {a.tolerance} dB of the best): {c['label']} -> "
                  f"{c['num_gaussians_mean']:.0f} Gaussians, {c[col]:.2f} dB "
                  f"(best {b['label']}: {b[col]:.2f} dB, {b['num_gaussians_mean']:.0f} Gaussians)")
        out = Path(a.out) if a.out is not None else Path("ablations/results") / (a.name or _sweep_name(a.dirs))
        (out / "choice.json").write_text(json.dumps(choices, indent=1))
    return 0


def _sweep_name(dirs) -> str:
    runs = load_runs([Path(d) for d in dirs])
    names = {c.get("ablation") for c in runs.frame["config"]}
    return str(names.pop()) if len(names) == 1 and None not in names else Path(dirs[0]).resolve().name


if __name__ == "__main__":
    raise SystemExit(main())
