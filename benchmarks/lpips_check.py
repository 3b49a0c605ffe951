"""Our pure-torch LPIPS (metrics.LPIPS) against the lpips package's, on the same image pairs.

python benchmarks/lpips_check.py [--net vgg] [--device cuda] [--dtype float32] [--sizes 64 256]
                                 [--out benchmarks/results/lpips_check.json]
Needs `lpips` and a torchvision that matches torch (a GPU install: pip install lpips torchvision); lpips.LPIPS puts
torchvision's backbone into torch's hub cache, and ours loads that file and the package's own lin file, so both use
the same weights. Prints (and with --out writes) JSON: each pair's two values and their difference. Exits 2 when
lpips does not import.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from realityavatar.metrics import LPIPS, TORCHVISION_NAMES, PackageLPIPS, hub_checkpoint


def image_pairs(sizes=(64, 256), seed: int = 0) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    """(name, a, b) with a, b [H,W,3] in [0,1]: smooth random images and usual distortions, a thin mask-box crop."""
    g = torch.Generator().manual_seed(seed)

    def smooth(size: int) -> torch.Tensor:
        low = torch.rand(1, 3, size // 8, size // 8, generator=g)
        return F.interpolate(low, size=(size, size), mode="bicubic", align_corners=False).clamp(0, 1)[0].permute(1, 2, 0)

    pairs, thin = [], None
    for size in sizes:
        a = smooth(size)
        noise = (a + 0.05 * torch.randn(a.shape, generator=g)).clamp(0, 1)
        blur = F.avg_pool2d(a.permute(2, 0, 1)[None], 5, 1, 2, count_include_pad=False)[0].permute(1, 2, 0)
        pairs += [(f"{size}/same", a, a), (f"{size}/noise", a, noise), (f"{size}/blur", a, blur),
                  (f"{size}/shift2", a, torch.roll(a, 2, dims=1)), (f"{size}/brighter", a, (a + 0.1).clamp(0, 1)),
                  (f"{size}/other", a, smooth(size))]
        thin = ("thin_box_12x40", a[:12, :40], noise[:12, :40])  # edge-padded to 16 rows by both
    return pairs + [thin]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--net", default="vgg", choices=("vgg",))
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 256], help="square image sizes (multiples of 8)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    try:
        import lpips  # imports torchvision
    except Exception as e:  # noqa: BLE001 (not installed, or a torchvision built for another torch)
        print(f"lpips_check: the lpips package does not import here ({type(e).__name__}: {e}); run it where lpips and "
              "a matching torchvision are installed (pip install lpips torchvision)", file=sys.stderr)
        return 2
    dtype, device = getattr(torch, args.dtype), torch.device(args.device)
    theirs = PackageLPIPS(lpips.LPIPS(net=args.net, verbose=False), args.net).to(device, dtype)
    lin = os.path.join(os.path.dirname(lpips.__file__), "weights", "v0.1", f"{args.net}.pth")
    backbone = hub_checkpoint(TORCHVISION_NAMES[args.net])
    if backbone is None:
        print(f"lpips_check: torchvision's {TORCHVISION_NAMES[args.net]} is not in torch's hub cache "
              f"({torch.hub.get_dir()}/checkpoints) after lpips.LPIPS loaded it", file=sys.stderr)
        return 2
    ours = LPIPS(args.net, backbone, lin).to(device, dtype)
    rows = []
    with torch.no_grad():
        for name, a, b in image_pairs(args.sizes):
            a, b = a.to(device), b.to(device)
            o, t = float(ours(a, b)), float(theirs(a, b))
            rows.append({"pair": name, "size": list(a.shape[:2]), "ours": o, "lpips_package": t, "abs_diff": abs(o - t)})
    def version(name: str) -> str | None:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return getattr(sys.modules.get(name), "__version__", None)

    res = {
        "net": args.net, "device": str(device), "dtype": args.dtype, "torch": torch.__version__,
        "torchvision": version("torchvision"), "lpips": version("lpips"),
        "weights": {"lin": lin, "backbone": backbone},
        "max_abs_diff": max(r["abs_diff"] for r in rows),
        "max_rel_diff": max(r["abs_diff"] / max(abs(r["lpips_package"]), 1e-12) for r in rows if r["lpips_package"]),
        "pairs": rows,
    }
    text = json.dumps(res, indent=2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
