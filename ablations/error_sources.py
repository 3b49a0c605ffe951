"""Where a trained run's held-out error comes from, per phase of a synthetic scene: light, texture or silhouette.

Usage: python ablations/error_sources.py <run_dir> --out <folder> [--unlit-root <dir>]
       python ablations/error_sources.py <run trained on the albedo-only scene> --out <folder> --lit-oracle <dir>

For every held-out (novel-view) image of the run's training frames it renders the model and measures:
- psnr: the model as it is;
- psnr_true_light: the model's albedo (colour / E) times the scene's true shading (lit image / albedo-only image of
  the same camera and frame, scaled by the global ratio of the two E's), inside the mask where the model is opaque;
- psnr_true_albedo: the scene's true albedo times the model's E (same pixels, same scale);
- psnr_unshaded: the model's error with each of those pixels' error divided by the scene's true shading there
  (relative to its mean over all those pixels): the error a phase would have if its garment were lit as brightly as
  on average, so phases compare without the light's change of brightness (a flared skirt faces the light);
- light_corr, light_err: how well the model's light matches the scene's per pixel (the same pixels): the correlation
  of E (grey) with the true shading, and the median |log| of their ratio after the global scale (for comparison,
  light_err_flat is that of a constant E, the image's mean true shading);
- light_map_corr, light_map_deg (once per run): the model's irradiance map E(n) against the scene's Lambert light
  ambient + diffuse max(0, n.l) over 20,000 random directions: their correlation, and the angle between the
  brightest direction of the map and the light's;
- the squared error's share by region (x1e4 of the image's mean): interior (mask, alpha > 0.9), edge (mask, alpha
  0.1-0.9), missed (mask, alpha <= 0.1), extra (outside the mask, alpha > 0.1), background (the rest); they sum to
  mse_total;
- blur_<s>: the ground truth against itself blurred by a Gaussian of s px, a model-free measure of how much detail
  each phase's images hold (a renderer of fixed sharpness loses more where there is more).
The albedo-only scene is built once under --unlit-root with the run's scene parameters and ambient=1, diffuse=0.
Needs a run with shading=irradiance (the light and albedo columns), a synthetic scene and its motion events.
Writes error_sources.json (phase means) and prints a table.

--lit-oracle <dir>: the run was trained on the albedo-only scene (`data.root=<albedo root>
'+data.build_overrides={ambient: 1.0, diffuse: 0.0}'`); its renders are multiplied by the scene's exact shading
(lit image / albedo-only image, per pixel; `true_shading`) and compared with the lit scene, built under <dir> with
the run's scene parameters and the default light. That is what a model with a perfect light model would score on
the lit scene, per phase (psnr, and the squared error by region as above); psnr_albedo is the run on its own
scene. Writes lit_oracle.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from torch.utils.data import default_collate

from realityavatar.build import build_data, load_run
from realityavatar.metrics import psnr

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ablations.probe import phase_of  # noqa: E402

BLUR_PX = (0.75, 1.0, 1.5, 2.0)


def blur(img: torch.Tensor, s: float) -> torch.Tensor:
    """Separable Gaussian blur of an [H,W,C] image (replicated borders)."""
    r = int(3 * s) + 1
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-x**2 / (2 * s * s))
    k = k / k.sum()
    im = img.permute(2, 0, 1)[:, None]
    im = F.conv2d(F.pad(im, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    im = F.conv2d(F.pad(im, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return im[:, 0].permute(1, 2, 0)


def regions(m: torch.Tensor, a: torch.Tensor) -> dict[str, torch.Tensor]:
    """The image's pixels by the mask m [H,W] and the model's alpha a [H,W]: interior, edge, missed, extra, background."""
    return dict(interior=m & (a > 0.9), edge=m & (a > 0.1) & (a <= 0.9), missed=m & (a <= 0.1),
                extra=~m & (a > 0.1), background=~m & (a <= 0.1))


def phase_means(per: dict[str, list[dict]]) -> dict[str, dict]:
    """Per phase: the number of images and the mean of every column of their rows."""
    return {ph: {"images": len(rows), **{k: float(np.mean([x[k] for x in rows])) for k in rows[0]}}
            for ph, rows in per.items()}


def unshade(err: torch.Tensor, sel: torch.Tensor, e_true: torch.Tensor, e_mean: float) -> torch.Tensor:
    """err [H,W,3] with each selected pixel's (sel [H,W]) error divided by its true shading relative to e_mean
    (e_true [H,W,3]; at most a 5x gain where the light is dim); other pixels as they are."""
    out = err.clone()
    out[sel] = err[sel] / (e_true[sel] / e_mean).clamp_min(0.2)
    return out


@torch.no_grad()
def true_shading(lit: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor, dark: float = 0.08) -> torch.Tensor:
    """The scene's shading per pixel [H,W,3]: lit / albedo inside the mask where the albedo is not dark (mean >
    `dark`); elsewhere (background, dark albedo) the median of those pixels, so a model's extra pixels are lit as
    the garment is on average."""
    ok = mask & (albedo.mean(-1) > dark)
    fill = float((lit[ok] / albedo[ok]).median()) if ok.any() else 1.0
    S = torch.full_like(lit, fill)
    S[ok] = lit[ok] / albedo[ok]
    return S


@torch.no_grad()
def light_map(shading, params: dict, n: int = 20_000) -> dict:
    """The model's irradiance map against the scene's light (render.LIGHT_DIR, the scene's ambient and diffuse)."""
    from realityavatar.data.synthetic.render import AMBIENT, DIFFUSE, LIGHT_DIR

    dirs = F.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    em = shading.irradiance(dirs.to(shading.coeffs)).mean(-1).double()
    light = torch.as_tensor(LIGHT_DIR, dtype=torch.float64)
    et = params.get("ambient", AMBIENT) + params.get("diffuse", DIFFUSE) * (dirs.double() @ light).clamp_min(0)
    cos = float(dirs[em.argmax()].double() @ light)
    return {"light_map_corr": float(torch.corrcoef(torch.stack([em, et]))[0, 1]),
            "light_map_deg": float(torch.rad2deg(torch.arccos(torch.tensor(min(1.0, cos)))))}


@torch.no_grad()
def lit_oracle(run: Path, lit_root: Path, threads: int = 1) -> dict:
    """A run trained on the albedo-only scene, its renders times the exact shading, against the lit scene."""
    torch.set_num_threads(threads)
    cfg, module, _ = load_run(run)
    bo = dict(cfg.data.get("build_overrides") or {})
    if bo.get("ambient") != 1.0 or bo.get("diffuse") != 0.0:
        raise ValueError(f"{run}: --lit-oracle needs a run trained on the albedo-only scene (data.build_overrides "
                         f"ambient=1.0, diffuse=0.0), got data.build_overrides={bo}")
    dm = build_data(cfg, module.body)
    lit_bo = {k: v for k, v in bo.items() if k not in ("ambient", "diffuse")}
    cfg_l = OmegaConf.merge(cfg, {"data": {"root": str(lit_root)}})
    cfg_l.data.build_overrides = lit_bo or None
    dm_l = build_data(cfg_l, module.body)
    meta = dm_l.scene.meta or {}
    events, fps = meta.get("motion", {}).get("events", {}), float(meta.get("fps", 25.0))
    ds, ds_l = dm.datasets["novel_view"], dm_l.datasets["novel_view"]
    per: dict[str, list[dict]] = {}
    for i, rec in enumerate(ds_l.records):
        b, bl = default_collate([ds[i]]), default_collate([ds_l[i]])
        posed = module.deform(b["poses"], b["transl"])
        W, H = int(b["width"][0]), int(b["height"][0])
        rgb = module.shade(posed, b["viewmat"], b["frame_idx"])[0]
        img, a, _ = module.splat(posed, 0, rgb, b["viewmat"], b["K"], W, H)
        img, a = img[0].clamp(0, 1), a[0, ..., 0]
        gt, albedo, m = bl["image"][0], b["image"][0], bl["mask"][0, ..., 0] > 0.5
        lit = img * true_shading(gt, albedo, m)
        se = ((lit - gt) ** 2).mean(-1)
        per.setdefault(phase_of(int(rec.frame), events, fps), []).append(dict(
            psnr=float(psnr(lit, gt)), psnr_albedo=float(psnr(img, albedo)), mse_total=float(se.mean() * 1e4),
            **{f"mse_{k}": float(se[v].sum() / se.numel() * 1e4) for k, v in regions(m, a).items()}))
    return {"run": str(run), "lit_root": str(lit_root), "phases": phase_means(per)}


@torch.no_grad()
def error_sources(run: Path, unlit_root: Path, threads: int = 1) -> dict:
    torch.set_num_threads(threads)
    cfg, module, _ = load_run(run)
    if type(module.shading).__name__ != "IrradianceShading":
        raise ValueError(f"{run}: needs a run trained with shading=irradiance, got {type(module.shading).__name__}")
    dm = build_data(cfg, module.body)
    # The same scene without its light, under its own root (the run's config with two data keys changed).
    cfg_u = OmegaConf.merge(cfg, {"data": {"root": str(unlit_root), "build_overrides": {"ambient": 1.0, "diffuse": 0.0}}})
    dm_u = build_data(cfg_u, module.body)
    meta = dm.scene.meta or {}
    events = meta.get("motion", {}).get("events", {})
    fps = float(meta.get("fps", 25.0))
    ds, ds_u = dm.datasets["novel_view"], dm_u.datasets["novel_view"]
    raw = []
    for i, rec in enumerate(ds.records):
        b, bu = default_collate([ds[i]]), default_collate([ds_u[i]])
        posed = module.deform(b["poses"], b["transl"])
        W, H = int(b["width"][0]), int(b["height"][0])
        rgb = module.shade(posed, b["viewmat"], b["frame_idx"])[0]
        light = module.shading(posed["x_e"], posed["rot"], posed.get("n_c"))[0]
        img, a, _ = module.splat(posed, 0, rgb, b["viewmat"], b["K"], W, H)
        e_img, _, _ = module.splat(posed, 0, light, b["viewmat"], b["K"], W, H)
        base, _, _ = module.splat(posed, 0, rgb / light, b["viewmat"], b["K"], W, H)
        a = a[0, ..., 0]
        gt, albedo, m = b["image"][0], bu["image"][0], b["mask"][0, ..., 0] > 0.5
        sel = m & (a > 0.9) & (albedo.mean(-1) > 0.08)
        raw.append(dict(phase=phase_of(int(rec.frame), events, fps), img=img[0], a=a, m=m, base=base[0], gt=gt,
                        albedo=albedo, sel=sel, e_model=e_img[0] / a[..., None].clamp_min(1e-3),
                        e_true=gt / albedo.clamp_min(1e-3)))
    # E and albedo share a global scale: match the model's E to the true one over all selected pixels.
    e_true_sum = sum(float(r["e_true"][r["sel"]].sum()) for r in raw)
    scale = e_true_sum / sum(float(r["e_model"][r["sel"]].sum()) for r in raw)
    # The true shading's mean over the same pixels: psnr_unshaded divides each pixel's error by its shading relative
    # to this mean, so a phase whose garment is brighter (a flared skirt tilted towards the light) is not
    # penalised for its larger absolute errors.
    e_mean = e_true_sum / sum(3 * int(r["sel"].sum()) for r in raw)
    per: dict[str, list[dict]] = {}
    for r in raw:
        img, gt, sel, a, m = r["img"].clamp(0, 1), r["gt"], r["sel"], r["a"], r["m"]
        light_fix, albedo_fix = img.clone(), img.clone()
        light_fix[sel] = r["base"][sel] * r["e_true"][sel] / scale
        albedo_fix[sel] = r["albedo"][sel] * r["e_model"][sel] * scale
        se = ((img - gt) ** 2).mean(-1)
        err_u = unshade(img - gt, sel, r["e_true"], e_mean)
        et, em = r["e_true"][sel].mean(-1), r["e_model"][sel].mean(-1) * scale
        light = dict(light_corr=float(torch.corrcoef(torch.stack([em, et]))[0, 1]) if len(et) > 1 else float("nan"),
                     light_err=float((em / et).log().abs().median()) if len(et) else float("nan"),
                     light_err_flat=float((et.mean() / et).log().abs().median()) if len(et) else float("nan"))
        row = dict(**light, psnr=float(psnr(img, gt)), psnr_true_light=float(psnr(light_fix.clamp(0, 1), gt)),
                   psnr_true_albedo=float(psnr(albedo_fix.clamp(0, 1), gt)),
                   psnr_unshaded=float(-10 * torch.log10(err_u.square().mean())),
                   mse_total=float(se.mean() * 1e4),
                   **{f"mse_{k}": float(se[v].sum() / se.numel() * 1e4) for k, v in regions(m, a).items()},
                   **{f"blur_{s}": float(psnr(blur(gt, s), gt)) for s in BLUR_PX})
        per.setdefault(r["phase"], []).append(row)
    return {"run": str(run), "e_scale": scale, **light_map(module.shading, meta.get("params", {})),
            "phases": phase_means(per)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--out", required=True)
    ap.add_argument("--unlit-root", default="scenes_unlit", help="where the albedo-only scene is built (once)")
    ap.add_argument("--lit-oracle", metavar="DIR", help="the run was trained on the albedo-only scene: its renders "
                    "times the exact shading against the lit scene built under DIR (writes lit_oracle.json)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.lit_oracle:
        res = lit_oracle(Path(a.run), Path(a.lit_oracle), a.threads)
        out.mkdir(parents=True, exist_ok=True)
        (out / "lit_oracle.json").write_text(json.dumps(res, indent=2))
        cols = ["psnr", "psnr_albedo", "mse_interior", "mse_edge", "mse_missed", "mse_extra"]
        print(f"{'phase':<9}{'n':>4}" + "".join(f"{c:>14}" for c in cols))
        for ph, v in res["phases"].items():
            print(f"{ph:<9}{v['images']:>4}" + "".join(f"{v[c]:14.3f}" for c in cols))
        print(f"wrote {out}/lit_oracle.json")
        return 0
    res = error_sources(Path(a.run), Path(a.unlit_root), a.threads)
    out.mkdir(parents=True, exist_ok=True)
    (out / "error_sources.json").write_text(json.dumps(res, indent=2))
    cols = ["psnr", "psnr_true_light", "psnr_true_albedo", "psnr_unshaded", "light_corr", "light_err", "mse_interior", "mse_edge", "mse_missed",
            "mse_extra", *[f"blur_{s}" for s in BLUR_PX]]
    print(f"{'phase':<9}{'n':>4}" + "".join(f"{c:>17}" for c in cols))
    for ph in ("rest", "spin", "after", "settled", "all"):
        if ph in res["phases"]:
            v = res["phases"][ph]
            print(f"{ph:<9}{v['images']:>4}" + "".join(f"{v[c]:17.3f}" for c in cols))
    print(f"light map against the scene's light: correlation {res['light_map_corr']:.3f}, brightest direction "
          f"{res['light_map_deg']:.1f} deg off")
    print(f"wrote {out}/error_sources.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
