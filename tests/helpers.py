"""What several test packages share: the repository's paths, model and run builders, and the benchmarks' scripts as
modules (for the benchmarks' own tests)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def benchmark(name: str):
    """benchmarks/<name>.py as a module (the benchmarks are scripts, not a package: no sys.path edit)."""
    key = f"_benchmarks_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, ROOT / "benchmarks" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


def stepping_module(body, monkeypatch, device: str = "cpu", log_every: int = 5, *overrides: str):
    """The default model (silhouette term included; conf/ with `overrides`) with the trainer's hooks stubbed, so its
    training_step runs without a Trainer at global step `module._test_step`, and a maker of 32 px batches of random
    targets (realityavatar.data.random_batch)."""
    from realityavatar.build import build_module
    from realityavatar.config import compose
    from realityavatar.data.random_batch import make_batch_fn

    cfg = compose(["gaussians.num_points=400", *overrides])
    module = build_module(cfg, body, num_train_frames=4, scene_extent=1.0).to(device)
    opt_cfg = module.configure_optimizers()
    opt, sched = opt_cfg["optimizer"], opt_cfg["lr_scheduler"]["scheduler"]
    monkeypatch.setattr(type(module), "global_step", property(lambda self: self._test_step))
    module.optimizers, module.lr_schedulers = (lambda: opt), (lambda: sched)
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *args, **kwargs: None
    module.log_every = log_every
    return module, make_batch_fn(module.avatar.body, 32, int(cfg.data.window_len), device=device)


def random_poses(B: int = 2, T: int = 5, seed: int = 0):
    """A batch of random pose windows: poses [B,T,24,3], translations [B,T,3]."""
    import torch

    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, T, 24, 3, generator=g) * 0.3, torch.randn(B, T, 3, generator=g) * 0.5


def assert_all_grads(module) -> None:
    """Every parameter of `module` received a finite, non-zero gradient."""
    import torch

    missing = [n for n, p in module.named_parameters()
               if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not missing, f"no gradient reached {missing}"


# The suite's one trained run (the session fixture `trained_run` in conftest.py): the ci scene, 60 steps, with
# density refinement at steps 15 and 30 (window 6..42), so the run, its checkpoint and every rebuild from it go
# through clone/split/prune and a changed Gaussian count. Train, evaluate, resume, animate, export, the viewer, the
# density and module checks read it instead of training their own.
ITERATIONS = 60
NUM_POINTS = 1500
TRAINED_RUN = ["data=synthetic_ci", "trainer=ci", f"iterations={ITERATIONS}", "density.refine_every=15",
               f"gaussians.num_points={NUM_POINTS}", "eval.save_video=false", "eval.save_images=2",
               "eval.fps_frames=2", "eval.fps_warmup=1"]


def train(out: Path, *overrides: str) -> dict:
    """`realityavatar-train <overrides> hydra.run.dir=<out>` in this process; returns the run's metrics."""
    from realityavatar.config import compose, prepare_run
    from realityavatar.train import run

    return run(*prepare_run(compose(list(overrides)), out))


def plant_found_weights(root: Path, monkeypatch, lin: bool = True, vgg16: bool = True, vgg19: bool = False) -> dict:
    """What metrics.py / build.py look for, with random weights, under `root`: an installed-looking lpips package
    (weights/v0.1/vgg.pth; importing it fails, as it does without a working torchvision) on sys.path, and
    torchvision's vgg16 / vgg19 in a torch hub cache ($TORCH_HOME). Returns {"lin", "vgg16", "vgg19"}: the paths."""
    import torch

    from realityavatar.metrics import vgg_features

    pkg, hub = root / "site" / "lpips", root / "torch_home" / "hub" / "checkpoints"
    paths = {"lin": pkg / "weights" / "v0.1" / "vgg.pth", "vgg16": hub / "vgg16-397923af.pth",
             "vgg19": hub / "vgg19-dcbb9e9d.pth"}
    for p in paths.values():
        p.parent.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").write_text("raise ImportError('planted lpips: weights only')\n")
    torch.manual_seed(0)
    if lin:
        torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate((64, 128, 256, 512, 512))},
                   paths["lin"])
    for arch, want in (("vgg16", vgg16), ("vgg19", vgg19)):
        if want:
            torch.save({f"features.{k}": v for k, v in vgg_features(arch).state_dict().items()}, paths[arch])
    monkeypatch.setenv("TORCH_HOME", str(root / "torch_home"))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)  # tests/conftest.py hides any installed lpips
    monkeypatch.syspath_prepend(str(root / "site"))
    return {k: str(v) for k, v in paths.items()}
