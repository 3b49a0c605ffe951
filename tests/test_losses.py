"""Loss terms (L1/mask/perceptual/skinning, VGG19 vs D-SSIM, the silhouette's chamfer terms)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from realityavatar.config import compose
from realityavatar.data.records import mask_distance
from realityavatar.losses import (
    MaskLoss,
    TrainingRender,
    VGG19PerceptualLoss,
    project_points,
    total_loss,
)
from realityavatar.metrics import (
    vgg_features,
)
from tests.model.configured import component


def _batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(2, 24, 24, 3, generator=g, requires_grad=True)
    alpha = torch.rand(2, 24, 24, 1, generator=g, requires_grad=True)
    gt = torch.rand(2, 24, 24, 3, generator=g)
    mask = (torch.rand(2, 24, 24, 1, generator=g) > 0.5).float()
    return pred, alpha, gt, mask


def _render(pred, alpha, gt, mask, skinning=None):
    from types import SimpleNamespace

    from realityavatar.body import build_body

    avatar = SimpleNamespace(body=build_body("mannequin"), skinning=skinning)
    return TrainingRender(pred, alpha, {"image": gt, "mask": mask}, {}, avatar)


def test_loss_terms_weights_and_schedule():
    """loss=learnt_skinning's terms sum in order with their weights: L1 + 0.1 mask + 0.2 D-SSIM + λ_skin skinning,
    λ_skin 10 before the skinning term's switch step and 0.1 from it on and for a finished run (set_progress, as the
    module calls it before each step). The skinning term refuses a field with nothing to train (the frozen grid)."""
    cfg = compose(["loss=learnt_skinning", "loss.skinning.switch=5", "loss.skinning.samples=32"])
    terms = {name: instantiate(term) for name, term in cfg.loss.items()}
    assert list(terms) == ["rgb", "mask", "perceptual", "skinning"]
    assert terms["perceptual"].kind == "dssim" and terms["perceptual"].weight == 0.2
    pred, alpha, gt, mask = _batch()
    field = component("skinning", "mlp", hidden_dim=16, num_layers=1)
    with pytest.raises(ValueError, match="loss.skinning: .*SkinningGrid has no trained weights"):
        terms["skinning"].bind(_render(pred, alpha, gt, mask, component("skinning", "grid")).avatar)
    with pytest.raises(RuntimeError, match="bind"):
        total_loss(terms, _render(pred, alpha, gt, mask, field))
    for term in terms.values():
        term.bind(_render(pred, alpha, gt, mask, field).avatar)  # as AvatarModule does when it is built
    # the skinning term's pool: 20 x samples points with the body's 24 weights, not saved in checkpoints
    assert terms["skinning"].pool_weights.shape == (640, 24) and not terms["skinning"].state_dict()
    for step, lam in ((4, 10.0), (5, 0.1), (4, 10.0), (None, 0.1)):
        for term in terms.values():
            term.set_progress(step)
        total, logs = total_loss(terms, _render(pred, alpha, gt, mask, field))
        expected = logs["l1"] + 0.1 * logs["mask"] + 0.2 * logs["perceptual"] + lam * logs["skin"]
        assert float(total.detach()) == pytest.approx(float(expected), rel=1e-6)
    assert float(logs["l1"]) == pytest.approx(float((pred - gt).abs().mean()), rel=1e-6)
    assert float(logs["mask"]) == pytest.approx(float(((alpha - mask) ** 2).mean()), rel=1e-6)
    total.backward()
    assert pred.grad.abs().sum() > 0 and alpha.grad.abs().sum() > 0
    assert all(p.grad is not None for p in field.parameters())
    # identical images: no photometric loss; a term that is not in the list is not computed
    t0, logs0 = total_loss({k: terms[k] for k in ("rgb", "mask", "perceptual")}, _render(gt, mask, gt, mask))
    assert float(t0) == pytest.approx(0.0, abs=1e-6) and "skin" not in logs0


def test_perceptual_term_is_vgg19_when_weights_exist(tmp_path):
    feats = vgg_features("vgg19")[:30]
    torch.save({f"features.{k}": v for k, v in feats.state_dict().items()}, tmp_path / "vgg19.pth")
    term = VGG19PerceptualLoss(weight=0.01, vgg19_weights=str(tmp_path / "vgg19.pth"))
    assert term.kind == "vgg19" and term.weight == 0.01
    assert not any(p.requires_grad for p in term.parameters())
    pred, alpha, gt, mask = _batch()
    total, logs = total_loss({"perceptual": term}, _render(pred, alpha, gt, mask))
    assert float(logs["perceptual"]) > 0
    total.backward()
    assert pred.grad.abs().sum() > 0
    _, logs_same = total_loss({"perceptual": term}, _render(gt, mask, gt, mask))
    assert float(logs_same["perceptual"]) == pytest.approx(0.0, abs=1e-6)


def test_loss_terms_bad_options(tmp_path):
    with pytest.raises(FileNotFoundError, match="vgg19_weights"):
        VGG19PerceptualLoss(weight=0.01, vgg19_weights=str(tmp_path / "missing.pth"))
    with pytest.raises(ValueError, match="loss.mask.kind"):
        MaskLoss(weight=0.1, kind="huber")


def _camera(H: int = 32):
    K = torch.tensor([[float(H), 0.0, H / 2], [0.0, float(H), H / 2], [0.0, 0.0, 1.0]])
    E = torch.eye(4)
    E[2, 3] = 2.0  # camera 2 m in front of the origin, looking down +z
    return K, E


def test_mask_distance_is_euclidean():
    m = torch.zeros(9, 9)
    m[4, 4] = 1
    d = mask_distance(m)
    assert d[4, 4] == 0 and d[4, 7] == pytest.approx(3.0) and d[0, 0] == pytest.approx(np.hypot(4, 4))


def test_outside_term_pulls_a_gaussian_whose_footprint_misses_the_mask():
    """A centre 10 px left of the mask (no footprint overlap) gets a gradient towards the mask."""
    H = 32
    K, E = _camera(H)
    mask = torch.zeros(H, H, 1)
    mask[10:22, 20:30] = 1
    alpha = mask.clone()  # everything covered: only the outside term acts
    x = torch.tensor([[(10 - H / 2) * 2.0 / H, (16 - H / 2) * 2.0 / H, 0.0]], requires_grad=True)  # projects to (10,16)
    uv, _ = project_points(x, E, K)
    assert torch.allclose(uv, torch.tensor([[10.0, 16.0]]), atol=1e-4)
    loss_fn = component("silhouette", "chamfer", weight=1.0)
    terms = loss_fn.image_terms(x, E, K, mask, mask_distance(mask[..., 0]), alpha)
    assert float(terms["sil_outside"]) == pytest.approx((10 / H) ** 2, rel=0.05)
    assert float(terms["sil_coverage"]) == 0.0
    loss_fn.total(terms).backward()
    assert x.grad[0, 0] < 0  # descending the loss moves +x, towards the mask
    assert abs(float(x.grad[0, 1])) < abs(float(x.grad[0, 0])) * 0.2


def test_coverage_term_pulls_the_nearest_centre_to_uncovered_mask_pixels():
    H = 32
    K, E = _camera(H)
    mask = torch.zeros(H, H, 1)
    mask[14:18, 24:28] = 1  # a flared hem nobody covers
    alpha = torch.zeros(H, H, 1)
    x = torch.tensor([[0.0, 0.0, 0.0], [-0.5, 0.0, 0.0]], requires_grad=True)  # project to (16,16) and (8,16)
    mask_in = mask.clone()
    mask_in[16, 16] = 1  # keep both centres' outside term small: only coverage should move them
    mask_in[16, 8] = 1
    terms = component("silhouette", "chamfer", weight=1.0, outside_weight=0.0).image_terms(x, E, K, mask_in,
                                                                     mask_distance(mask_in[..., 0]), alpha)
    assert float(terms["sil_coverage"]) > 0
    component("silhouette", "chamfer", weight=1.0, outside_weight=0.0).total(terms).backward()
    assert x.grad[0, 0] < 0, "the nearest centre must be pulled towards the uncovered pixels (+x)"
    assert float(x.grad[1].abs().sum()) == 0.0, "a farther centre is not the nearest to any uncovered pixel"


def test_nearest_index_matches_the_dense_argmin():
    from realityavatar.losses import nearest_index

    g = torch.Generator().manual_seed(0)
    pts, q = torch.rand(3000, 2, generator=g) * 128, torch.rand(500, 2, generator=g) * 128
    assert torch.equal(nearest_index(q, pts), torch.cdist(q.double(), pts.double()).argmin(1))


def test_every_default_loss_term_reaches_a_trained_parameter():
    """The loss lists only terms that act: each term of the default config, on a tiny rendered batch of the default
    model, has a gradient path to a parameter the optimizer trains (a λ3 term on the frozen skinning grid has none)."""
    from realityavatar.body import build_body
    from realityavatar.build import build_module
    from realityavatar.data.records import mask_distance

    body = build_body("mannequin")
    module = build_module(compose(["gaussians.num_points=300"]), body, num_train_frames=2, scene_extent=1.0)
    trained = [p for g in module.param_groups() for p in g["params"]]
    poses, transl = torch.zeros(1, 3, 24, 3), torch.zeros(1, 3, 3)
    R = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # OpenCV camera 3 m in front of the body, looking back at it
    E = torch.eye(4)
    E[:3, :3], E[:3, 3] = R, -R @ torch.tensor([0.0, -0.3, 3.0])
    S = 32
    mask = torch.zeros(1, S, S, 1)
    mask[:, 4:28, 10:22] = 1.0
    batch = {**module.avatar.pose_inputs(poses, transl), "frame_idx": torch.tensor([0]), "viewmat": E[None],
             "K": torch.tensor([[[30.0, 0, S / 2], [0, 30.0, S / 2], [0, 0, 1]]]), "width": torch.tensor([S]),
             "height": torch.tensor([S]), "image": mask.expand(-1, -1, -1, 3) * 0.5, "mask": mask,
             "mask_dist": mask_distance(mask[0, ..., 0])[None]}
    rgb, alpha, _, posed = module.avatar.render_batch(batch)
    out = TrainingRender(rgb, alpha, batch, posed, module)
    assert {"rgb", "mask", "perceptual", "silhouette"} <= set(module.losses)
    for name, term in module.losses.items():
        value, _ = term(out)
        assert value.grad_fn is not None, f"loss.{name} has no gradient at all"
        grads = torch.autograd.grad(value, trained, retain_graph=True, allow_unused=True)
        assert any(g is not None and g.abs().sum() > 0 for g in grads), f"loss.{name} reaches no trained parameter"
