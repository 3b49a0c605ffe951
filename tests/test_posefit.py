"""posefit=silhouette: the pose path's own steps on other training frames' silhouettes (model/posefit.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.model.posefit import NoPoseFit, SilhouettePoseFit


def _ci_module(extra: list[str]):
    from realityavatar.build import build_data, build_module

    cfg = compose(["data=synthetic_ci", "trainer=ci", "gaussians.num_points=300", "sheet=skirt", "sheet.rows=4",
                   "sheet.cols=12", "sheet.per_cell=1", "sheet.basis=4", "posefit=silhouette", *extra])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    module = build_module(cfg, body, dm.num_train_frames, dm.scene_extent, data=dm)
    module.sheet.canonicalise(body, module.skinning)
    return cfg, dm, module


def test_posefit_is_off_by_default_composes_and_refuses_bad_values():
    assert isinstance(instantiate(compose([]).posefit), NoPoseFit)
    pf = instantiate(compose(["posefit=silhouette"]).posefit)
    assert isinstance(pf, SilhouettePoseFit) and pf.passes == 2 and pf.optimizer == "own"
    for bad, field in (({"frames": 0}, "posefit.frames"), ({"passes": 1.5}, "posefit.passes"),
                       ({"weight": -1.0}, "posefit.weight"), ({"groups": ["means"]}, "posefit.groups"),
                       ({"optimizer": "sgd"}, "posefit.optimizer"), ({"cover": "body"}, "posefit.cover")):
        with pytest.raises(ValueError, match=field):
            SilhouettePoseFit(**bad)


def test_deform_points_is_deforms_geometry_for_the_free_gaussians_and_the_sheet(scenes_root):
    """The posefit pass's cheap geometry path gives the same posed centres as the full `deform` (the free
    Gaussians picked, then the sheet's vertices), the sheet's motion basis included."""
    _, dm, module = _ci_module([])
    with torch.no_grad():
        module.sheet.basis.normal_(0.0, 0.05)  # a motion basis that moves the vertices
        for p in list(module.deformer.parameters()) + list(module.sheet.coeff.parameters()):
            p.add_(0.01 * torch.randn_like(p))
    ds = dm.datasets["train"]
    batch = torch.utils.data.default_collate([ds[0], ds[len(ds) // 2]])  # at rest, mid-sequence
    idx = torch.tensor([3, 0, 250, 17])
    with torch.no_grad():
        full = module.deform(batch["poses"], batch["transl"])
        pts = module.deform_points(batch["poses"], batch["transl"], idx)
    assert pts.shape == (2, 4 + module.sheet.vertices.shape[0], 3)
    assert torch.allclose(pts[:, :4], full["means"][:, idx], atol=1e-5)
    assert torch.allclose(pts[:, 4:], full["sheet_verts"], atol=1e-5)
    assert float((pts[0, 4:] - pts[1, 4:]).abs().max()) > 1e-3  # two frames, two garment shapes


@pytest.mark.parametrize("optimizer", ["own", "shared"])
def test_posefit_steps_move_only_the_pose_path_and_lower_its_silhouette_loss(scenes_root, optimizer):
    _, dm, module = _ci_module(["posefit.passes=40", "posefit.frames=6", f"posefit.optimizer={optimizer}"])
    pf = module.posefit
    record = pf.build(dm)
    assert record["frames"] == dm.num_train_frames and record["images"] == len(dm.datasets["train"])
    opt = torch.optim.Adam(module.param_groups(), eps=1e-15)
    frozen = {n: p.detach().clone() for n, p in module.named_parameters()
              if not n.startswith(("encoder.", "temporal.", "deformer.", "sheet.basis", "sheet.coeff"))}
    moving = {n: p.detach().clone() for n, p in module.named_parameters()
              if n.startswith(("encoder.", "deformer.", "sheet.basis"))}
    torch.manual_seed(0)
    with torch.no_grad():
        before = float(sum(pf.loss(module, 1000, k)[0] for k in range(4)))
    pf.step(module, opt, step=0)
    with torch.no_grad():
        after = float(sum(pf.loss(module, 1000, k)[0] for k in range(4)))
    assert after < 0.8 * before, (before, after)
    changed = [n for n, v in frozen.items() if not torch.equal(v, dict(module.named_parameters())[n])]
    assert not changed, f"posefit moved parameters outside the pose path: {changed[:5]}"
    assert all(not torch.equal(v, dict(module.named_parameters())[n]) for n, v in moving.items())
    assert all(p.grad is None for p in module.parameters())  # nothing left for the next image step
    # the frames drawn depend only on the seed, the step and the pass (a resumed run draws the same)
    again = SilhouettePoseFit(seed=pf.seed, frames=pf.frames)
    again.bank = pf.bank
    assert again.draw(123, 1)[0] == pf.draw(123, 1)[0] and pf.draw(123, 1)[0] != pf.draw(124, 1)[0]


def test_posefit_trains_end_to_end_without_advancing_the_trainers_steps(scenes_root, tmp_path):
    """The extra pose-path steps go to the optimizer itself: the run still makes `iterations` image steps (through
    Lightning's optimizer each would count as a training step and end the run early)."""
    from realityavatar.config import prepare_run
    from realityavatar.train import run

    cfg, choices = prepare_run(compose(["data=synthetic_ci", "trainer=ci", "iterations=12", "gaussians.num_points=300",
                                        "posefit=silhouette", "posefit.frames=2", "posefit.free_points=64",
                                        "eval.max_frames_per_split=1", "eval.save_video=false",
                                        "eval.save_images=0"]), tmp_path / "run")
    run(cfg, choices)
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert np.isfinite(m["test/novel_view/psnr"])
    ckpt = torch.load(tmp_path / "run" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 12
    rows = (tmp_path / "run" / "logs" / "csv" / "metrics.csv").read_text()
    assert "train/posefit_outside" in rows.splitlines()[0]


def test_garment_cover_keeps_the_mask_pixels_the_simulated_cloth_explains(scenes_root):
    """posefit.cover=garment: the pixels left to the garment sheet (farther than body_margin_px from the posed
    body) lie on the simulated cloth's projection, and a flaring frame leaves more of them than the first frame."""
    from realityavatar.build import build_data
    from realityavatar.losses import nearest_index, project_points

    cfg = compose(["data=synthetic_ci", "posefit=silhouette", "posefit.cover=garment"])
    body = instantiate(cfg.body)
    dm = build_data(cfg, body)
    pf = instantiate(cfg.posefit)
    pf.build(dm)
    g = np.load(scenes_root / f"{cfg.data.sequence}-garment.npz")
    frames = {int(f): i for i, f in enumerate(g["frames"])}
    V, faces = torch.from_numpy(g["vertices"]).float(), torch.from_numpy(g["faces"]).long()
    bary = torch.distributions.Dirichlet(torch.ones(3)).sample((40,))  # 40 points per triangle
    near, counts = [], []
    for b in pf.bank:
        tri = V[frames[b["frame"]]][faces]  # [F,3,3]
        cloth = torch.einsum("sk,fkd->fsd", bary, tri).reshape(-1, 3)
        n = 0
        for v in b["views"]:
            pix = v["pix"].float()
            n += len(pix)
            if len(pix):
                uv, _ = project_points(cloth, v["viewmat"], v["K"])
                near.append((uv[nearest_index(pix, uv)] - pix).norm(dim=-1))
        counts.append(n)
    d = torch.cat(near)
    assert len(d) > 50 and float((d < 1.5).float().mean()) > 0.95, float((d < 1.5).float().mean())
    assert max(counts) > 2 * counts[0]
