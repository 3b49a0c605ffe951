"""The avatar's outputs (model/avatar.py): rendered batches, animation frames, posed Gaussians with their colour baked,
and a trained avatar loaded without the Lightning module."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from realityavatar.config import compose
from tests.helpers import ROOT, random_poses

S = 48  # image size


@pytest.fixture(scope="module")
def avatar():
    """A float64 avatar of 400 Gaussians with the light on (irradiance over the body's normals); colour features, decoder
    output, light coefficients and frame latents drawn away from their initial values, so colour depends on view,
    place and frame."""
    from realityavatar.body import build_body
    from realityavatar.build import build_avatar

    body = build_body("mannequin")
    torch.manual_seed(0)
    a = build_avatar(compose(["gaussians.num_points=400", "shading=irradiance"]), body, num_train_frames=3).double()
    a.shading.init_from_body(body.canonical_vertices().double(), body.faces)
    with torch.no_grad():
        a.gaussians.features.normal_(0, 0.5)
        a.shading.coeffs.normal_(0, 0.2)
        a.deformer.out.weight.normal_(0, 0.01)
        a.color.frame_latents.weight.normal_(0, 1.0)  # Z_r: each training frame's light, apart from their mean
    return a.eval()


def camera(at: torch.Tensor, distance: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """viewmat [4,4] of an OpenCV camera `distance` m in front of point `at` (+z side, looking back), K [3,3]."""
    R = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    E = torch.eye(4, dtype=torch.float64)
    E[:3, :3], E[:3, 3] = R, -R @ (at + torch.tensor([0.0, 0.0, distance], dtype=torch.float64))
    return E, torch.tensor([[50.0, 0, S / 2], [0, 50.0, S / 2], [0, 0, 1]], dtype=torch.float64)


def batch_of(avatar, poses, transl, frame_idx) -> dict:
    """A batch as the dataset makes one: pose inputs, frame indices and one camera per sample in front of its body."""
    inputs = avatar.pose_inputs(poses.double(), transl.double())
    cams = [camera(t[-1].double()) for t in transl]
    return {**inputs, "frame_idx": torch.as_tensor(frame_idx), "viewmat": torch.stack([c[0] for c in cams]),
            "K": torch.stack([c[1] for c in cams]), "width": torch.tensor([S] * len(cams)),
            "height": torch.tensor([S] * len(cams))}


@torch.no_grad()
def test_render_batch_renders_each_sample_as_alone(avatar):
    """render_batch: rgb [B,H,W,3], alpha [B,H,W,1], one rasterizer meta per sample, the posed Gaussians [B,N,...];
    each sample is the image it renders alone (its own pose, camera and frame latent), and the body is in view."""
    poses, transl = random_poses(B=2, T=4, seed=3)
    batch = batch_of(avatar, poses, transl, [0, 2])
    rgb, alpha, metas, posed = avatar.render_batch(batch)
    N = avatar.gaussians.num_points
    assert rgb.shape == (2, S, S, 3) and alpha.shape == (2, S, S, 1) and len(metas) == 2
    assert posed["B"] == 2 and posed["means"].shape == (2, N, 3) and posed["opacities"].shape == (N,)
    assert all(float(alpha[b].amax()) > 0.5 for b in range(2))  # each body in its camera's view
    assert (rgb[0] - rgb[1]).abs().amax() > 0.05  # two poses, two images
    for b in range(2):
        one = {k: v[b : b + 1] for k, v in batch.items()}
        rgb1, alpha1, _, _ = avatar.render_batch(one)
        torch.testing.assert_close(rgb1[0], rgb[b], rtol=0, atol=1e-12)
        torch.testing.assert_close(alpha1[0], alpha[b], rtol=0, atol=1e-12)


@torch.no_grad()
def test_an_animation_frame_is_render_batch_without_a_frame_latent(avatar):
    """render_view (realityavatar-animate's frames) of one pose window is render_batch's image of the same pose and
    camera at frame -1 (no training frame's colour latent), and differs from a training frame's."""
    poses, transl = random_poses(B=1, T=4, seed=5)
    vm, K = camera(transl[0, -1].double())
    img = avatar.render_view(avatar.posed(poses[0], transl[0]), vm, K, S, S)
    ref = avatar.render_batch(batch_of(avatar, poses, transl, [-1]))[0][0]
    assert img.shape == (S, S, 3)
    torch.testing.assert_close(img, ref, rtol=0, atol=1e-12)
    framed = avatar.render_batch(batch_of(avatar, poses, transl, [1]))[0][0]
    assert (framed - img).abs().amax() > 1e-3


@torch.no_grad()
def test_baked_colour_is_shades_averaged_over_the_six_axis_directions(avatar):
    """Avatar.baked (export's PLY, the viewer's splats): the posed Gaussians of the pose window, each coloured with
    the mean of what `shade` gives it when seen along +-x, +-y, +-z (cameras 1e9 m away), lit, clamped to [0,1]."""
    from realityavatar.model.avatar import AXES, views_of

    poses, transl = random_poses(B=1, T=4, seed=6)
    baked = avatar.baked(poses[0], transl[0])
    posed = avatar.posed(poses[0], transl[0])
    for k in ("means", "quats", "scales"):
        torch.testing.assert_close(baked[k], posed[k][0], rtol=0, atol=0)
    torch.testing.assert_close(baked["opacities"], posed["opacities"], rtol=0, atol=0)
    viewmats = torch.eye(4, dtype=torch.float64).repeat(len(AXES), 1, 1)
    viewmats[:, :3, 3] = 1e9 * torch.tensor(AXES, dtype=torch.float64)  # R = I: centre -t, the view direction +d
    seen = avatar.shade(views_of(posed, len(AXES)), viewmats, torch.full((len(AXES),), -1))  # [6,N,3]
    assert (seen.amax(0) - seen.amin(0)).amax() > 0.01  # the colour depends on the view: the average means something
    torch.testing.assert_close(baked["rgb"], seen.mean(0).clamp(0, 1), rtol=0, atol=1e-7)
    can = avatar.baked()  # canonical: the Gaussians where they rest
    ref = avatar.canonical_gaussians()
    assert all(torch.equal(can[k], ref[k]) for k in ref) and can["rgb"].shape == ref["means"].shape


def test_export_loads_an_avatar_without_the_lightning_module(trained_run, tmp_path):
    """realityavatar-export (canonical and posed) and load_avatar rebuild the trained Avatar alone: AvatarModule is
    never imported, the PLY holds load_avatar's baked Gaussians, and the avatar equals the module load_run rebuilds
    (weights, and the decoder's coarse-to-fine window where the checkpoint's step had it)."""
    from realityavatar.build import load_avatar, load_run
    from realityavatar.export import gaussians_for_export, read_ply

    out, _ = trained_run
    script = (f"import sys, json; from realityavatar.export import main\n"
              f"assert main(['run_dir={out}', 'out={tmp_path / 'c.ply'}']) == 0\n"
              f"assert main(['run_dir={out}', 'frame=3', 'out={tmp_path / 'p.ply'}']) == 0\n"
              f"print(json.dumps(sorted(m for m in sys.modules if m.startswith('realityavatar.model'))))")
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    imported = json.loads(done.stdout.strip().splitlines()[-1])
    assert "realityavatar.model.avatar" in imported and "realityavatar.model.module" not in imported, imported
    cfg, avatar, _ = load_avatar(out)
    ply, ref = read_ply(tmp_path / "c.ply"), gaussians_for_export(avatar)
    assert ply["means"].shape == ref["means"].shape and abs(ply["means"] - ref["means"]).max() == 0
    _, module, _ = load_run(out)
    mine, theirs = avatar.state_dict(), module.avatar.state_dict()
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    assert not avatar.training
    # a checkpoint of a step halfway through the decoder's coarse-to-fine anneal renders with the bands it had then
    mid = tmp_path / "mid.ckpt"
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=True)
    torch.save({**state, "global_step": cfg.schedule.deform_start + cfg.schedule.deform_anneal // 2}, mid)
    window = load_avatar(out, ckpt=mid)[1].deformer.encoding
    assert 0 < window.alpha < window.num_freqs and window.alpha == load_run(out, ckpt=mid)[1].avatar.deformer.encoding.alpha
