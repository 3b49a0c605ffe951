"""Ablation table from a hydra multirun: mean ± std over seeds, averaged over scenes, as CSV, Markdown and LaTeX.

    python ablations/collect.py outputs/sweeps/paper/<timestamp> [more multirun dirs] [--out ablations/results/paper]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `ablations` importable from the repository root
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd

from ablations.common import (
    RUN_NUMBERS,
    SPLITS,
    Runs,
    aggregate,
    display_label,
    latex_escape,
    load_runs,
    metric_key,
    provenance,
    within_spread,
)

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
    cols += [
        _column("train_seconds", "train_seconds", "Train time (s)", "Train (s)", dec=1),
        _column("num_gaussians", "num_gaussians", "Gaussians", "Gaussians"),
        _column("num_parameters", "num_parameters", "Parameters", "Params"),
    ]
    return cols


# Also in the CSV (not in the printed table): masked metrics and render speed.
EXTRA = [metric_key(s, n) for s in SPLITS for n in ("psnr_masked", "ssim_masked", "lpips_masked")] + ["render_fps"]


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
        "<!-- generated by ablations/collect.py from " + ", ".join(prov["sweep_dirs"]) + " -->",
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
        "% generated by ablations/collect.py from " + ", ".join(prov["sweep_dirs"]),
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
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
