"""Named scene presets (sizes ci / demo / full) and sequences (garment x motion, like I3D-Human's takes)."""

from __future__ import annotations

from realityavatar.data.synthetic.motions import MOTIONS

GARMENT_NAMES = ("skirt", "dress")  # the cloth module's GARMENTS; checked against it when a scene is built
# Every garment x motion pair is a sequence "<garment>_<motion>"; the first four mirror I3D-Human's ID1_1, ID1_2,
# ID2_1, ID3_1 (spins with abrupt stops, swaying, arm flapping, walking in a long dress).
FEATURED = ("skirt_spin", "dress_spin", "skirt_flap", "dress_walk")
SEQUENCES = {f"{g}_{m}": (g, m) for g in GARMENT_NAMES for m in MOTIONS}

COMMON = {
    "sequence": "skirt_spin",
    "body": "mannequin",
    "camera_radius": 2.8,  # metres from the subject
    "camera_height": 1.2,  # camera centres above the ground
    "target_height": 0.9,  # cameras look at this point above the ring centre
    "subject_height": 1.75,
    "fill": 0.7,  # fraction of the image height a standing subject spans
    "camera_phase_deg": 0.0,
    "motion_params": {},  # per-motion knobs (spin_seconds, turns, sway_hz, flap_hz, walk_speed, ...)
    "cloth_params": {},  # passed to cloth.simulate_garment
    "ambient": 0.4,  # Lambert shading under one directional light fixed in the world (render.LIGHT_DIR):
    "diffuse": 0.6,  # albedo x (ambient + diffuse * max(0, n.l)); ambient=1, diffuse=0 renders the albedo alone
    # Rays per pixel side: a camera integrates over each pixel, so its images carry no detail finer than a pixel.
    # One ray through each pixel centre (1, the scenes before this key) aliases the garment's sub-pixel stripes into
    # noise that differs per view and frame: at 256 px it alone was 29.7 / 34.4 dB PSNR from the 4x4-integrated
    # image on the two held-out cameras, as large as a trained model's whole error (see docs/research/2026-11-23-pixel-integrated-scenes.md).
    "supersample": 3,
    # Held-out cameras for the novel-view evaluation only, half on the ring's height and half 40 degrees above the
    # look-at point, none within 30 degrees of a training camera (cameras.eval_cameras); training keeps the ring's.
    "eval_cameras": 8,
}

PRESETS = {
    # seconds on a CPU; just enough frames for one spin and its settling
    "ci": {**COMMON, "fps": 10.0, "train_frames": 24, "novel_frames": 10, "cameras": 4, "novel_view_cameras": 1,
           "eval_cameras": 2, "width": 64, "height": 64,
           # the unconverged 20 x 10 cloth (6x faster than the default 40 x 20): the tests need a skirt, not a fabric
           "cloth_params": {"n_around": 20, "n_rings": 10}},
    # sized for `make demo` (about 15 minutes in all on a laptop CPU)
    "demo": {**COMMON, "fps": 25.0, "train_frames": 100, "novel_frames": 35, "cameras": 6, "novel_view_cameras": 2,
             "width": 256, "height": 256},
    # GPU-scale runs: I3D-Human-like 10 cameras at 512 px
    "full": {**COMMON, "fps": 50.0, "train_frames": 400, "novel_frames": 120, "cameras": 10, "novel_view_cameras": 4,
             "width": 512, "height": 512},
}
