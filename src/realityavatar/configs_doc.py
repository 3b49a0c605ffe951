"""docs/configs.md from conf/: every group, option and key with its default, its yaml comment and its measured effect.

`python -m realityavatar.configs_doc` writes the file; `--check` exits 1 when the committed file is stale.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from realityavatar.config import CONFIG_DIR

OUT = CONFIG_DIR.parent / "docs" / "configs.md"
RESEARCH = "research/"  # relative to docs/
_SWEEP = "sweep preset, 3 seeds"
_DYN = f"{_SWEEP}, `f7cf8b9` / `82dd645`; [dynamics sweep]({RESEARCH}2026-11-26-dynamics-sweep-learnt-normals.md)"
_PAPER = f"{_SWEEP}, `a140910`; [results](results.md), ablations/results/paper"
_BUDGET = "256², 3 seeds, `acbcff3`; [results](results.md#the-gaussian-budget)"

# Measured effects, copied from README.md and the docs it links (each with its commit); "group/option" or
# "group/option:key" (a key of that file) or "train:key". Δ NV / NP PSNR against the default unless stated; † within
# the seed spread. An entry whose file or key no longer exists stops the generator.
EFFECTS = {
    "temporal/lstm": f"**kept, measured gain**: +1.30 / +1.58 dB NV / NP over `temporal=none` ({_PAPER})",
    "temporal/none": f"−1.30 / −1.58 dB NV / NP ({_PAPER}); the paper's ablation axis",
    "temporal/gru": f"+0.01 † / +0.07 † dB ({_SWEEP}, `344e7ab`; [more candidates]({RESEARCH}2026-11-26-more-candidates.md))",
    "variant/full": f"the reference row: NV / NP 31.56 ± 0.15 / 31.01 ± 0.13 dB ({_PAPER})",
    "variant/no_lstm": f"−1.30 / −1.58 dB NV / NP ({_PAPER})",
    "variant/no_zc": f"+0.03 † / −0.08 † dB ({_PAPER})",
    "variant/no_split": f"+0.04 † / +0.03 † dB ({_PAPER})",
    "encoder/no_zc": f"+0.03 † / −0.08 † dB ({_PAPER}); the paper's ablation axis",
    "encoder/no_split": f"+0.04 † / +0.03 † dB ({_PAPER}); the paper's ablation axis",
    "shading/irradiance": f"**kept, measured gain**: +0.97 / +0.89 dB over `shading=none` ({_DYN})",
    "shading/none": f"−0.97 / −0.89 dB ({_DYN})",
    "shading/irradiance:normals": f"learnt against body: +0.20 / +0.13 dB ({_DYN})",
    "silhouette/chamfer": f"**kept, measured gain**: +0.40 / +0.30 dB over `silhouette=none` ({_DYN})",
    "silhouette/none": f"−0.40 / −0.30 dB ({_DYN})",
    "skinning/grid": f"+0.20 / +0.12 † dB over `skinning=mlp` with its λ3 term (now `loss=learnt_skinning`), 0.02 "
                     f"against 0.17 GEMM units per step at 10k ({_DYN})",
    "skinning/mlp": f"with `loss=learnt_skinning`: −0.20 / −0.12 † dB ({_DYN})",
    "sampler/hard_frames": f"**kept, measured gain**: +0.25 / +0.10 dB over `sampler=uniform` ({_DYN})",
    "sampler/uniform": f"−0.25 / −0.10 dB ({_DYN})",
    "deformer/motion_trend:activation": f"relu against silu: +0.17 † / +0.30 dB ({_SWEEP}, `0cb8667`; "
                                        f"[ReLU decoder]({RESEARCH}2026-11-24-relu-decoder.md))",
    "train:schedule.deform_anneal": f"0 (off): −0.39 / −0.17 † dB ({_DYN})",
    "sheet/skirt": f"**kept, measured gain**: +0.28 / +0.36 dB over `sheet=none` ({_DYN})",
    "sheet/skirt:basis": f"64: +0.45 / +0.33 dB over `sheet=none` ({_DYN})",
    "sheet/skirt_slide": "**kept in `make demo`, measured gain**: +0.62 dB garment PSNR in the held-out spin over "
                         "`sheet=skirt` (box +0.36), other phases and novel pose within the seed spread (demo, 256², 3 seeds, "
                         f"[note]({RESEARCH}2026-11-29-garment-motion-and-flow.md))",
    "sheet/physics": "garment PSNR −0.2 / −0.5 / +0.2 / +0.1 dB at rest / spin / after / settled against "
                     "`sheet=none`, 0.7–1.5 dB below `sheet=skirt_slide`, NV −0.8 dB (demo, 256², 3 seeds, "
                     f"[note]({RESEARCH}2026-12-08-physics-garment.md))",
    "density/default": f"2,000 initial Gaussians: NV / NP 29.63 / 28.87 against 29.43 / 28.59 off, 178 s against 94 s "
                       f"of training ({_BUDGET})",
    "density/off": f"the demo's choice: better at equal training time ({_BUDGET})",
    "render/default:backend": "rasterizer fwd + bwd, 10k Gaussians, 256²: numba 0.013 s (CPU, `281fea6`), "
                              "gsplat 2.0 ms (H200, `e65a774`) ([gpu](gpu.md))",
}
NOT_MEASURED = "not measured"


def _split_comment(line: str) -> tuple[str, str]:
    """'key: value  # why' -> ('key: value', 'why'); a '#' inside quotes is part of the value."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i].rstrip(), line[i + 1:].strip()
    return line.rstrip(), ""


def parse(path: Path) -> tuple[str, list[dict]]:
    """A yaml file's header comment and its keys in order: [{key (dotted), value (as written), comment}].

    Comment lines directly above a key belong to it; comment lines indented past a key's column continue its
    inline comment; block lists (`- item`) are shown as one flow list."""
    header, rows, stack, pending = [], [], [], []
    last = None  # (row, indent) of the last key
    seen_key = False
    for raw in path.read_text().splitlines():
        if not raw.strip():
            pending = []
            continue
        indent = len(raw) - len(raw.lstrip())
        body, comment = _split_comment(raw)
        if not body.strip():  # a comment-only line
            if comment.startswith("@package"):
                continue
            if not seen_key:
                header.append(comment)
            elif last is not None and last[0]["comment"] and indent > last[1]:
                last[0]["comment"] += " " + comment
            else:
                pending.append(comment)
            continue
        seen_key = True
        text = body.strip()
        if text.startswith("- "):  # an item of the last key's block list: (item, its comment, comment lines above)
            row = last[0]
            row["items"].append((text[2:].strip(), comment, " ".join(pending)))
            row["value"] = "[" + ", ".join(i for i, _, _ in row["items"]) + "]"
            pending = []
            continue
        if text in ("{}", "null", "~"):  # an empty file body: no keys
            continue
        m = re.match(r"([^:]+?):(?:\s+(.*))?$", text)
        if m is None:
            raise ValueError(f"{path}: cannot read the line {raw!r} (expected `key: value`)")
        key, value = m.group(1).strip(), (m.group(2) or "").strip()
        while stack and stack[-1][1] >= indent:
            stack.pop()
        full = ".".join([s[0] for s in stack] + [key])
        row = {"key": full, "value": value, "comment": " ".join(pending + ([comment] if comment else [])),
               "items": []}
        pending = []
        rows.append(row)
        last = (row, indent)
        if not value:
            stack.append((key, indent))
    return " ".join(header), rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("<", "&lt;").replace("\n", " ")


def _value(v: str) -> str:
    return f"`{_cell(v)}`" if v else ""


def _defaults() -> dict[str, str]:
    _, rows = parse(CONFIG_DIR / "train.yaml")
    out = {}
    for row in rows:
        if row["key"] == "defaults":
            for item, comment, above in row["items"]:
                if ":" in item:
                    g, o = (s.strip() for s in item.split(":", 1))
                    out[g] = (o.strip("'\""), comment, above)
    return out


def _groups() -> dict[str, list[Path]]:
    groups: dict[str, list[Path]] = {}
    for p in sorted(CONFIG_DIR.rglob("*.yaml")):
        if p.parent != CONFIG_DIR:
            groups.setdefault(p.parent.relative_to(CONFIG_DIR).as_posix(), []).append(p)
    return groups


def _check_effects(groups: dict[str, list[Path]]) -> None:
    known = {f"{g}/{p.stem}": p for g, ps in groups.items() for p in ps}
    for name in EFFECTS:
        target, _, key = name.partition(":")
        path = CONFIG_DIR / "train.yaml" if target == "train" else known.get(target)
        if path is None or (key and key not in {r["key"] for r in parse(path)[1]}):
            raise ValueError(f"realityavatar/configs_doc.py: EFFECTS entry {name!r} names a config option or key "
                             "that conf/ no longer has; remove or update the entry")


def _key_table(rows: list[dict], effect_of) -> list[str]:
    rows = [r for r in rows if r["key"] != "defaults" and (r["value"] or r["comment"])]
    if not rows:
        return []
    effects = {r["key"]: effect_of(r["key"]) for r in rows}
    with_effect = any(effects.values())
    head = ["| key | default | comment |" + (" measured effect |" if with_effect else ""),
            "|---|---|---|" + ("---|" if with_effect else "")]
    body = [f"| `{r['key']}` | {_value(r['value'])} | {_cell(r['comment'])} |"
            + (f" {_cell(effects[r['key']] or '')} |" if with_effect else "") for r in rows]
    return head + body


def render() -> str:
    groups = _groups()
    _check_effects(groups)
    defaults = {g: o for g, (o, _, _) in _defaults().items()}
    lines = [
        "# Configuration reference",
        "",
        ("<!-- generated by `python -m realityavatar.configs_doc` from conf/; do not edit by hand "
         "(tests/test_configs_doc.py fails when this file is stale) -->"),
        "",
        ("Every config group in `conf/`, each option file and each key with its default and the comment beside it in "
         "the yaml. Pick an option with `<group>=<option>` and set a key with `<group>.<key>=<value>` "
         "(`+<group>=<option>` for `variant`, `ablation`, `experiment`, `preset`). **Bold**: the option "
         "`conf/train.yaml` picks. Measured effects are Δ PSNR on novel view / novel pose (NV / NP) against the "
         "default, copied with their commit from the README and the docs it links (the sweep preset: the demo's "
         "skirt-spin scene at 128², 1,000 steps); † within the seed spread; \"not measured\" where no measurement is "
         "recorded. Options removed as no gain: [research/removed-options.md](research/removed-options.md)."),
        "",
        "## Options at a glance",
        "",
        "| group | option | what it is | measured effect |",
        "|---|---|---|---|",
    ]
    for group, paths in groups.items():
        for p in paths:
            header, _ = parse(p)
            name = f"**{p.stem}**" if defaults.get(group) == p.stem else p.stem
            lines.append(f"| `{group}` | {name} | {_cell(_first_sentence(header))} | "
                         f"{_cell(EFFECTS.get(f'{group}/{p.stem}', NOT_MEASURED))} |")
    lines += ["", "## Primary configs", ""]
    for p in sorted(CONFIG_DIR.glob("*.yaml")):
        header, rows = parse(p)
        lines += [f"### `conf/{p.name}`", "", _cell(header), ""] if header else [f"### `conf/{p.name}`", ""]
        if p.stem == "train":
            lines += ["Its defaults list, the option each group starts from:", "", "| group | option | comment |",
                      "|---|---|---|"]
            for g, (o, c, above) in _defaults().items():
                lines += ([f"| *{_cell(above)}* | | |"] if above else []) + [f"| `{g}` | {o} | {_cell(c)} |"]
            lines += [""]
        lines += _key_table(rows, lambda k, s=p.stem: EFFECTS.get(f"{s}:{k}")) + [""]
    for group, paths in groups.items():
        lines += [f"## `{group}`", ""]
        for p in paths:
            header, rows = parse(p)
            default = " (default)" if defaults.get(group) == p.stem else ""
            lines += [f"### `{group}={p.stem}`{default}", "", f"`conf/{group}/{p.name}`. {_cell(header)}".rstrip(), ""]
            inherits = next((r["value"] for r in rows if r["key"] == "defaults"), None)
            if inherits:
                lines += [f"Defaults list: {_value(inherits)}.", ""]
            effect = EFFECTS.get(f"{group}/{p.stem}")
            if effect:
                lines += [f"Measured effect: {effect}.", ""]
            table = _key_table(rows, lambda k, g=group, s=p.stem: EFFECTS.get(f"{g}/{s}:{k}"))
            lines += table + ([""] if table else [])
    return "\n".join(lines).rstrip() + "\n"


def _first_sentence(text: str, limit: int = 160) -> str:
    m = re.match(r"(.+?\.)(\s|$)", text)
    out = m.group(1) if m else text
    return out if len(out) <= limit else out[:limit].rsplit(" ", 1)[0] + " …"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when docs/configs.md differs from what conf/ gives")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    text = render()
    if a.check:
        if not a.out.is_file() or a.out.read_text() != text:
            print(f"{a.out} is stale: run `python -m realityavatar.configs_doc`", file=sys.stderr)
            return 1
        print(f"{a.out} is up to date")
        return 0
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
