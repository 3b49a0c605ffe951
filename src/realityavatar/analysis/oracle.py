"""Glued-Gaussian oracle: Gaussians fixed on a synthetic scene's true body and garment meshes, appearance learnt,
scored on the held-out images as a training run is (the ceiling a model that tracks the cloth perfectly reaches).

Usage: python -m realityavatar.analysis.oracle [--data synthetic_demo] [--steps 3000] [--views train|all]
       [--slide-cm S] [--drape true|pose] [--light exact|none] [--cloth-of RUN] [--body 16000] [--garment 24000]
       [--out DIR] [config overrides ...]

Every Gaussian sits at a fixed triangle and barycentric point of the scene's posed body (the package's body model on
the scene's poses, as the scene builder poses it) or of its simulated garment (<root>/<scene>-garment.npz), so in
every frame it is where its material point is. It is a flat disc in the surface (two in-surface scales between 0.1 and
2 times the sampling's spacing, 1 mm along the normal, turned by a learnt angle, shifted at most 2 cm along the normal:
the rasterizer's 0.3 px low-pass widens a dense layer by ~1 px) lit as the scene is (albedo x (ambient + diffuse x
max(0, n.l)), the normal turned to the camera as the scene's two-sided cloth is). Learnt, shared by all frames: albedo,
opacity, scales, angle and shift per Gaussian, with L1 + 0.2 D-SSIM + 0.1 mask MSE on the training cameras of every
training frame (`--views all`: the held-out cameras' images too, a bound set by the representation alone).
`--slide-cm S` slides the garment's Gaussians S cm towards the waist at peak flare (in proportion to the flare in
other frames): a controlled version of the drift learnt models show. `--drape pose`: a training frame whose pose
window (what a pose-driven model reads: data.window_len poses data.window_step apart) equals an earlier frame's shows
that frame's cloth, so a drape the poses cannot tell apart (the demo's skirt settles after its stop into another
drape than it started in, at the same pose) is the ceiling of a model driven by the pose window that tracks the cloth
perfectly otherwise (docs/research/2026-11-28-garment-settled-drape.md). `--light none`: one unlit colour per Gaussian.
`--cloth-of RUN`: the garment's Gaussians glued to a sheet=physics run's simulated cloth instead (its `track`, the
simulation without the residual): the ceiling of that cloth's geometry (docs/research/2026-12-08-physics-garment.md).
The simulator's meshes serve this oracle and diagnostics only, never training.
Writes <out>/metrics.json (test/<split>/<phase>/<metric>, as a training run), per_frame.csv, phases.png and prints
the table (docs/research/2026-11-28-garment-oracle-256.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from torch.utils.data import default_collate

NORMAL_SCALE = 1e-3  # metres: the Gaussians are discs in the surface
NORMAL_SHIFT = 0.02  # metres: the most a Gaussian may sit off the surface, along its normal


def scene_meshes(dm, body) -> tuple[list[int], torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
    """Per frame of the garment file: frames, body vertices [T,V,3] (world, float64), body faces [F,3], garment
    vertices [T,Vg,3], garment faces [Fg,3], garment uv [Vg,2]. The body is posed from the scene's poses."""
    from realityavatar.data.synthetic.scene import body_sequence

    npz = Path(dm.root) / f"{dm.sequence}-garment.npz"
    if not npz.is_file():
        raise FileNotFoundError(f"{npz}: not found (the oracle needs a synthetic scene's simulated garment)")
    g = np.load(npz)
    for key in ("vertices", "faces", "uv", "frames"):
        if key not in g.files:
            raise ValueError(f"{npz}: no field {key!r} (expected vertices [T,Vg,3], faces, uv [Vg,2], frames [T])")
    frames = [int(f) for f in g["frames"]]
    missing = [f for f in frames if f not in dm.scene.poses]
    if missing:
        raise ValueError(f"{npz}: field 'frames' names frames {missing[:5]} that {dm.scene.source} has no pose for")
    pose = torch.stack([dm.scene.poses.get(f)[0] for f in frames]).double()  # [T,24,3] SMPL convention
    transl = torch.stack([dm.scene.poses.get(f)[1] for f in frames]).double()
    motion = SimpleNamespace(pose=pose.numpy(), Rh=np.zeros((len(frames), 3)), Th=transl.numpy())
    body_v = torch.as_tensor(body_sequence(body, motion)[0])
    return (frames, body_v, body.faces.long(), torch.as_tensor(g["vertices"], dtype=torch.float64),
            torch.as_tensor(g["faces"]).long(), g["uv"])


def pose_driven_rows(dm, frames: list[int]) -> list[int]:
    """Per garment frame, the row of the earliest training frame whose pose window (the dataset's: data.window_len
    poses data.window_step apart) equals its own, else its own row. Only the training frames are matched; the
    novel-pose sequence keeps its own cloth."""
    train = {int(r.frame) for r in dm.datasets["train"].records}

    def window(f: int) -> torch.Tensor:
        poses, transl = dm.scene.poses.window(f, dm.window_len, dm.window_step)
        return torch.cat([poses.flatten(), transl.flatten()]).double()

    row = {f: i for i, f in enumerate(frames)}
    out, seen = list(range(len(frames))), []
    for f in (f for f in frames if f in train):
        w = window(f)
        match = next((g for g, wg in seen if torch.allclose(w, wg, rtol=0, atol=1e-6)), None)
        if match is None:
            seen.append((f, w))
        else:
            out[row[f]] = row[match]
    return out


def run_cloth(run: Path, frames: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """A sheet=physics run's simulated cloth (its checkpoint's track, without the residual) at `frames`: vertices
    [T,P,3] (float64), faces [F,3]."""
    ckpt = run / "last.ckpt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: not found (--cloth-of takes a sheet=physics run folder)")
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    if "avatar.sheet.track" not in state:
        raise ValueError(f"{ckpt}: no simulated cloth (avatar.sheet.track): not a sheet=physics run")
    first = state["avatar.sheet.track_frames"].long()
    rows = torch.tensor(frames) - int(first[0])
    if int(rows.min()) < 0 or int(rows.max()) >= len(first):
        raise ValueError(f"{ckpt}: its cloth covers frames {int(first[0])}..{int(first[-1])}, the scene {frames[0]}.."
                         f"{frames[-1]}")
    return state["avatar.sheet.track"][rows].double(), state["avatar.sheet.faces"].long()


def grid_locate(uv: torch.Tensor, cols: int, rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points [...,2] of the garment's uv square (u around, periodic; v waist to hem, clamped) -> vertex ids [...,3]
    and barycentrics [...,3] on its regular cols x rows vertex grid, whose quads are split as cloth.tube_topology's."""
    a = torch.remainder(uv[..., 0], 1.0) * (cols - 1)
    b = uv[..., 1].clamp(0.0, 1.0) * (rows - 1)
    c, r = a.floor().clamp(max=cols - 2), b.floor().clamp(max=rows - 2)
    a, b = a - c, b - r
    i = (r * cols + c).long()
    lower = (a + b <= 1)[..., None]
    ids = torch.where(lower, torch.stack([i, i + 1, i + cols], -1), torch.stack([i + 1, i + cols + 1, i + cols], -1))
    bary = torch.where(lower, torch.stack([1 - a - b, a, b], -1), torch.stack([1 - b, a + b - 1, 1 - a], -1))
    return ids, bary


def flare(V: torch.Tensor, cols: int) -> torch.Tensor:
    """Per frame, the hem ring's mean distance from the waist ring's axis beyond its first-frame value, over its
    largest such value: 0 at rest, 1 at peak flare. V [T,Vg,3] (world, y up; the first and last rings)."""
    axis = V[:, :cols].mean(1, keepdim=True)
    radius = (V[:, -cols:] - axis)[..., [0, 2]].norm(dim=-1).mean(1)  # [T]
    out = (radius - radius[0]).clamp_min(0)
    return out / out.max().clamp_min(1e-9)


class GluedGaussians(torch.nn.Module):
    """Gaussians at fixed points of per-frame meshes, appearance and footprint learnt (shared by all frames).

    parts: [(V [T,Nv,3], F [Nf,3], n, slide)] per mesh; slide None, or (uv [Nv,2], cols, rows, dv [T]) to place the
    part's Gaussians at their material point's (u, v + dv(t)) in frame t (dv 0: on their material point)."""

    def __init__(self, parts: list[tuple], gen: torch.Generator, light: str, ambient: float, diffuse: float,
                 light_dir) -> None:
        from realityavatar.geometry import sample_barycentric
        from realityavatar.model.shading import vertex_normals

        super().__init__()
        if light not in ("exact", "none"):
            raise ValueError(f"light: expected 'exact' or 'none', got {light!r}")
        self.light, self.ambient, self.diffuse = light, float(ambient), float(diffuse)
        self.register_buffer("light_dir", torch.as_tensor(light_dir, dtype=torch.float32))
        pos, nrm, tan, spacing = [], [], [], []
        for V, F, n, slide in parts:
            fi, bary, area = sample_barycentric(V[0], F, n, gen)  # on the first frame's mesh
            T = V.shape[0]
            ids, w = F[fi][None].expand(T, n, 3), bary.double()[None].expand(T, n, 3)
            if slide is not None:
                uv, cols, rows, dv = slide
                uv0 = (bary.double()[..., None] * uv[F[fi]]).sum(1)  # [n,2] each Gaussian's material point
                ids, w = grid_locate(uv0[None] + torch.stack([torch.zeros_like(dv), dv], -1)[:, None], cols, rows)
            tri = V[torch.arange(T)[:, None, None], ids]  # [T,n,3,3]
            vn = torch.stack([vertex_normals(v, F) for v in V])[torch.arange(T)[:, None, None], ids]
            pos.append((w[..., None] * tri).sum(2))
            nrm.append(torch.nn.functional.normalize((w[..., None] * vn).sum(2), dim=-1))
            tan.append(tri[:, :, 1] - tri[:, :, 0])
            spacing.append(torch.full((n,), float((area.sum() / n).sqrt())))
        self.register_buffer("pos", torch.cat(pos, 1).float())  # [T,N,3]
        self.register_buffer("nrm", torch.cat(nrm, 1).float())  # [T,N,3] the surface's normal there
        self.register_buffer("tan", torch.cat(tan, 1).float())  # [T,N,3] a triangle edge: the angle's origin
        self.register_buffer("spacing", torch.cat(spacing))  # [N] metres between neighbouring samples
        N = self.pos.shape[1]
        self.albedo = torch.nn.Parameter(torch.zeros(N, 3))  # sigmoid: 0.5 grey
        self.opacity = torch.nn.Parameter(torch.full((N,), 2.0))  # sigmoid: 0.88
        self.scale_logit = torch.nn.Parameter(torch.full((N, 2), -0.69))  # 0.1 + 1.9 sigmoid: 0.6 x the spacing
        self.angle = torch.nn.Parameter(torch.zeros(N))
        self.shift_logit = torch.nn.Parameter(torch.zeros(N))

    def at(self, t: int, eye: torch.Tensor):
        """Row t of the frames, the camera centre eye [3] -> means [N,3], quats [N,4], scales [N,3], opacities [N],
        colours [N,3]."""
        from realityavatar.geometry import matrix_to_quat

        n, e = self.nrm[t], self.tan[t]
        x = self.pos[t] + NORMAL_SHIFT * torch.tanh(self.shift_logit)[:, None] * n
        t1 = torch.nn.functional.normalize(e - (e * n).sum(-1, keepdim=True) * n, dim=-1)
        t2 = torch.linalg.cross(n, t1)
        c, s = self.angle.cos()[:, None], self.angle.sin()[:, None]
        R = torch.stack([c * t1 + s * t2, -s * t1 + c * t2, n], -1)  # columns: the disc's axes
        s2 = self.spacing[:, None] * (0.1 + 1.9 * torch.sigmoid(self.scale_logit))
        scales = torch.cat([s2, torch.full_like(s2[:, :1], NORMAL_SCALE)], -1)
        rgb = torch.sigmoid(self.albedo)
        if self.light == "exact":
            facing = torch.where(((x - eye) * n).sum(-1, keepdim=True) > 0, -n, n)  # two-sided, as the scene
            rgb = rgb * (self.ambient + self.diffuse * (facing @ self.light_dir).clamp_min(0))[:, None]
        return x, matrix_to_quat(R), scales, torch.sigmoid(self.opacity), rgb


def render(model: GluedGaussians, t: int, b: dict, background, options: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """One collated sample b -> image [1,H,W,3], alpha [1,H,W,1] of frame row t over `background` [3], rasterized
    with the run's `render` options (backend, rasterize_mode, eps2d, ...) as a trained model is."""
    from realityavatar.geometry import camera_centres
    from realityavatar.render.splat import rasterize

    means, quats, scales, opac, rgb = model.at(t, camera_centres(b["viewmat"])[0])
    img, alpha, _ = rasterize(means, quats, scales, opac, rgb, b["viewmat"], b["K"], int(b["width"][0]),
                              int(b["height"][0]), background=background, **options)
    return img, alpha


def main(argv: list[str] | None = None) -> int:
    from hydra.utils import instantiate

    from realityavatar.build import build_data, git_commit, write_json
    from realityavatar.config import compose
    from realityavatar.data.datamodule import composite
    from realityavatar.data.synthetic.render import AMBIENT, DIFFUSE, LIGHT_DIR
    from realityavatar.evaluate import format_table, motion_phases, summarise, write_outputs
    from realityavatar.kernels import dssim
    from realityavatar.metrics import image_metrics
    from realityavatar.runtime import add_threads_option, set_threads

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="synthetic_demo", help="data config (a synthetic scene)")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps, one training image each")
    ap.add_argument("--views", choices=("train", "all"), default="train",
                    help="fit the training cameras, or the held-out cameras' images too")
    ap.add_argument("--slide-cm", type=float, default=0.0, help="garment Gaussians slide this far at peak flare")
    ap.add_argument("--drape", choices=("true", "pose"), default="true",
                    help="the garment's cloth per frame: the true one, or the one of the earliest frame with the same pose window")
    ap.add_argument("--light", choices=("exact", "none"), default="exact")
    ap.add_argument("--cloth-of", default=None, metavar="RUN",
                    help="glue the garment's Gaussians to this sheet=physics run's simulated cloth, not the scene's")
    # defaults: ~0.9 cm apart on both meshes, about a pixel of the 256 px demo scene
    ap.add_argument("--body", type=int, default=16000, help="Gaussians on the body mesh")
    ap.add_argument("--garment", type=int, default=24000, help="Gaussians on the garment mesh")
    ap.add_argument("--seed", type=int, default=0)
    add_threads_option(ap)
    ap.add_argument("--out", default=None, help="output folder (default outputs/oracle/<data>_<views>...)")
    ap.add_argument("overrides", nargs="*", help="more config overrides (data.image_scale=0.5, +render.eps2d=0.1, ...)")
    a = ap.parse_args(argv)
    if a.cloth_of and a.slide_cm:
        ap.error("--slide-cm slides along the scene's cloth: not with --cloth-of")
    set_threads(a.threads, "--threads")
    commit = git_commit()  # the code that runs: read before other sessions commit
    tag = (a.views + (f"_slide{a.slide_cm:g}cm" if a.slide_cm else "") + ("_unlit" if a.light == "none" else "")
           + ("_posedrape" if a.drape == "pose" else "") + ("_modelcloth" if a.cloth_of else ""))
    out = Path(a.out or f"outputs/oracle/{a.data}_{tag}")
    cfg = compose([f"data={a.data}", *a.overrides])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    options = {k: v for k, v in cfg.render.items() if k != "background"}  # the scene's background is dm's
    frames, body_v, body_f, garm_v, garm_f, uv = scene_meshes(dm, body)
    if a.cloth_of:
        garm_v, garm_f = run_cloth(Path(a.cloth_of), frames)
    row = {f: i for i, f in enumerate(frames)}
    cols, rows = len(np.unique(uv[:, 0])), len(np.unique(uv[:, 1]))
    if a.drape == "pose":
        rep = pose_driven_rows(dm, frames)
        print(f"oracle: --drape pose: {sum(r != i for i, r in enumerate(rep))} frames show an earlier frame's cloth")
        garm_v = garm_v[rep]
    slide = None
    if a.slide_cm:
        length = (garm_v[0, -cols:] - garm_v[0, :cols]).norm(dim=-1).mean()  # waist to hem at rest, metres
        slide = (torch.as_tensor(uv, dtype=torch.float64), cols, rows, -a.slide_cm / 100 / length * flare(garm_v, cols))
    params = (dm.scene.meta or {}).get("params", {})
    gen = torch.Generator().manual_seed(a.seed)
    model = GluedGaussians([(body_v, body_f, a.body, None), (garm_v, garm_f, a.garment, slide)], gen, a.light,
                           params.get("ambient", AMBIENT), params.get("diffuse", DIFFUSE), LIGHT_DIR)

    def samples(split: str) -> list[dict]:
        ds = dm.datasets.get(split)
        return [] if ds is None else [composite(default_collate([ds[i]])) for i in range(len(ds))]

    held = {s: samples(s) for s in dm.test_split_names}
    covered = {s: [b for b in bs if int(b["frame"][0]) in row] for s, bs in held.items()}
    for s, bs in held.items():
        if len(covered[s]) < len(bs):
            print(f"oracle: {len(bs) - len(covered[s])} {s} images are of frames the garment file lacks; "
                  "not scored", file=sys.stderr)
    fit = samples("train") + (covered.get("novel_view", []) if a.views == "all" else [])
    opt = torch.optim.Adam([{"params": [model.albedo, model.opacity], "lr": 2e-2},
                            {"params": [model.scale_logit, model.angle, model.shift_logit], "lr": 1e-2}])
    t0, recent = time.perf_counter(), []
    for step in range(a.steps):
        b = fit[int(torch.randint(len(fit), (1,), generator=gen))]
        img, alpha = render(model, row[int(b["frame"][0])], b, dm.background, options)
        loss = ((img - b["image"]).abs().mean() + 0.2 * dssim(img.permute(0, 3, 1, 2), b["image"].permute(0, 3, 1, 2))
                + 0.1 * ((alpha - b["mask"]) ** 2).mean())  # conf/loss/default's image terms (D-SSIM as without VGG)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        recent.append(loss.item())
        if (step + 1) % 500 == 0:
            print(f"step {step + 1}: mean loss of the last 500 {np.mean(recent):.4f} ({time.perf_counter() - t0:.0f} s)",
                  flush=True)
            recent = []
    fit_s = time.perf_counter() - t0
    records, render_s, tiles = [], 0.0, {}
    with torch.no_grad():
        for split, batches in covered.items():
            phases = motion_phases(dm, split)
            for b in batches:
                f, view = int(b["frame"][0]), int(b["view"][0])
                t1 = time.perf_counter()
                img, alpha = render(model, row[f], b, dm.background, options)
                render_s += time.perf_counter() - t1
                pred = img[0].clamp(0, 1)
                rec = image_metrics(pred, b["image"][0], alpha[0], b["mask"][0], b.get("garment", [None])[0])
                rec_phase = phases.get(f, "all")
                records.append({"split": split, "frame": f, "view": view, "phase": rec_phase, **rec})
                if split == "novel_view" and view == int(batches[0]["view"][0]) and rec_phase not in tiles:
                    tiles[rec_phase] = torch.cat([pred, b["image"][0]], 1)  # the first image of each phase
    metrics = {**summarise(records), "oracle": {
        "data": a.data, "overrides": a.overrides, "views": a.views, "slide_cm": a.slide_cm, "drape": a.drape, "light": a.light,
        "cloth_of": a.cloth_of,
        "body": a.body, "garment": a.garment, "seed": a.seed, "ambient": model.ambient, "diffuse": model.diffuse},
        "commit": commit, "iterations": a.steps, "num_gaussians": int(model.pos.shape[1]),
        "train_seconds": round(fit_s, 1), "render_fps": len(records) / max(render_s, 1e-9),
        "command": "python -m realityavatar.analysis.oracle " + " ".join(sys.argv[1:] if argv is None else argv)}
    out.mkdir(parents=True, exist_ok=True)
    write_outputs(records, out, save_images=0, save_video=False)  # per_frame.csv
    if tiles:
        import imageio.v2 as imageio

        grid = torch.cat([tiles[p] for p in tiles], 0)  # one row per phase: prediction | ground truth
        imageio.imwrite(out / "phases.png", (grid.numpy() * 255).round().astype(np.uint8))
    write_json(out / "metrics.json", metrics)
    print(format_table(metrics))
    print(f"wrote {out / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
