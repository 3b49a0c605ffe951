"""A hand-written multirun folder, as a paper sweep over two scenes leaves it (collect and pareto read it)."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

PSNR = {
    "full": {"sceneA": [30.0, 31.0, 32.0], "sceneB": [28.0, 29.0, 30.0]},
    "no_zc": {"sceneA": [30.5, 30.0, 31.0], "sceneB": [29.0, 28.5, 29.5]},
    "no_lstm": {"sceneA": [27.0, 27.2, 27.4], "sceneB": [25.0, 25.2, 25.4]},
}


def write_fake_sweep(root: Path, lpips_missing_for: str = "no_lstm") -> Path:
    """A multirun folder as `realityavatar-train -m +ablation=paper data=sceneA,sceneB` leaves it."""
    root.mkdir(parents=True)
    (root / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {
        "hydra": ["hydra.mode=MULTIRUN"], "task": ["+ablation=paper", "data=sceneA,sceneB"]}}}))
    job = 0
    for variant, scenes in PSNR.items():
        for scene, values in scenes.items():
            for seed, psnr in enumerate(values):
                d = root / str(job)
                (d / ".hydra").mkdir(parents=True)
                overrides = [f"+variant={variant}", f"data={scene}", f"seed={seed}", "+ablation=paper"]
                (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
                lp = variant != lpips_missing_for
                m = {
                    "config": {"variant": variant, "data": scene, "ablation": "paper", "color": "mlp"},
                    "overrides": overrides, "seed": seed, "commit": "abc1234", "scene": scene,
                    "train_seconds": 100.0 + 10 * seed, "iterations": 2000, "num_gaussians": 5000,
                    "num_parameters": 123456, "render_fps": 20.0 + seed, "perceptual": "dssim",
                    "lpips": "computed (lpips package 0.1.4 vgg)" if lp else "not computed: no LPIPS weights configured",
                    "test/novel_view/psnr": psnr, "test/novel_view/ssim": 0.9 + 0.01 * seed,
                    # a number next to a "not computed" status must still come out as n/c
                    "test/novel_view/lpips": 0.040 + 0.001 * seed if (lp or seed == 0) else None,
                    "test/novel_view/psnr_masked": psnr - 5, "test/novel_view/ssim_masked": 0.8,
                    "test/novel_pose/psnr": psnr - 2, "test/novel_pose/ssim": 0.85,
                    "test/novel_pose/lpips": 0.050 if lp else None,
                    "test/novel_pose/psnr_masked": psnr - 7, "test/novel_pose/ssim_masked": 0.7,
                    "test/novel_view/spin/psnr_garment_camera_std": 2.0 + 0.1 * seed,  # spread over cameras
                }
                (d / "metrics.json").write_text(json.dumps(m))
                job += 1
    return root
