"""The committed results stay small: scripts/shrink_png.py shrinks a chart to its shown width and a palette, and
ablations/ holds at most 2.5 MB (ablations/results/README.md, "Images")."""

from __future__ import annotations

import importlib.util

import numpy as np
from PIL import Image

from tests.helpers import ROOT


def shrink_png():
    spec = importlib.util.spec_from_file_location("shrink_png", ROOT / "scripts" / "shrink_png.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_shrink_png_keeps_the_chart_at_its_shown_width(tmp_path):
    rng = np.random.default_rng(0)
    img = np.full((300, 2400, 4), 255, np.uint8)
    img[100:200, 200:2200, :3] = rng.integers(0, 256, (100, 2000, 3))  # many colours, as antialiased lines give
    img[:20, :20, 3] = 0  # a transparent corner
    path = tmp_path / "chart.png"
    Image.fromarray(img).save(path)
    before, after = shrink_png().shrink(path, width=1200, colors=64)
    out = Image.open(path)
    assert out.size == (1200, 150) and out.mode == "P" and len(out.getcolors()) <= 64
    assert after == path.stat().st_size and after < before / 2
    assert out.convert("RGB").getpixel((2, 2)) == (255, 255, 255)  # transparency shown on white


def test_results_folder_is_at_most_2_5_mb():
    files = [p for p in (ROOT / "ablations").rglob("*") if p.is_file()]
    total = sum(p.stat().st_size for p in files)
    largest = sorted(files, key=lambda p: -p.stat().st_size)[:5]
    assert total <= 2.5e6, (f"ablations/ holds {total / 1e6:.2f} MB: shrink images with scripts/shrink_png.py; the "
                            f"largest: {[f'{p.relative_to(ROOT)} {p.stat().st_size // 1024} KiB' for p in largest]}")
