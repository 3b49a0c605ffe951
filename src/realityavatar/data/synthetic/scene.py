"""Write a synthetic loose-clothing scene in the I3D-Human/HumanNeRF layout (see docs/CONTRACTS.md).

Pipeline: motion (body poses + Rh/Th) -> MuJoCo garment (cloth.simulate_garment) -> ray-cast RGB + masks per camera
-> `<root>/<scene>-{train,novelview,novelpose}` (with garment_masks/: the pixels that show the cloth, for evaluation), `<scene>-meta.json`, `<scene>-garment.npz`. Deterministic per seed,
cached by a hash of the parameters, written to a temporary folder and moved into place at the end.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path

import numpy as np
import torch

from realityavatar.data.synthetic.cameras import eval_cameras, novel_view_ids, ring_cameras
from realityavatar.data.synthetic.motions import MOTIONS, Motion, make_motion
from realityavatar.data.synthetic.presets import PRESETS, SEQUENCES
from realityavatar.data.synthetic.render import BodyTexture, GarmentTexture, all_camera_rays, render_views

GENERATOR_VERSION = 3  # bump when the output changes for the same parameters (invalidates caches)
SPLITS = {"train": "train", "novel_view": "novelview", "novel_pose": "novelpose"}
PICKLE_PROTOCOL = 4
PNG_COMPRESS = 6


def default_root() -> Path:
    """$REALITYAVATAR_SCENES, else `scenes/` in the repository (editable install), else ./scenes."""
    if os.environ.get("REALITYAVATAR_SCENES"):
        return Path(os.environ["REALITYAVATAR_SCENES"])
    repo = Path(__file__).resolve().parents[4]
    return repo / "scenes" if (repo / "pyproject.toml").is_file() else Path.cwd() / "scenes"


def scene_paths(prefix: Path) -> dict[str, Path]:
    """Files of the scene whose prefix is `<root>/<scene>` (what build_scene returns)."""
    prefix = Path(prefix)
    out = {k: prefix.with_name(f"{prefix.name}-{v}") for k, v in SPLITS.items()}
    out["meta"] = prefix.with_name(f"{prefix.name}-meta.json")
    out["garment"] = prefix.with_name(f"{prefix.name}-garment.npz")
    return out


def resolve_params(preset_or_params: str | dict, sequence: str | None = None, overrides: dict | None = None) -> dict:
    """Full, validated parameter dict from a preset name or a dict (missing keys from the `demo` preset)."""
    if isinstance(preset_or_params, str):
        if preset_or_params not in PRESETS:
            raise ValueError(f"preset: unknown scene preset {preset_or_params!r}; expected one of {tuple(PRESETS)}")
        p = {**PRESETS[preset_or_params], "preset": preset_or_params}
    elif isinstance(preset_or_params, dict):
        base = preset_or_params.get("preset", "demo")
        if base not in PRESETS:
            raise ValueError(f"params['preset']: unknown scene preset {base!r}; expected one of {tuple(PRESETS)}")
        p = {**PRESETS[base], "preset": base, **preset_or_params}
    else:
        raise ValueError(  # noqa: TRY004 -- every bad scene parameter raises ValueError (one type for callers)
            f"preset_or_params: expected a preset name or a dict, got {type(preset_or_params).__name__}")
    if sequence is not None:
        p["sequence"] = sequence
    p.update(overrides or {})
    known = set(PRESETS["demo"]) | {"preset", "name", "garment", "motion"}
    unknown = sorted(set(p) - known)
    if unknown:
        raise ValueError(f"scene params: unknown keys {unknown}; known: {sorted(known)}")
    if "garment" not in p or "motion" not in p:
        if p["sequence"] not in SEQUENCES:
            raise ValueError(f"sequence: unknown sequence {p['sequence']!r}; expected one of {tuple(SEQUENCES)}")
        g, m = SEQUENCES[p["sequence"]]
        p.setdefault("garment", g)
        p.setdefault("motion", m)
    from realityavatar.data.synthetic.cloth import GARMENTS

    if p["garment"] not in GARMENTS:
        raise ValueError(f"garment: unknown garment {p['garment']!r}; expected one of {tuple(GARMENTS)}")
    if p["motion"] not in MOTIONS:
        raise ValueError(f"motion: unknown motion {p['motion']!r}; expected one of {MOTIONS}")
    for k in ("train_frames", "novel_frames", "cameras", "novel_view_cameras", "eval_cameras", "width", "height",
              "supersample"):
        if isinstance(p[k], bool) or not isinstance(p[k], (int, np.integer)):
            raise ValueError(f"{k}: expected an integer, got {p[k]!r}")  # noqa: TRY004 -- one error type
        p[k] = int(p[k])
    if p["train_frames"] < 2:
        raise ValueError(f"train_frames: expected at least 2 training frames, got {p['train_frames']}")
    if p["novel_frames"] < 1:
        raise ValueError(f"novel_frames: expected at least 1 held-out frame, got {p['novel_frames']}")
    if p["cameras"] < 2:
        raise ValueError(f"cameras: expected at least 2 cameras (training + novel view), got {p['cameras']}")
    if not 1 <= p["novel_view_cameras"] < p["cameras"]:
        raise ValueError(f"novel_view_cameras: expected 1 <= count < cameras ({p['cameras']}), "
                         f"got {p['novel_view_cameras']}")
    if p["eval_cameras"] < 0 or p["eval_cameras"] % 2:
        raise ValueError(f"eval_cameras: expected an even count >= 0 (half at each elevation), got {p['eval_cameras']}")
    if not 1 <= p["supersample"] <= 8:
        raise ValueError(f"supersample: expected 1..8 rays per pixel side (1: one ray through each pixel centre), "
                         f"got {p['supersample']}")
    if not 8 <= p["width"] <= 4096 or not 8 <= p["height"] <= 4096:
        raise ValueError(f"width/height: expected 8..4096 px, got {p['width']}x{p['height']}")
    for k in ("fps", "camera_radius", "camera_height", "target_height", "subject_height", "fill", "camera_phase_deg",
              "ambient", "diffuse"):
        if isinstance(p[k], bool) or not isinstance(p[k], (int, float)) or not np.isfinite(p[k]):
            raise ValueError(f"{k}: expected a finite number, got {p[k]!r}")
        p[k] = float(p[k])
    if p["fps"] <= 0 or p["camera_radius"] <= 1.0 or not 0 < p["fill"] <= 1.5:
        raise ValueError(f"fps > 0, camera_radius > 1 m and 0 < fill <= 1.5 expected, got fps={p['fps']}, "
                         f"camera_radius={p['camera_radius']}, fill={p['fill']}")
    if p["ambient"] < 0 or p["diffuse"] < 0 or p["ambient"] + p["diffuse"] <= 0:
        raise ValueError(f"ambient/diffuse: expected >= 0 with a positive sum, got {p['ambient']}, {p['diffuse']}")
    if p["body"] != "mannequin":
        raise ValueError(f"body: synthetic scenes use the mannequin body, got {p['body']!r}")
    p["motion_params"] = dict(p["motion_params"] or {})
    p["cloth_params"] = dict(p["cloth_params"] or {})
    if not p.get("name"):
        p["name"] = f"{p['garment']}_{p['motion']}_{p['preset']}"
    if "-" in p["name"] or "/" in p["name"] or p["name"].startswith("."):
        raise ValueError(f"name: scene names may not contain '-' or '/' or start with '.', got {p['name']!r}")
    return p


def code_hash() -> str:
    """Hash of the generator's source files: a changed cloth default or texture must invalidate cached scenes."""
    h = hashlib.sha256()
    for name in ("cameras.py", "cloth.py", "motions.py", "presets.py", "render.py", "scene.py"):
        h.update((Path(__file__).parent / name).read_bytes())
    return h.hexdigest()[:16]


def params_hash(params: dict, seed: int) -> str:
    blob = json.dumps({"params": params, "seed": int(seed), "generator": GENERATOR_VERSION, "code": code_hash()},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _versions() -> dict:
    out = {}
    for pkg in ("realityavatar", "numpy", "trimesh", "embreex", "mujoco", "mannequin-x", "pillow", "torch"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def body_sequence(body, motion: Motion):
    """Posed body per frame: vertices_world [F,V,3], joints_body [F,24,3], joints_world [F,24,3], rots_world [F,24,3,3]."""
    from realityavatar.geometry import axis_angle_to_matrix

    pose = torch.as_tensor(motion.pose, dtype=torch.float64)
    A = body.double()(pose)  # [F,24,4,4] body frame
    joints_body = (A[..., :3, :3] @ body.rest_joints.double()[:, :, None]).squeeze(-1) + A[..., :3, 3]
    verts = body.lbs(body.rest_vertices.double(), body.skin_weights.double(), A)  # [F,V,3]
    R = axis_angle_to_matrix(torch.as_tensor(motion.Rh, dtype=torch.float64))  # [F,3,3]
    T = torch.as_tensor(motion.Th, dtype=torch.float64)
    verts_w = torch.einsum("fab,fvb->fva", R, verts) + T[:, None]
    joints_w = torch.einsum("fab,fjb->fja", R, joints_body) + T[:, None]
    rots_w = R[:, None] @ A[..., :3, :3]
    body.float()
    return verts_w.numpy(), joints_body.numpy(), joints_w.numpy(), rots_w.numpy()


def is_built(prefix: Path, phash: str) -> bool:
    paths = scene_paths(prefix)
    if not all(paths[k].exists() for k in paths):
        return False
    try:
        return json.loads(paths["meta"].read_text()).get("params_hash") == phash
    except (OSError, json.JSONDecodeError):
        return False


def build_scene(preset_or_params: str | dict = "demo", root: str | Path | None = None, seed: int = 0, *,
                sequence: str | None = None, overrides: dict | None = None, force: bool = False,
                progress: bool = True) -> Path:
    """Generate (or reuse) a scene; returns its prefix `<root>/<scene>`: splits are `<prefix>-train` etc.

    preset_or_params: "ci" | "demo" | "full" or a dict of parameters (missing keys from its "preset", default demo).
    Parameters are validated before anything is written; a build that fails leaves no scene folder behind.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    p = resolve_params(preset_or_params, sequence, overrides)
    root = Path(root) if root is not None else default_root()
    prefix = root / p["name"]
    phash = params_hash(p, seed)
    remove_stale_builds(root, p["name"])
    if not force and is_built(prefix, phash):
        return prefix
    # Everything that can fail on the parameters runs before the first file is written.
    from realityavatar.body import build_body
    from realityavatar.data.synthetic.cloth import simulate_garment

    body = build_body(p["body"])
    rest_v = body.rest_vertices.numpy().astype(np.float64)
    pelvis_body = body.rest_joints[0].numpy().astype(np.float64)
    pelvis_height = float(pelvis_body[1] - rest_v[:, 1].min())  # soles on the ground y = 0
    motion = make_motion(p["motion"], p["fps"], p["train_frames"], p["novel_frames"], pelvis_body, pelvis_height,
                         seed=seed, params=p["motion_params"])
    Ks, viewmats = ring_cameras(p["cameras"], p["camera_radius"], p["camera_height"], p["target_height"],
                                p["width"], p["height"], p["subject_height"], p["fill"], p["camera_phase_deg"])
    nv_ids = novel_view_ids(p["cameras"], p["novel_view_cameras"])
    train_ids = [c for c in range(p["cameras"]) if c not in nv_ids]
    # Held-out cameras off the ring (two elevations), for the novel-view evaluation only: ids after the ring's.
    K_ev, view_ev = eval_cameras(viewmats[train_ids], viewmats[nv_ids], p["eval_cameras"], p["camera_radius"],
                                 p["camera_height"], p["target_height"], Ks[0])
    Ks, viewmats = np.concatenate([Ks, K_ev]), np.concatenate([viewmats, view_ev])
    nv_ids = nv_ids + list(range(p["cameras"], p["cameras"] + p["eval_cameras"]))

    verts_w, joints_body, joints_w, rots_w = body_sequence(body, motion)
    garment = simulate_garment(joints_w, rots_w, p["fps"], p["garment"], p["cloth_params"], seed=seed)

    root.mkdir(parents=True, exist_ok=True)
    with _building(root):  # the jobs of a sweep that start at once: the first builds, the others wait and reuse it
        if not force and is_built(prefix, phash):
            return prefix
        # The builder's pid is in the name, so a later build can tell a killed build's leftovers from a running one.
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{p['name']}-{os.getpid()}-", dir=root))
        try:
            _write(tmp, p, seed, phash, body, motion, Ks, viewmats, train_ids, nv_ids, verts_w, joints_body, garment,
                   progress)
            paths = scene_paths(prefix)
            # Replace an old build piece by piece; the meta file (the cache marker) moves last.
            for key in ("meta", "train", "novel_view", "novel_pose", "garment"):
                if paths[key].is_dir():
                    shutil.rmtree(paths[key])
                elif paths[key].exists():
                    paths[key].unlink()
            for key in ("train", "novel_view", "novel_pose", "garment", "meta"):
                os.replace(tmp / paths[key].name, paths[key])
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return prefix


@contextmanager
def _building(root: Path):
    """An exclusive lock on the scenes folder (flock on the folder itself: no lock file), held while a scene is
    written into it. Two processes that found a scene missing at once no longer both ray cast it and replace each
    other's files under a reader."""
    fd = os.open(root, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def remove_stale_builds(root: Path, name: str, max_age_s: float = 24 * 3600) -> list[Path]:
    """Delete `.tmp-<name>-<pid>-*` folders of builds whose process is gone (a SIGKILLed make-scene); a folder
    without a pid in its name (older builds) is removed once it is older than `max_age_s`."""
    import time

    from realityavatar.runs import pid_alive

    removed = []
    for d in Path(root).glob(f".tmp-{name}-*"):
        rest = d.name[len(f".tmp-{name}-"):]
        head = rest.split("-", 1)[0]
        if head.isdigit() and "-" in rest:
            stale = not pid_alive(int(head))
        else:
            stale = time.time() - d.stat().st_mtime > max_age_s
        if stale and d.is_dir():
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


_FRAME_JOB: dict | None = None  # what _render_frame needs, inherited by the forked workers (not pickled per frame)


def _render_frame(f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame f of the scene being written: rgb [C,H,W,3], mask [C,H,W], part [C,H,W] (uint8; 2: the garment) of every
    camera."""
    j = _FRAME_JOB
    verts_w, body_faces, body_tex, garment_verts, garment_faces, garm_tex = j["parts"]
    C = len(j["Ks"]) if f < j["num_train"] else j["ring"]  # the evaluation-only cameras see the training frames
    P = C * j["width"] * j["height"]
    return render_views([(verts_w[f], body_faces, body_tex), (garment_verts[f], garment_faces, garm_tex)], j["Ks"][:C],
                        j["viewmats"][:C], j["width"], j["height"], (j["rays"][0][:P], j["rays"][1][:P]),
                        ambient=j["ambient"], diffuse=j["diffuse"], supersample=j["supersample"])


def _one_blas_thread() -> None:
    """A frame worker's BLAS on one thread: each worker already has a core, and BLAS's own threads (as many as the
    machine's cores, in every worker) only contend (2-core AVX2: the demo scene 95 -> 69 s; a 16-core GPU host cast
    the 512 px scene at ~1 frame/s, a frame per 2.4 s of one core)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


def _rendered_frames(job: dict, F: int):
    """The renders of frames 0..F-1 of `job` (_render_frame's inputs) in order, ray cast by one forked process per CPU
    core, each with one BLAS thread (each frame is independent and deterministic, so the files are the same as from
    one process); in one process where forking is not possible. The job is released when the frames are done."""
    import multiprocessing as mp

    global _FRAME_JOB
    _FRAME_JOB = job
    try:
        workers = min(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1, F)
        if workers < 2 or mp.current_process().daemon or "fork" not in mp.get_all_start_methods():
            yield from map(_render_frame, range(F))
            return
        with mp.get_context("fork").Pool(workers, initializer=_one_blas_thread) as pool:
            yield from pool.imap(_render_frame, range(F))
    finally:
        _FRAME_JOB = None


def _write(tmp: Path, p: dict, seed: int, phash: str, body, motion: Motion, Ks, viewmats, train_ids, nv_ids,
           verts_w, joints_body, garment, progress: bool) -> None:
    from tqdm import tqdm

    from realityavatar.data.i3d import I3DSplitWriter

    name = p["name"]
    tpose = body.rest_joints.numpy().astype(np.float32)
    writers = {k: I3DSplitWriter(tmp / f"{name}-{v}", tpose, PNG_COMPRESS, PICKLE_PROTOCOL) for k, v in SPLITS.items()}
    body_tex = BodyTexture(body.rest_vertices.numpy(), body.skin_weights.numpy(), seed)
    garm_tex = GarmentTexture(garment.uv, seed)
    body_faces = body.faces.numpy()
    all_ids = list(range(p["cameras"]))  # the ring: the novel poses are not seen by the evaluation-only cameras
    F = motion.num_frames
    rays = all_camera_rays(Ks, viewmats, p["width"], p["height"])
    job = {"parts": (verts_w, body_faces, body_tex, garment.vertices, garment.faces, garm_tex), "Ks": Ks,
           "viewmats": viewmats, "width": p["width"], "height": p["height"], "rays": rays, "ambient": p["ambient"],
           "diffuse": p["diffuse"], "supersample": p["supersample"], "num_train": motion.num_train,
           "ring": p["cameras"]}
    for f, (rgb, mask, part) in enumerate(tqdm(_rendered_frames(job, F), total=F, desc=f"scene {name}",
                                         disable=not progress, unit="frame")):
        poses = motion.pose[f].reshape(72).astype(np.float32)
        info = {"poses": poses, "Rh": motion.Rh[f].astype(np.float32), "Th": motion.Th[f].astype(np.float32),
                "joints": joints_body[f].astype(np.float32), "tpose_joints": tpose}
        if f < motion.num_train:
            targets = [("train", c) for c in train_ids] + [("novel_view", c) for c in nv_ids]
        else:
            targets = [("novel_pose", c) for c in all_ids]
        for split, c in targets:
            writers[split].add(f, c, rgb[c], mask[c], Ks[c].astype(np.float32), viewmats[c].astype(np.float32), info,
                               garment=np.where(part[c] == 2, 255, 0).astype(np.uint8))
    for w in writers.values():
        w.close()
    frames = np.arange(F, dtype=np.int64)
    with open(tmp / f"{name}-garment.npz", "wb") as fh:
        np.savez(fh, vertices=garment.vertices.astype(np.float32), faces=np.asarray(garment.faces, np.int64),
                 uv=np.asarray(garment.uv, np.float32), frames=frames)
    meta = {
        "name": name, "generator": "realityavatar.data.synthetic", "generator_version": GENERATOR_VERSION,
        "params": p, "params_hash": phash, "code_hash": code_hash(), "seed": int(seed), "fps": p["fps"], "body": p["body"],
        "world_up": "+y", "ground": "y = 0",
        "garment": p["garment"], "garment_params": _jsonable(getattr(garment, "params", {})),
        "motion": {"name": motion.name, "events": _jsonable(motion.events), "train_frames": motion.num_train,
                   "novel_frames": motion.num_novel},
        "frames": {"train": [0, motion.num_train], "novel_pose": [motion.num_train, F]},
        "cameras": {"train": train_ids, "novel_view": nv_ids, "novel_pose": all_ids,
                    "eval_only": [c for c in nv_ids if c >= p["cameras"]]},
        "splits": {k: f"{name}-{v}" for k, v in SPLITS.items()},
        "versions": _versions(),
    }
    (tmp / f"{name}-meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x
