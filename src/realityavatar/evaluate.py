"""Evaluation: novel-view and novel-pose metrics, per-frame CSV, image grids, videos, FPS -> metrics.json.

Command: `realityavatar-evaluate run_dir=<run folder> [threads=N] [overrides]` re-evaluates a trained run's checkpoint.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import torch

from realityavatar.build import build_data, load_run, run_device, write_json
from realityavatar.data.poses import PHASES

# metrics.image_metrics's scores: the whole image, the mask's box ("masked"), the garment's pixels ("garment")
METRIC_KEYS = ("psnr", "ssim", "iou", "flip", "lpips", "psnr_masked", "ssim_masked", "flip_masked", "lpips_masked",
               "detail_masked", "psnr_garment", "ssim_garment", "flip_garment", "detail_garment")
CAMERA_SPREAD_KEYS = ("psnr", "psnr_garment", "ssim_garment", "detail_garment")


def summarise(records: list[dict]) -> dict:
    """Mean of every metric per split, "test/<split>/<metric>", and per motion phase of the split (records with a
    "phase" other than "all"), "test/<split>/<phase>/<metric>"; absent metrics stay absent."""
    out: dict = {}
    for split in sorted({r["split"] for r in records}):
        rows = [r for r in records if r["split"] == split]
        groups = [(f"test/{split}", rows)] + [(f"test/{split}/{ph}", [r for r in rows if r.get("phase") == ph])
                                              for ph in PHASES]
        for prefix, sel in groups:
            if not sel:
                continue
            out[f"{prefix}/num_images"] = len(sel)
            for k in METRIC_KEYS:
                vals = [r[k] for r in sel if k in r and np.isfinite(r[k])]
                if vals:
                    out[f"{prefix}/{k}"] = float(np.mean(vals))
            for k in CAMERA_SPREAD_KEYS:  # how much the held-out cameras disagree: std of their means
                per_view = [np.mean(v) for v in _by_view(sel, k).values()]
                if len(per_view) > 1:
                    out[f"{prefix}/{k}_camera_std"] = float(np.std(per_view))
    return out


def _by_view(rows: list[dict], key: str) -> dict:
    """{view: [finite values of `key`]} of `rows`."""
    out: dict = {}
    for r in rows:
        if key in r and np.isfinite(r[key]):
            out.setdefault(r.get("view"), []).append(r[key])
    return out


def write_outputs(records: list[dict], out_dir: Path, save_images: int = 8, save_video: bool = True, fps: int = 10) -> dict:
    """Per-frame CSV, a prediction|ground-truth|error grid of `save_images` images per split (0: none), an MP4 per
    split. Returns written paths."""
    import imageio.v2 as imageio

    from realityavatar.animate import check_video_writer

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    csv_path = out_dir / "per_frame.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["split", "frame", "view", "phase", *METRIC_KEYS])
        for r in records:
            w.writerow([r["split"], r["frame"], r["view"], r.get("phase", "all"),
                        *[f"{r[k]:.6f}" if k in r else "" for k in METRIC_KEYS]])
    paths["per_frame_csv"] = str(csv_path)
    (out_dir / "images").mkdir(exist_ok=True)
    (out_dir / "videos").mkdir(exist_ok=True)
    for split in sorted({r["split"] for r in records}):
        rows = sorted([r for r in records if r["split"] == split], key=lambda r: (r["view"], r["frame"]))
        if not rows:
            continue
        if save_images > 0:
            pick = np.linspace(0, len(rows) - 1, min(save_images, len(rows))).round().astype(int)
            tiles = []
            for i in pick:
                pred, gt = rows[i]["_pred"].numpy(), rows[i]["_gt"].numpy()
                err = np.abs(pred - gt).mean(-1, keepdims=True).repeat(3, -1) * 4
                tiles.append(np.concatenate([pred, gt, np.clip(err, 0, 1)], 1))
            grid = (np.concatenate(tiles, 0) * 255).round().astype(np.uint8)
            p = out_dir / "images" / f"{split}_grid.png"
            imageio.imwrite(p, grid)
            paths[f"{split}_grid"] = str(p)
        if save_video:
            view0 = rows[0]["view"]
            frames = [np.concatenate([r["_pred"].numpy(), r["_gt"].numpy()], 1) for r in rows if r["view"] == view0]
            frames = [(np.clip(fr, 0, 1) * 255).round().astype(np.uint8) for fr in frames]
            p = out_dir / "videos" / f"{split}.mp4"
            try:
                check_video_writer(p)  # without ffmpeg imageio takes a TIFF writer for .mp4 (TypeError on fps)
                imageio.mimwrite(p, frames, fps=fps, macro_block_size=1)
                paths[f"{split}_video"] = str(p)
            except Exception as e:  # noqa: BLE001 (no ffmpeg, or a writer error: keep the metrics, say why)
                print(f"[evaluate] video for {split} not written: {e}", file=sys.stderr)
    return paths


def split_loader(dm, split: str, max_frames: int | None = None):
    """Test loader of one split; with `max_frames`, only that many evenly spaced frames (every camera of each)."""
    ds = dm.datasets[split]
    frames = sorted({r.frame for r in ds.records})
    if max_frames is None or len(frames) <= int(max_frames):
        return dm._loader(ds, shuffle=False)
    keep = {frames[i] for i in np.linspace(0, len(frames) - 1, int(max_frames)).round().astype(int)}
    idx = [i for i, r in enumerate(ds.records) if r.frame in keep]
    return dm._loader(torch.utils.data.Subset(ds, idx), shuffle=False)


def motion_phases(dm, split: str) -> dict[int, str]:
    """{frame: phase} of a split's frames from its poses (PoseTable.motion_phases); every frame "all" when the data
    has no frame rate (a config from before data.fps)."""
    frames = sorted({r.frame for r in dm.datasets[split].records})
    if not dm.fps:
        return dict.fromkeys(frames, "all")
    return dm.scene.poses.motion_phases(frames, dm.fps)


def protocol_scores(records: list[dict], dm, body, protocol, lpips=None) -> list[dict]:
    """`records` (test_step's, with their `_pred`/`_gt` images) with psnr, ssim and lpips rescored as `protocol`
    (metrics.EvalProtocol) scores them; the other scores stay ours. The pixels a protocol keeps come from each
    image's sample: its mask (SeqAvatar's box) or its pose and camera (Dyco's SMPL box, from `body`'s joints)."""
    from realityavatar.geometry import axis_angle_to_matrix
    from realityavatar.metrics import mask_box_mask, smpl_box_mask

    if protocol.name == "ours":
        return records
    index = {split: {(r.frame, r.view): i for i, r in enumerate(ds.records)} for split, ds in dm.datasets.items()}
    host = body.host_copy().double() if protocol.masking == "smpl_box" else None  # the samples are on the host
    out = []
    for r in records:
        ds = dm.datasets[r["split"]]
        sample = ds[index[r["split"]][(r["frame"], r["view"])]]
        pred, gt = r["_pred"], r["_gt"]
        H, W = pred.shape[:2]
        keep = None
        if protocol.masking == "mask_box":
            keep = mask_box_mask(sample["inside"])
        elif protocol.masking == "smpl_box":
            pose, transl = sample["poses"][-1].double(), sample["transl"][-1].double()  # the frame's own pose
            with torch.no_grad():
                joints = host.joints(pose, transl)  # [24,3] world
            keep = smpl_box_mask(joints, axis_angle_to_matrix(pose[0]), sample["K"], sample["viewmat"], H, W)
        scores = protocol.scores(pred, gt, keep, lpips, sample["background"])
        out.append({**{k: v for k, v in r.items() if k not in ("psnr", "ssim", "lpips")}, **scores})
    return out


def evaluate_module(module, dm, trainer, cfg, out_dir: Path) -> dict:
    """Test every split (novel_view, novel_pose), write outputs, return the metric dict.

    Each stage (each split's test loop, the per-frame CSV / grids / videos, the FPS measurement) runs on its own: a
    failing stage is recorded under "evaluation_errors" ({stage: message}) and the others still report.
    """
    from realityavatar.config import check_settings
    from realityavatar.metrics import eval_protocol

    check_settings(cfg, prefix="eval.")
    ev = cfg.get("eval", {}) or {}
    protocol = eval_protocol(ev.get("protocol", "ours"))  # a run from before the key: ours
    records, errors = [], {}
    for split in dm.test_split_names:
        module.test_records = []
        try:
            trainer.test(module, dataloaders=split_loader(dm, split, ev.get("max_frames_per_split")), verbose=False)
            phases = motion_phases(dm, split)
            scored = protocol_scores(module.test_records, dm, module.avatar.body, protocol, module.lpips)
            records += [{**r, "phase": phases.get(r["frame"], "all")} for r in scored]
        except Exception as e:  # noqa: BLE001 - recorded; the other split still runs
            errors[f"test/{split}"] = f"{type(e).__name__}: {e}"
    module.test_records = []
    metrics = summarise(records)
    metrics["eval_protocol"] = protocol.describe()
    if ev.get("max_frames_per_split") is not None:
        metrics["eval_max_frames_per_split"] = int(ev["max_frames_per_split"])
    if module.eval_supersample > 1:
        metrics["eval_supersample"] = module.eval_supersample
    try:
        metrics["outputs"] = write_outputs(records, Path(out_dir), ev.get("save_images", 8), ev.get("save_video", True))
    except Exception as e:  # noqa: BLE001
        errors["outputs"] = f"{type(e).__name__}: {e}"
    if dm.test_split_names:
        try:
            batch = next(iter(split_loader(dm, dm.test_split_names[0], 1)))
            module.to(trainer.strategy.root_device)  # time the run's device (teardown after test moved it to the CPU)
            metrics["render_fps"] = module.measure_fps(batch, ev.get("fps_warmup", 3), ev.get("fps_frames", 20))
            metrics["render_fps_device"] = module.run_info["fps"]["device"]
            metrics["render_fps_backend"] = module.run_info["fps"]["backend"]
            metrics["render_resolution"] = [int(batch["width"][0]), int(batch["height"][0])]
        except Exception as e:  # noqa: BLE001
            errors["render_fps"] = f"{type(e).__name__}: {e}"
    if errors:
        metrics["evaluation_errors"] = errors
    return metrics


def undersampled(info: dict, supersample: int, width: int) -> str | None:
    """What to do when a run is rendered below the resolution it trained at (info: its checkpoint's run facts) without
    enough supersampling: its sub-pixel Gaussians widen under the rasterizer's 2D filter (a 256 px run lost 2.6 dB
    at 128 px, 7.2 dB at 64 px; docs/gpu.md). None when it is not, or either size is unknown (a checkpoint from before
    the record; width 0: evaluation's FPS stage, which records the rendered size, failed)."""
    trained = (info.get("render") or {}).get("resolution")
    if not trained or not width or trained[0] <= 1.25 * supersample * width:
        return None
    return (f"the run trained at {trained[0]} px wide and renders at {supersample * width} for {width} px images: its "
            f"sub-pixel Gaussians widen; eval.supersample={max(round(trained[0] / width), 1)} renders at the training "
            f"size and averages (docs/gpu.md)")


def format_table(metrics: dict) -> str:
    """A short results table for the terminal: per split, then per split and motion phase where the data has
    phases (the garment's columns where it has garment labels)."""
    def g(key):
        return metrics.get(key)

    def num(v, fmt):
        return f"{v:{fmt}}" if v is not None and np.isfinite(v) else f"{'-':>{int(fmt.split('.')[0])}}"

    lines = [(f"{'split':<12}{'PSNR':>8}{'SSIM':>8}{'IoU':>7}{'FLIP':>8}{'LPIPS':>9}{'PSNR(box)':>11}"
              f"{'SSIM(box)':>11}{'images':>8}")]
    for split in ("novel_view", "novel_pose"):
        p = f"test/{split}"
        if g(f"{p}/psnr") is None:
            continue
        lp = f"{g(f'{p}/lpips'):9.2f}" if g(f"{p}/lpips") is not None else f"{'n/c':>9}"
        lines.append(f"{split:<12}{num(g(f'{p}/psnr'), '8.2f')}{num(g(f'{p}/ssim'), '8.4f')}"
                     f"{num(g(f'{p}/iou'), '7.3f')}{num(g(f'{p}/flip'), '8.4f')}{lp}{num(g(f'{p}/psnr_masked'), '11.2f')}"
                     f"{num(g(f'{p}/ssim_masked'), '11.4f')}{g(f'{p}/num_images'):8d}")
    phased = [(split, ph) for split in ("novel_view", "novel_pose") for ph in PHASES
              if g(f"test/{split}/{ph}/num_images")]
    if phased:
        garment = any(g(f"test/{s}/{ph}/psnr_garment") is not None for s, ph in phased)
        cols = [("PSNR", "psnr", "8.2f"), ("PSNR(box)", "psnr_masked", "11.2f"), ("detail", "detail_masked", "8.2f")]
        if garment:
            cols += [("PSNR(garm)", "psnr_garment", "12.2f"), ("SSIM(garm)", "ssim_garment", "12.4f"),
                     ("FLIP(garm)", "flip_garment", "12.4f"), ("detail(garm)", "detail_garment", "14.2f")]
        lines.append(f"{'phase':<21}" + "".join(f"{name:>{int(fmt.split('.')[0])}}" for name, _, fmt in cols)
                     + f"{'images':>8}")
        for split, ph in phased:
            p = f"test/{split}/{ph}"
            lines.append(f"{split + ' ' + ph:<21}" + "".join(num(g(f"{p}/{k}"), fmt) for _, k, fmt in cols)
                         + f"{g(f'{p}/num_images'):8d}")
    lines.append(
        f"Gaussians {metrics.get('num_gaussians')}  parameters {metrics.get('num_parameters')}  "
        f"train {metrics.get('train_seconds', float('nan')):.0f} s / {metrics.get('iterations')} it  "
        f"render {metrics.get('render_fps', float('nan')):.1f} FPS"
    )
    if metrics.get("lpips"):  # "computed (<where the weights came from>)" or "not computed: <why>"
        lines.append(f"LPIPS {metrics.get('lpips')}")
    proto = metrics.get("eval_protocol") or {"name": "ours"}  # metrics.json from before the key: ours
    lines.append(f"protocol {proto['name']}" + (
        " (eval.protocol: the raw render scored against the image)" if proto["name"] == "ours" else
        f": PSNR / SSIM / LPIPS as {proto['name']} scores them ({proto.get('masking')} masking, "
        f"{'uint8-floored images, ' if proto.get('uint8_floor') else ''}{proto.get('ssim')}, {proto.get('psnr')}, "
        f"LPIPS on {proto.get('lpips_input')}); the other columns as ours"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import pytorch_lightning as pl

    from realityavatar.runtime import set_threads

    args = list(sys.argv[1:] if argv is None else argv)
    run_dir = next((a.split("=", 1)[1] for a in args if a.startswith("run_dir=")), None)
    if run_dir is None:
        print("usage: realityavatar-evaluate run_dir=<run folder> [threads=N] [key=value overrides]", file=sys.stderr)
        return 2
    overrides = [a for a in args if not a.startswith("run_dir=")]
    try:
        set_threads(next((a.split("=", 1)[1] for a in overrides if a.split("=", 1)[0].lstrip("+") == "threads"), None))
    except ValueError as e:
        print(f"realityavatar-evaluate: {e}", file=sys.stderr)
        return 2
    cfg, module, info = load_run(run_dir, overrides)  # checks the settings it is given
    dm = build_data(cfg, module.avatar.body)
    # The run's device: its GPU when it trained on one and CUDA is here, else the CPU (a GPU run evaluates anywhere).
    trainer = pl.Trainer(accelerator=run_device(cfg).type.replace("cuda", "gpu"), devices=1, logger=False,
                         enable_progress_bar=False)
    out = Path(run_dir) / "eval"
    metrics = evaluate_module(module, dm, trainer, cfg, out)
    metrics["lpips"] = module.lpips_status
    note = undersampled(info, module.eval_supersample, (metrics.get("render_resolution") or [0])[0])
    if note:
        metrics["eval_undersampled"] = note
        print(f"realityavatar-evaluate: {note}", file=sys.stderr)
    write_json(out / "metrics.json", {**info.get("metrics_header", {}), **metrics})
    print(format_table({**info.get("metrics_header", {}), **metrics}))
    print(f"wrote {out / 'metrics.json'}")
    if metrics.get("evaluation_errors"):
        for stage, err in metrics["evaluation_errors"].items():
            print(f"realityavatar-evaluate: {stage} failed: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
