"""Adaptive density control: clone/split/prune with the optimizer state, caps, and inside a real fit."""

from __future__ import annotations

import csv
import math

import pytest
import torch

from realityavatar.config import compose
from realityavatar.model.density import NoDensityControl
from realityavatar.model.gaussians import PARAM_NAMES, CanonicalGaussians
from tests.fixtures_data import RandomBody
from tests.helpers import ITERATIONS, NUM_POINTS, TRAINED_RUN
from tests.model.configured import component


@pytest.fixture(scope="module")
def body() -> RandomBody:
    return RandomBody(seed=3, pelvis=(0.0, 0.0, 0.0), spread=0.15)


def _adam_with_state(g: CanonicalGaussians) -> torch.optim.Adam:
    groups = [{"params": ps, "name": n} for n, ps in g.param_groups().items()]
    opt = torch.optim.Adam(groups, lr=1e-3)
    for n in g.param_names:
        p = getattr(g, n)
        p.grad = torch.arange(p.numel(), dtype=torch.float32).reshape(p.shape) + 1.0
    opt.step()
    return opt


def _meta(n, high_idx, value=1e-2):
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    means2d.grad[0, high_idx, 0] = value
    return {"means2d": means2d, "radii": torch.ones(1, n, dtype=torch.int32)}


def test_density_clone_split_prune_with_optimizer_state(body):
    g = component("gaussians", body=body, num_points=20, feature_dim=4, seed=0)
    assert g.param_names == PARAM_NAMES
    with torch.no_grad():
        g.log_scales[:10] = math.log(0.001)  # small -> clone
        g.log_scales[10:] = math.log(0.05)  # large -> split
        g.opacity_logits[:] = 2.0
        g.opacity_logits[19] = -8.0  # prune
    opt = _adam_with_state(g)
    old_avg = {n: opt.state[getattr(g, n)]["exp_avg"].clone() for n in g.param_names}
    old_means = g.means.detach().clone()
    old_scales = g.scales().detach().clone()
    dc = component("density", refine_start=0, refine_stop=100, refine_every=10, grad_threshold=2e-4, prune_opacity=0.05,
                        grow_scale3d=0.01, scene_scale=1.0, reset_every=0, max_points=1000)
    high = [0, 1, 2, 12, 13]  # 3 clones, 2 splits
    stats = dc.step_post_backward(g, opt, _meta(20, high), step=10, image_size=(64, 48))
    assert stats["cloned"] == 3 and stats["split"] == 2 and stats["pruned"] == 1
    assert g.num_points == 20 + 3 + 2 - 1
    # the optimizer now points at the new parameters and its rows follow them
    for n in g.param_names:
        p = getattr(g, n)
        assert any(p is q for grp in opt.param_groups for q in grp["params"])
        st = opt.state[p]["exp_avg"]
        assert st.shape[0] == g.num_points
    # layout: kept originals (not split, not pruned) first, then clones' zero rows, then split children's zero rows
    kept = [i for i in range(20) if i not in (12, 13, 19)]
    avg = opt.state[g.means]["exp_avg"]
    assert torch.equal(avg[: len(kept)], old_avg["means"][kept])
    assert (avg[len(kept):] == 0).all()
    assert torch.allclose(g.means[: len(kept)], old_means[kept])
    assert torch.allclose(g.means[len(kept): len(kept) + 3], old_means[[0, 1, 2]])  # clones copy
    assert torch.allclose(g.scales()[-4:], old_scales[[12, 13, 12, 13]] / 1.6, rtol=1e-5)  # split children
    # training continues with the edited optimizer
    for n in g.param_names:
        getattr(g, n).grad = torch.ones_like(getattr(g, n))
    opt.step()
    assert dc.grad2d.shape == (g.num_points,) and float(dc.grad2d.sum()) == 0.0


def test_density_cap_reset_state_and_disabled(body):
    g = component("gaussians", body=body, num_points=20, feature_dim=4, seed=0)
    with torch.no_grad():
        g.log_scales[:] = math.log(0.001)
        g.opacity_logits[:] = 2.0
    opt = _adam_with_state(g)
    off = NoDensityControl(prune_opacity=0.02, refine_every=50)  # what a preset tuned for density control passes
    assert off.step_post_backward(g, opt, _meta(20, list(range(20))), 10, (64, 64)) == {} and g.num_points == 20
    with pytest.raises(TypeError, match="density=off: unknown option.*prune_opacty"):
        NoDensityControl(prune_opacty=0.02)
    dc = component("density", refine_start=0, refine_stop=100, refine_every=10, reset_every=5, max_points=24, prune_opacity=0.05)
    dc.step_post_backward(g, opt, _meta(20, list(range(20))), step=3, image_size=(64, 64))
    state = dc.state_dict()
    dc2 = component("density", refine_start=0, refine_stop=100, refine_every=10, reset_every=5, max_points=24)
    dc2.load_state_dict(state)
    assert torch.equal(dc2.grad2d, dc.grad2d) and dc2.grad2d.sum() > 0
    stats = dc.step_post_backward(g, opt, _meta(20, list(range(20))), step=10, image_size=(64, 64))
    assert stats["cloned"] == 4 and g.num_points == 24  # capped at max_points
    stats = dc.step_post_backward(g, opt, _meta(24, []), step=15, image_size=(64, 64))
    assert stats.get("reset") == 1 and (g.opacities() <= 0.1 + 1e-6).all()
    assert (opt.state[g.opacity_logits]["exp_avg"] == 0).all()


def test_density_gradient_of_a_multi_image_batch_is_scaled_by_its_images(body):
    """gsplat's rule: the loss is a mean over a batch's images, so a Gaussian seen by V samples (one meta each, as a
    batch of V images renders them) with 1/V of one image's gradient each accumulates what one image gives alone."""
    g = component("gaussians", body=body, num_points=20, feature_dim=4, seed=0)
    kw = {"refine_start": 0, "refine_stop": 100, "refine_every": 10, "grad_threshold": 2e-4, "prune_opacity": 0.05,
          "grow_scale3d": 0.01, "scene_scale": 1.0, "reset_every": 0, "max_points": 1000}
    one, four = component("density", **kw), component("density", **kw)
    one.step_post_backward(g, None, _meta(20, [3], 1e-2), step=1, image_size=(64, 48))
    four.step_post_backward(g, None, [_meta(20, [3], 1e-2 / 4) for _ in range(4)], step=1, image_size=(64, 48))
    avg_one = one.grad2d / one.count.clamp_min(1)
    avg_four = four.grad2d / four.count.clamp_min(1)
    assert float(avg_one[3]) > 0 and torch.allclose(avg_four, avg_one, rtol=1e-6), (avg_one[3], avg_four[3])


def test_density_control_fires_inside_the_training_loop(trained_run):
    """Clone/split/prune during a real fit: the Adam state, the parameters and the LR schedule stay consistent."""
    from realityavatar.model.gaussians import PARAM_NAMES

    out, metrics = trained_run
    with open(out / "logs" / "csv" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    fired = {k: sum(float(r[k]) for r in rows if r.get(k)) for k in ("train/density_cloned", "train/density_split",
                                                                      "train/density_pruned")}
    assert sum(fired.values()) > 0, f"refinement never changed the Gaussians: {fired}"
    assert metrics["num_gaussians"] != NUM_POINTS
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=True)
    N = metrics["num_gaussians"]
    assert state["state_dict"]["avatar.gaussians.means"].shape[0] == N
    opt = state["optimizer_states"][0]
    sched = state["lr_schedulers"][0]
    assert len(sched["base_lrs"]) == len(opt["param_groups"]) and sched["last_epoch"] == ITERATIONS
    cfg = compose(TRAINED_RUN)
    for group, base in zip(opt["param_groups"], sched["base_lrs"]):
        if group["name"] not in PARAM_NAMES:
            continue
        (idx,) = group["params"]
        st = opt["state"][idx]
        shape = tuple(state["state_dict"][f"avatar.gaussians.{group['name']}"].shape)
        assert tuple(st["exp_avg"].shape) == shape == tuple(st["exp_avg_sq"].shape), group["name"]
        assert st["exp_avg_sq"].abs().sum() > 0, f"{group['name']}: Adam state lost at refinement"
        f = cfg.optim.final_factor.get(group["name"], cfg.optim.final_factor.default)
        assert group["lr"] == pytest.approx(base * f ** 1.0, rel=1e-6), f"{group['name']}: LR schedule lost"
