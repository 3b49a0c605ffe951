"""probe: cloth tracking, novel-pose phases, garment shape change."""

from __future__ import annotations

import realityavatar.config  # noqa: F401  registers the resolvers (int_mul, ...) the real tree's configs use


def test_probe_cloth_tracking_measures_sliding(tmp_path):
    """probe's cloth tracking: points glued to the cloth keep their material position (drift 0) while
    the cloth moves 20 cm; points left in place while the cloth slides 5 cm under them drift 5 cm; points far from
    the cloth at rest are not the garment's."""
    import numpy as np

    from realityavatar.analysis.probe import ClothTracker, cloth_tracking

    u, v = np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11), indexing="ij")
    flat = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)  # a 1 m square in z = 0
    faces = [(i * 11 + j, (i + 1) * 11 + j, i * 11 + j + 1) for i in range(10) for j in range(10)]
    faces += [((i + 1) * 11 + j, (i + 1) * 11 + j + 1, i * 11 + j + 1) for i in range(10) for j in range(10)]
    shift = [np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0]), np.array([0.2, 0.0, 0.1])]
    np.savez(tmp_path / "g.npz", vertices=np.stack([flat + s for s in shift]), faces=np.array(faces),
             frames=np.arange(4))
    tr = ClothTracker(tmp_path / "g.npz")
    pts = np.array([[0.3, 0.3, 0.0], [0.5, 0.6, 0.0], [0.5, 0.5, 0.5]])  # two on the cloth, one 50 cm above it
    phase = {0: "rest", 1: "rest", 2: "spin", 3: "settled"}
    glued = {f: tr.locate(f, pts + shift[f]) for f in range(4)}
    still = {f: tr.locate(f, pts + (shift[f] if f != 2 else 0.0)) for f in range(4)}
    g, s = cloth_tracking(glued, phase), cloth_tracking(still, phase)
    assert g[2][1] < 0.01 and g[3][1] < 0.01 and g[3][0] < 0.01  # cloth_p50, drift_p50 in metres
    assert abs(s[2][1] - 0.05) < 0.01 and s[3][1] < 0.01


def test_probe_novel_pose_phases_follow_the_root(tmp_path):
    """probe's held-out-sequence phases: rest until the root turns, spin while it turns by more than
    0.5 degrees a frame (0.3 is still), after from the first still frame on (PoseTable.motion_phases' after and
    settled); PSNR per phase from per_frame.csv's novel-pose rows."""
    import pickle

    import numpy as np

    from realityavatar.analysis.probe import heading_stops, novel_pose_phases

    turn = [0, 0.3, 0, 5, 10, 10, 10, 3, 0, 0, 0]  # degrees per frame about y
    angle, infos = 0.0, {}
    for i, t in enumerate(turn):
        angle += np.radians(t)
        for view in (0, 1):
            infos[f"frame_{100 + i:06d}_view_{view:02d}"] = {
                "poses": np.zeros(72, np.float32), "Rh": np.array([0.0, angle, 0.0], np.float32),
                "Th": np.zeros(3, np.float32)}
    mesh = tmp_path / "seq-novelpose"
    mesh.mkdir()
    with open(mesh / "mesh_infos.pkl", "wb") as f:
        pickle.dump(infos, f)
    phases = heading_stops(mesh, fps=2.0)  # frame 110 is a second after the stop: motion_phases says "settled"
    assert [phases[100 + i] for i in range(11)] == ["np_rest"] * 3 + ["np_spin"] * 5 + ["np_after"] * 3
    run = tmp_path / "run"
    run.mkdir()
    lines = ["split,frame,view,psnr,iou"] + [f"novel_pose,{100 + i},0,{20 + i},0.9" for i in range(10)]
    lines += ["novel_view,109,1,99,1.0"]
    (run / "per_frame.csv").write_text("\n".join(lines) + "\n")
    out = novel_pose_phases(run, mesh, 2.0)
    assert out["novel_pose/np_after/psnr"] == 28.5 and out["novel_pose/np_rest/psnr"] == 21.0
    assert out["novel_pose/np_spin/images"] == 5


def test_probe_garment_shape_change_ignores_the_turn(tmp_path):
    """probe's garment shape change: a cloth turned and moved rigidly with its waist has none (a spin
    at a fixed pose), a hem swung 30 cm out shows it as the median vertex's displacement, and the reference is the
    given settled frame."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from realityavatar.analysis.probe import garment_curves

    theta, y = np.meshgrid(np.linspace(0, 2 * np.pi, 12, endpoint=False), np.linspace(0.0, -0.5, 6), indexing="ij")
    tube = np.stack([0.2 * np.cos(theta), y, 0.2 * np.sin(theta)], -1).reshape(-1, 3)  # waist ring at y = 0
    turned = Rotation.from_rotvec([0.0, 2.0, 0.0]).apply(tube) + [0.3, 0.0, -0.1]
    swung = tube.copy()
    low = swung[:, 1] < -0.15  # the lower four of six rings (two thirds of the vertices) move 0.3 m sideways
    swung[low, 0] += 0.3
    np.savez(tmp_path / "g.npz", vertices=np.stack([tube, turned, swung, tube]), faces=np.zeros((0, 3), int),
             frames=np.arange(4))
    c = garment_curves(tmp_path / "g.npz", settled_frame=3)
    assert c[0][2] < 1e-9 and c[1][2] < 1e-6  # same shape, turned 115 degrees and moved
    assert abs(c[2][2] - 0.3) < 1e-6
    assert garment_curves(tmp_path / "g.npz", settled_frame=2)[2][2] < 1e-9


def test_probe_renders_on_the_runs_device(trained_run, monkeypatch):
    """The probe renders a run on the device its training used (build.run_device: a GPU run on its GPU, where gsplat
    needs CUDA tensors; it fell back to the torch backend on the CPU before). Here the run is a CPU run: the device
    is asked for once, and every held-out image is probed."""
    import numpy as np
    import torch

    from realityavatar.analysis import probe

    asked = []

    def device_of(cfg, override=None):
        asked.append(str(cfg.trainer.accelerator))
        return torch.device("cpu")

    monkeypatch.setattr(probe, "run_device", device_of)
    rows, summary = probe.probe_run(trained_run[0], kinds=("heldout",))
    assert asked == ["cpu"]
    assert rows and all(r["kind"] == "heldout" and np.isfinite(r["psnr"]) for r in rows)
    assert "heldout/all/psnr" in summary


def test_frames_renders_on_the_runs_device(trained_run, monkeypatch, tmp_path):
    """analysis.frames renders a run on its training device, as the probe does; here a CPU run, asked once."""
    import torch

    from realityavatar.analysis import frames
    from realityavatar.build import build_data, load_run

    asked = []

    def device_of(cfg, override=None):
        asked.append(str(cfg.trainer.accelerator))
        return torch.device("cpu")

    monkeypatch.setattr(frames, "run_device", device_of)
    cfg, module, _ = load_run(trained_run[0])
    first = build_data(cfg, module.avatar.body).datasets["novel_view"].records[0].frame
    out = tmp_path / "frames.png"
    assert frames.main([str(trained_run[0]), "--frames", str(first), "--out", str(out)]) == 0
    assert asked == ["cpu"] and out.is_file()
