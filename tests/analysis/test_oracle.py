"""oracle: Gaussians glued to a synthetic scene's true meshes, fitted and scored as a training run is."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import realityavatar.config  # noqa: F401  registers the resolvers the real tree's configs use


def _oracle(out, steps: int, *overrides: str) -> dict:
    from realityavatar.analysis.oracle import main

    assert main(["--data", "synthetic_ci", "--steps", str(steps), "--body", "2000", "--garment", "2000",
                 "--out", str(out), *overrides]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_oracle_fit_writes_garment_metrics_per_phase_and_beats_unfitted(scenes_root, tmp_path):
    """A 30-step fit on the ci scene (64 px) writes a training run's key layout, the garment's scores in every
    phase of both held-out splits (the garment file covers the novel-pose frames too), and scores better than the
    same Gaussians unfitted, on the whole image and on the garment's pixels."""
    fitted, unfitted = _oracle(tmp_path / "fit", 30), _oracle(tmp_path / "unfit", 0)
    for split, phases in (("novel_view", ("rest", "spin", "after")), ("novel_pose", ("rest", "spin"))):
        for ph in phases:
            for k in ("psnr", "psnr_masked", "psnr_garment", "ssim_garment", "flip_garment", "detail_garment"):
                assert np.isfinite(fitted[f"test/{split}/{ph}/{k}"]), (split, ph, k)
    assert fitted["num_gaussians"] == 4000 and fitted["iterations"] == 30
    assert (tmp_path / "fit" / "per_frame.csv").is_file() and (tmp_path / "fit" / "phases.png").is_file()
    for k in ("psnr", "psnr_garment", "ssim_garment"):
        assert fitted[f"test/novel_view/{k}"] > unfitted[f"test/novel_view/{k}"] + 0.5 * (k != "ssim_garment"), k
    assert fitted["test/novel_view/flip_garment"] < unfitted["test/novel_view/flip_garment"]


def test_oracle_renders_with_the_runs_render_options(scenes_root, tmp_path):
    """The glued Gaussians are rasterized with the config's `render` options, as a trained model is: a wider 2-D
    filter (`+render.eps2d`) blurs the same unfitted Gaussians, so less of the ground truth's detail is kept."""
    sharp = _oracle(tmp_path / "sharp", 0, "+render.eps2d=0.1")
    wide = _oracle(tmp_path / "wide", 0, "+render.eps2d=3.0")
    assert wide["test/novel_view/detail_masked"] < 0.8 * sharp["test/novel_view/detail_masked"]


def _tube(T: int = 3, around: int = 8, rings: int = 5):
    """A garment-like tube (cloth.tube_topology's triangles, its uv grid) 0.5 m long whose hem ring opens from
    0.2 m to 0.4 m in the last frame: vertices [T,V,3] (y up, waist at y = 1), faces, uv [V,2]."""
    from realityavatar.data.synthetic.cloth import tube_topology

    _, faces = tube_topology(around, rings)
    u, v = np.meshgrid(np.arange(around + 1) / around, np.linspace(0, 1, rings))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    V = []
    for t in range(T):
        r = 0.2 + (0.2 * uv[:, 1] if t == T - 1 else 0.0)
        a = 2 * np.pi * uv[:, 0]
        V.append(np.stack([r * np.cos(a), 1.0 - 0.5 * uv[:, 1], r * np.sin(a)], -1))
    return torch.as_tensor(np.stack(V)), torch.as_tensor(faces).long(), torch.as_tensor(uv)


def test_oracle_slide_and_light():
    """--slide-cm: with no slide the garment's Gaussians are where the unslid ones are (grid_locate splits the quads
    as the garment's triangles); at peak flare 5 cm moves them ~5 cm towards the waist, at rest not at all.
    --light none: a Gaussian's colour is its albedo; exact: albedo x (ambient + diffuse x max(0, n.l)), the normal
    turned to the camera."""
    from realityavatar.analysis.oracle import GluedGaussians, flare

    V, F, uv = _tube()
    curve = flare(V, 9)
    assert torch.allclose(curve, torch.tensor([0.0, 0.0, 1.0], dtype=curve.dtype))
    light = torch.nn.functional.normalize(torch.tensor([0.3, 0.8, 0.5]), dim=0)

    def model(dv, kind="exact"):
        slide = None if dv is None else (uv, 9, 5, dv)
        return GluedGaussians([(V, F, 500, slide)], torch.Generator().manual_seed(0), kind, 0.4, 0.6, light)

    glued, still, slid = model(None), model(torch.zeros(3)), model(-0.05 / 0.5 * curve)
    assert torch.allclose(glued.pos, still.pos, atol=1e-6)
    moved = (slid.pos - glued.pos).norm(dim=-1)  # [T,N]
    assert moved[:2].max() < 1e-6
    # 5 cm of the 50 cm rest length is a tenth of v: a tenth of the flared tube's 53.9 cm from waist to hem
    assert abs(float(moved[2].median()) - 0.1 * np.hypot(0.5, 0.2)) < 0.005
    assert (slid.pos[2, :, 1] >= glued.pos[2, :, 1] - 1e-6).all()  # towards the waist (up)
    with torch.no_grad():
        glued.albedo.normal_(generator=torch.Generator().manual_seed(1))
        unlit = model(None, "none")
        unlit.albedo.copy_(glued.albedo)
    eye = torch.tensor([0.0, 1.0, 3.0])
    x, _, _, _, rgb = glued.at(2, eye)  # the flared frame: normals tilted towards and away from the light
    n = glued.nrm[2]
    facing = torch.where(((x - eye) * n).sum(-1, keepdim=True) > 0, -n, n)
    shade = 0.4 + 0.6 * (facing @ light).clamp_min(0)
    assert shade.min() < 0.45 and shade.max() > 0.6
    assert torch.allclose(rgb, torch.sigmoid(glued.albedo) * shade[:, None])
    assert torch.allclose(unlit.at(2, eye)[4], torch.sigmoid(glued.albedo))


def test_oracle_pose_drape_maps_equal_windows_to_the_earliest_frame():
    """--drape pose: a training frame whose pose window equals an earlier frame's shows that frame's cloth (the rest
    and the settled frames of a spin at one pose); a frame whose window still holds the spin, or any frame the
    training split lacks (the novel-pose sequence), keeps its own."""
    from types import SimpleNamespace

    from realityavatar.analysis.oracle import pose_driven_rows
    from realityavatar.data.poses import PoseTable

    F = 14
    poses = torch.zeros(F, 24, 3)
    poses[4:7, 0, 1] = torch.tensor([1.0, 2.0, 3.0])  # the root turns in frames 4-6, then stands as at rest
    table = PoseTable(list(range(F)), poses, torch.zeros(F, 3))
    train = [SimpleNamespace(frame=f) for f in range(12) for _ in range(2)]  # frames 12, 13: another split's
    dm = SimpleNamespace(scene=SimpleNamespace(poses=table), window_len=3, window_step=2,
                         datasets={"train": SimpleNamespace(records=train)})
    frames = list(range(F))
    rows = pose_driven_rows(dm, frames)
    # windows (t-4, t-2, t): frames 0-3 read rest only; 4-10 hold the turn; 11 reads 7, 9, 11: rest again
    assert rows == [0, 0, 0, 0, 4, 5, 6, 7, 8, 9, 10, 0, 12, 13]


def test_cloth_of_reads_a_physics_runs_simulated_cloth(tmp_path):
    """--cloth-of: the track of a sheet=physics checkpoint at the scene's frames; other folders are named."""

    from realityavatar.analysis.oracle import run_cloth

    track = torch.randn(6, 5, 3)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4]])
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"state_dict": {"avatar.sheet.track": track, "avatar.sheet.faces": faces,
                               "avatar.sheet.track_frames": torch.arange(10, 16)}}, run / "last.ckpt")
    V, F = run_cloth(run, [11, 12, 15])
    assert torch.equal(V, track[[1, 2, 5]].double()) and torch.equal(F, faces)
    with pytest.raises(ValueError, match="covers frames 10..15"):
        run_cloth(run, [9, 10])
    torch.save({"state_dict": {}}, run / "last.ckpt")
    with pytest.raises(ValueError, match="not a sheet=physics run"):
        run_cloth(run, [11])
    with pytest.raises(FileNotFoundError, match="--cloth-of"):
        run_cloth(tmp_path / "none", [11])
