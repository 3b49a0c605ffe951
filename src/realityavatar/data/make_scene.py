"""`realityavatar-make-scene`: generate synthetic loose-clothing scenes (presets ci / demo / full) with a progress bar."""

from __future__ import annotations

import argparse
import json
import sys
import time

from realityavatar.data.synthetic.presets import PRESETS, SEQUENCES
from realityavatar.data.synthetic.scene import build_scene, default_root, scene_paths


def _value(text: str):
    """Parse an override value as JSON (numbers, lists, dicts), falling back to the plain string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="realityavatar-make-scene", description=__doc__)
    ap.add_argument("--preset", default="demo", choices=sorted(PRESETS), help="size preset (default: demo)")
    ap.add_argument("--sequence", action="append", default=None, choices=sorted(SEQUENCES) + ["all"],
                    help="garment_motion sequence(s); repeat for several, 'all' for every one (default: skirt_spin)")
    ap.add_argument("--root", default=None, help=f"output folder (default: {default_root()})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a parameter, e.g. --set width=192 --set train_frames=80")
    ap.add_argument("--force", action="store_true", help="rebuild even when the cached scene matches")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--release", default=None, metavar="TRAIN,NOVEL",
                    help="also write the scene as I3D-Human is released, under --release-root: every TRAIN-th "
                         "training frame, every NOVEL-th novel-view / novel-pose frame, and each split's dense "
                         "frameid_pose.pkl (e.g. 5,5)")
    ap.add_argument("--release-root", default=None, help="folder of the release (required with --release)")
    ap.add_argument("--no-frameid-pose", action="store_true",
                    help="a release without frameid_pose.pkl (the reader's approximate windows, for comparison)")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    overrides = {}
    for item in args.set:
        if "=" not in item:
            raise SystemExit(f"--set: expected KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip()] = _value(v)
    release = None
    if args.release is not None:
        try:
            release = [int(x) for x in args.release.split(",")]
        except ValueError:
            release = []
        if len(release) != 2 or min(release) < 1:
            raise SystemExit(f"--release: expected TRAIN,NOVEL (two whole numbers >= 1), got {args.release!r}")
        if not args.release_root:
            raise SystemExit("--release needs --release-root (a folder other than the scene's)")
    seqs = args.sequence or [PRESETS[args.preset]["sequence"]]
    if "all" in seqs:
        seqs = sorted(SEQUENCES)
    for seq in seqs:
        t0 = time.perf_counter()
        try:
            prefix = build_scene(args.preset, args.root, args.seed, sequence=seq, overrides=overrides,
                                 force=args.force, progress=not args.quiet)
        except ValueError as e:
            print(f"realityavatar-make-scene: {e}", file=sys.stderr)
            return 2
        meta = json.loads(scene_paths(prefix)["meta"].read_text())
        print(f"{prefix.name}: {prefix.parent} ({time.perf_counter() - t0:.1f} s, hash {meta['params_hash']}, "
              f"train cams {meta['cameras']['train']}, novel-view cams {meta['cameras']['novel_view']})")
        if release is not None:
            from realityavatar.data.i3d import write_release

            out = write_release(prefix, args.release_root, *release, frameid_pose=not args.no_frameid_pose)
            print(f"{out.name}: released under {out.parent} (training every {release[0]}th frame, held-out every "
                  f"{release[1]}th, frameid_pose.pkl {'no' if args.no_frameid_pose else 'yes'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
