"""Shrink PNG charts and grids in place for committing under ablations/: at most --width pixels wide (what a page shows)
and quantised to a palette of --colors (64 keeps a matplotlib chart readable; renders want 256).
  .venv/bin/python scripts/shrink_png.py --colors 64 ablations/results/paper/probe/probe.png
  .venv/bin/python scripts/shrink_png.py --colors 256 ablations/results/oracle/*/phases.png"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image


def shrink(path: Path, width: int, colors: int) -> tuple[int, int]:
    """Rewrite `path`; return its size in bytes before and after."""
    before = path.stat().st_size
    im = Image.open(path).convert("RGBA")
    white = Image.new("RGBA", im.size, (255, 255, 255, 255))
    im = Image.alpha_composite(white, im).convert("RGB")  # a palette without alpha: transparency shown on white
    if im.width > width:
        im = im.resize((width, round(im.height * width / im.width)), Image.LANCZOS)
    method = Image.Quantize.MEDIANCUT if colors <= 64 else Image.Quantize.MAXCOVERAGE
    im.quantize(colors=colors, method=method, dither=Image.Dither.NONE).save(path, "PNG", optimize=True)
    return before, path.stat().st_size


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pngs", nargs="+", type=Path)
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--colors", type=int, default=64)
    args = ap.parse_args(argv)
    for p in args.pngs:
        before, after = shrink(p, args.width, args.colors)
        print(f"{p}: {before / 1024:.0f} -> {after / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
