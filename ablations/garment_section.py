"""Where a trained model puts the garment's Gaussians, against the simulated cloth (synthetic scenes only).

Usage: python ablations/garment_section.py <run_dir> [...] --out <folder> [--labels a,b] [--frames 10,28,32,36]

Garment Gaussians are those within 2 cm of the cloth in every rest frame (ablations/probe.py's rule). For every
training frame it deforms the Gaussians (the training frame's own inputs, frame codes included) and writes, per run:
- section_<label>.png: radius from the waist ring's centre against height below it, the cloth's surface samples
  (black) and the Gaussians within 15 cm of the cloth (garment ones coloured by their distance to the cloth, the rest
  orange), for the frames of --frames. A skirt that flares less than the cloth shows as a cone steeper than the black
  one; body Gaussians dragged along with it as an orange fan between the legs and the cone.
- section.csv: per frame, the garment Gaussians' median distance to the cloth (cm) and how far their material
  position has slid in texture cells, split into around the waist (u, GarmentTexture's 16 cells) and from waist to
  hem (v, its 24 cells): median |du|, median du, median |dv|, median dv. A Gaussian whose material position has slid
  shows the colour of another cell. Columns band0..band4: the median distance to the cloth (cm) of the garment
  Gaussians in each fifth of the skirt's length, by their rest material position (band0 at the waist, band4 the hem).
  cover, cover0..cover4: the share of the cloth's surface (samples, overall and per fifth of its length by texture v)
  with the centre of some Gaussian of opacity > 0.1 within 2 cm, whichever Gaussian it is: a model may build the
  flared skirt from Gaussians that sat elsewhere at rest (e.g. hidden under the skirt), which the distances above
  do not see. cloth_up: the cloth's outward normal's mean vertical component (0 hanging, towards 1 flared into a
  disc). With a garment sheet (sheet=skirt) also sheet_up (the same for the sheet's cells, opacity-weighted),
  sheet_lap_cm (median second difference down its columns of its displacement from the rest layout: a flare moves a
  column linearly, a crumpled sheet zigzags) and sheet_zigzag (median column path length over its end-to-end length).
  With shading=irradiance also light_up, light_cos and light_ratio: the shading normals of the Gaussians within 2 cm
  of the cloth against the cloth's own (`light_normals`): a flared skirt lit by the hanging body's normals gets the
  light of a hanging skirt.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.utils.data import default_collate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from probe import CLOTH_NEAR, phase_of

from realityavatar.build import build_data, load_run

CELLS_U, CELLS_V = 16, 24  # realityavatar.data.synthetic.render.GarmentTexture's default cells
SAMPLES = 60000  # cloth surface samples (a few mm apart on the demo skirt)


def outward(normals: np.ndarray, points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Normals [n,3] turned away from the vertical axis (y is up) through `centre` [3] at their points [n,3]."""
    radial = (points - centre)[:, [0, 2]]
    return normals * np.where((radial * normals[:, [0, 2]]).sum(1) < 0, -1.0, 1.0)[:, None]


def outward_up(centres: np.ndarray, normals: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Mean vertical component (y is up) of unit normals [n,3] turned away from the vertical axis through their
    points' centre (centres [n,3]), weighted by `weights` [n]: 0 for a hanging skirt, towards 1 for one flared into a
    disc."""
    return float(np.average(outward(normals, centres, centres.mean(0))[:, 1], weights=weights))


def cloth_up(verts: np.ndarray, faces: np.ndarray) -> float:
    """outward_up of the cloth's faces, area-weighted."""
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(n, axis=1)
    return outward_up(tri.mean(1), n / np.maximum(area, 1e-12)[:, None], area)


@torch.no_grad()
def sheet_shape(module, posed: dict) -> dict:
    """A garment sheet's posed shape (sheet=skirt runs): whether it is a surface that flares like the cloth.
    sheet_up: outward_up of its cells' normals, opacity-weighted; sheet_lap_cm: the median second difference down
    its columns of its displacement from the rest layout (a flare or the body's turn displaces a column linearly,
    a zigzag does not); sheet_zigzag: the median over columns of their path length over their end-to-end length."""
    sh = module.sheet
    R, C = sh.rows + 1, sh.cols
    V = posed["sheet_verts"][0].double()
    normals = sh._cell_frame(V[None].float())[2]  # each Gaussian's cell normal (its frame's third axis)
    up = outward_up(sh.place(V[None].float())["means"][0].double().numpy(), normals[0].double().numpy(),
                    sh.opacities().detach().double().numpy())
    G = V.reshape(R, C, 3)
    D = G - sh._reference_layout().double().reshape(R, C, 3)
    lap = (D[2:] - 2 * D[1:-1] + D[:-2]).norm(dim=-1)
    path = (G[1:] - G[:-1]).norm(dim=-1).sum(0)
    chord = (G[-1] - G[0]).norm(dim=-1).clamp_min(1e-9)
    return {"sheet_up": up, "sheet_lap_cm": float(lap.median()) * 100, "sheet_zigzag": float((path / chord).median())}


@torch.no_grad()
def light_normals(module, posed: dict, pts: np.ndarray, tris: np.ndarray, nearest: np.ndarray,
                  near: np.ndarray) -> dict:
    """The shading's world normals (shading.normals: the body's at x_e, or carried by the decoder's field) of the
    Gaussians `near` the cloth against the outward normal of their nearest cloth sample (pts [P,3], their
    triangles tris [P,3,3], nearest [N] sample index). light_up: the shading normals' median outward vertical
    component (compare cloth_up); light_cos: their median cosine to the cloth's normal; light_ratio: the mean
    irradiance E (grey) they give over the one the cloth's normal would give, under the run's trained light map."""
    if not near.any():
        return {"light_up": float("nan"), "light_cos": float("nan"), "light_ratio": float("nan")}
    sh = module.shading
    n_c = posed.get("n_c")
    n_c = sh.normals(posed["x_e"][0]) if n_c is None else n_c[0]
    n_w = (posed["rot"][0] @ n_c[..., None]).squeeze(-1)[torch.from_numpy(near)]
    t = tris[nearest[near]]
    cn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    cn /= np.maximum(np.linalg.norm(cn, axis=1, keepdims=True), 1e-12)
    at, centre = pts[nearest[near]], pts.mean(0)
    cn = outward(cn, at, centre)  # as cloth_up
    unit = torch.nn.functional.normalize(n_w, dim=-1).double().numpy()
    e_model = sh.irradiance(n_w).mean(-1)
    e_cloth = sh.irradiance(torch.from_numpy(cn).to(n_w) * n_w.norm(dim=-1, keepdim=True)).mean(-1)
    return {"light_up": float(np.median(outward(unit, at, centre)[:, 1])),
            "light_cos": float(np.median((unit * cn).sum(1))),
            "light_ratio": float((e_model / e_cloth).mean())}


def cloth_samples(faces: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Triangles [n] and barycentrics [n,3] of uniform samples on a mesh's faces (fixed across frames)."""
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, len(faces), n)
    r = rng.random((n, 2))
    r = np.where(r.sum(1, keepdims=True) > 1, 1 - r, r)
    return tri, np.stack([1 - r.sum(1), r[:, 0], r[:, 1]], 1)


@torch.no_grad()
def section(run_dir: Path, threads: int = 1) -> dict:
    """Per training frame: posed means [N,3], their distance to the cloth [N] and material uv [N,2]; plus the cloth."""
    torch.set_num_threads(threads)
    cfg, module, _ = load_run(run_dir)
    dm = build_data(cfg, module.body)
    npz = Path(str(cfg.data.root)) / f"{cfg.data.sequence}-garment.npz"
    if not npz.is_file():
        raise FileNotFoundError(f"{npz}: garment_section needs a synthetic scene's simulated garment")
    g = np.load(npz)
    V, F, UV, gframes = g["vertices"], g["faces"], g["uv"].astype(np.float64), [int(f) for f in g["frames"]]
    tri, bary = cloth_samples(F, SAMPLES)
    uv_s = np.einsum("pk,pkc->pc", bary, UV[F[tri]])
    meta = dm.scene.meta or {}
    events, fps = meta.get("motion", {}).get("events", {}), float(meta.get("fps", 25.0))
    ds = dm.datasets["train"]
    frames: dict[int, dict] = {}
    for i, rec in enumerate(ds.records):
        f = int(rec.frame)
        if f in frames or f not in gframes:
            continue
        b = default_collate([ds[i]])
        posed = module.deform(b["poses"], b["transl"], frame_idx=b["frame_idx"])
        x = posed["means"][0].double().numpy()
        pts = np.einsum("pk,pkc->pc", bary, V[gframes.index(f)][F[tri]])
        d, j = cKDTree(pts).query(x)
        seen = x[posed["opacities"].detach().numpy() > 0.1]
        covered = cKDTree(seen).query(pts)[0] < CLOTH_NEAR if len(seen) else np.zeros(len(pts), bool)
        frames[f] = {"x": x, "d": d, "uv": uv_s[j], "cloth": pts, "phase": phase_of(f, events, fps),
                     "covered": covered, "shape": {"cloth_up": cloth_up(V[gframes.index(f)], F)}}
        if hasattr(module.shading, "irradiance"):  # shading=irradiance: the light's normals against the cloth's
            near = (d < CLOTH_NEAR) & (posed["opacities"].detach().numpy() > 0.1)
            frames[f]["shape"].update(light_normals(module, posed, pts, V[gframes.index(f)][F[tri]], j, near))
        if module.sheet is not None:
            frames[f]["shape"].update(sheet_shape(module, posed))
    rest = [f for f in sorted(frames) if frames[f]["phase"] == "rest"] or sorted(frames)[:1]
    on = np.all([frames[f]["d"] < CLOTH_NEAR for f in rest], 0)
    if not on.any():
        raise ValueError(f"{run_dir}: no Gaussian lies within {CLOTH_NEAR} m of the cloth in every rest frame")
    home = np.mean([frames[f]["uv"][on] for f in rest], 0)
    return {"frames": frames, "garment": on, "home": home, "cloth_v": uv_s[:, 1]}


def table(res: dict) -> list[dict]:
    on, home, rows = res["garment"], res["home"], []
    for f in sorted(res["frames"]):
        r = res["frames"][f]
        du = (r["uv"][on, 0] - home[:, 0] + 0.5) % 1.0 - 0.5  # u wraps around the waist
        dv = r["uv"][on, 1] - home[:, 1]
        rows.append({"frame": f, "phase": r["phase"], "garment_gaussians": int(on.sum()),
                     "dist_cm": float(np.median(r["d"][on]) * 100),
                     "abs_du_cells": float(np.median(np.abs(du)) * CELLS_U), "du_cells": float(np.median(du) * CELLS_U),
                     "abs_dv_cells": float(np.median(np.abs(dv)) * CELLS_V), "dv_cells": float(np.median(dv) * CELLS_V)})
        band = np.minimum((home[:, 1] * 5).astype(int), 4)  # fifths of the length by rest position (v: waist 0)
        for k in range(5):
            sel = band == k
            rows[-1][f"band{k}"] = float(np.median(r["d"][on][sel]) * 100) if sel.any() else float("nan")
        rows[-1]["cover"] = float(r["covered"].mean())
        cband = np.minimum((res["cloth_v"] * 5).astype(int), 4)
        for k in range(5):
            rows[-1][f"cover{k}"] = float(r["covered"][cband == k].mean())
        rows[-1].update(r.get("shape", {}))
    return rows


def plot(res: dict, frames: list[int], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = [f for f in frames if f in res["frames"]]
    fig, axs = plt.subplots(1, len(frames), figsize=(4.2 * len(frames), 4.6), squeeze=False)
    sc = None
    for ax, f in zip(axs[0], frames):
        r = res["frames"][f]
        cloth, x, d, on = r["cloth"], r["x"], r["d"], res["garment"]
        top = cloth[:, 1].max()
        ring = cloth[cloth[:, 1] > top - 0.02]  # the waist ring: the cloth's top 2 cm
        c = ring.mean(0)
        def rad(p: np.ndarray, c: np.ndarray = c) -> np.ndarray:  # horizontal distance from the centre (y is up)
            return np.linalg.norm((p - c)[:, [0, 2]], axis=1)

        near = d < 0.15
        sub = cloth[:: max(1, len(cloth) // 3000)]  # drawn first: the Gaussians go on top
        ax.scatter(rad(sub), sub[:, 1] - c[1], s=1, c="0.75", label="cloth")
        ax.scatter(rad(x[near & ~on]), x[near & ~on, 1] - c[1], s=2, c="tab:orange", alpha=0.4, label="other Gaussians")
        sc = ax.scatter(rad(x[near & on]), x[near & on, 1] - c[1], s=2, c=d[near & on] * 100, cmap="viridis", vmin=0,
                        vmax=8, alpha=0.7)
        ax.set_title(f"frame {f} ({r['phase']})")
        ax.set_xlabel("radius from the waist's centre (m)")
        ax.set_xlim(0, 0.75)
        ax.set_ylim(-0.7, 0.1)
        ax.set_aspect("equal")
    axs[0][0].set_ylabel("height below the waist (m)")
    axs[0][0].legend(loc="lower left", markerscale=4, fontsize=8)
    fig.suptitle(title)
    if sc is not None:
        fig.colorbar(sc, ax=axs[0].tolist(), label="garment Gaussian's distance to the cloth (cm)")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--labels", default=None, help="comma-separated, one per run (default: folder names)")
    ap.add_argument("--frames", default="10,28,32,36", help="frames of the section plots")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    labels = a.labels.split(",") if a.labels else [p.name for p in a.runs]
    if len(labels) != len(a.runs):
        ap.error(f"--labels: {len(labels)} labels for {len(a.runs)} runs")
    a.out.mkdir(parents=True, exist_ok=True)
    frames = [int(f) for f in a.frames.split(",")]
    rows = []
    for run, label in zip(a.runs, labels):
        res = section(run, a.threads)
        rows += [{"run": label, **r} for r in table(res)]
        plot(res, frames, f"{label}: garment Gaussians against the simulated cloth", a.out / f"section_{label}.png")
    with open(a.out / "section.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    keys = ("dist_cm", "abs_du_cells", "abs_dv_cells", "dv_cells", "cover", "cover4", "cloth_up")
    if all("light_up" in r for r in rows):
        keys += ("light_up", "light_cos", "light_ratio")
    if all("sheet_up" in r for r in rows):
        keys += ("sheet_up", "sheet_lap_cm", "sheet_zigzag")
    print("run | phase | " + " | ".join(keys) + "  (medians over the phase's frames)")
    for label in labels:
        for ph in ("rest", "spin", "after", "settled"):
            sel = [r for r in rows if r["run"] == label and r["phase"] == ph]
            if sel:
                print(f"{label} | {ph} | " + " | ".join(f"{np.mean([r[k] for r in sel]):.2f}" for k in keys))
    print(f"wrote {a.out}/section.csv and section_<label>.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
