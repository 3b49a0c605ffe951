"""Loose garments (flared skirt, dress) simulated with MuJoCo flex cloth, driven kinematically by a 24-joint skeleton.

The waist ring follows the pelvis; legs, hips and torso are kinematic capsules; the hem's shape depends on history.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

GARMENTS = ("skirt", "dress")

# SMPL joint indices used here.
_PELVIS, _LHIP, _RHIP, _LKNEE, _RKNEE, _SPINE2, _LANKLE, _RANKLE, _NECK = 0, 1, 2, 4, 5, 6, 7, 8, 12

# Defaults shared by both garments; lengths in metres, masses in kg, times in seconds.
_COMMON = {
    # 40 x 20: from here to 80 x 40 the rest drape moves 1.9 cm (median), less than a 1 mm change of the initial ripple
    # moves it (3.3 cm), the spin's flare 1.1 cm, for about 6x the simulation; at 20 x 10 the folds were the mesh's
    # buckling (benchmarks/cloth.py, docs/research/2026-12-07-converged-cloth.md)
    "n_around": 40,  # vertices per ring (the simulated tube; output adds one seam column)
    "n_rings": 20,  # rings from waist (pinned) to hem
    "waist_offset": 0.06,  # waist ring above the pelvis joint, along the body axis
    "waist_radius": None,  # None: max(hip_sep/2 + 0.08, torso_radius + 0.02)
    "length_scale": 1.0,  # cloth length (waist to hem along the surface) relative to the hem level below
    # Stretch: every edge keeps its rest length (a soft equality constraint with this time constant, stable at dt_max
    # at any resolution; an elastic membrane needs a step that shrinks with the edge). Bending: elastic, from young,
    # poisson and thickness (D = E t^3 / 12(1 - nu^2) ~ 7e-5 N m, a cotton's), so the folds' width is the fabric's.
    "edge_timeconst": 4.0e-3,
    "young": 3.0e4,  # Pa
    "poisson": 0.2,
    "thickness": 3.0e-3,
    "elastic_damping": 1.0e-3,  # flex elasticity damping (internal, relative motion)
    "drag_tau": 0.5,  # air drag: per-vertex force -m v / drag_tau (relative to the world, why motion decays)
    # Collision half-thickness of the cloth: under half the finest edge that is simulated (1.5 cm at 80 x 40), else
    # neighbouring triangles touch at rest (1 cm: 49k self-contacts at 80 x 40, MuJoCo's arena overflowed).
    "cloth_radius": 0.005,
    # The cloth collides with itself (MuJoCo's "auto" midphase): without it folds pass through each other and the
    # body shows through them; 3x the simulation's time at 40 x 20 with a 1 cm half-thickness (22 -> 68 s, the demo).
    "self_collision": True,
    "friction": 0.3,
    "contact_timeconst": 0.005,  # contact solref time constant (s): stiffer than MuJoCo's 0.02 so legs push cloth firmly
    "thigh_radius": 0.075,
    "shin_radius": 0.055,
    "hip_radius": 0.09,  # capsule between the two hip joints (buttocks / pelvis)
    "torso_radius": 0.11,  # capsule pelvis -> spine2
    "dt_max": 2.0e-3,  # largest physics step; substeps per frame = ceil(1 / (fps * dt_max))
    "preroll": 2.0,  # seconds of settling holding the first frame before recording
    "preroll_drag_tau": 0.1,  # stronger air drag during the pre-roll so the initial cone settles within it
    "init_noise": 1.0e-3,  # seeded radial ripple of the initial cone (m; breaks its symmetry so it can fold): smooth in
    # (u, v), so it is the same cloth at every resolution
}
_GARMENT_DEFAULTS = {
    # hem_level: where the hem hangs, as a blend knee (0) -> ankle (1); flare: initial cone angle from the body axis.
    "skirt": {"hem_level": 0.0, "flare_deg": 40.0, "mass": 0.15},
    "dress": {"hem_level": 0.5, "flare_deg": 30.0, "mass": 0.25},
}


@dataclass
class GarmentSequence:
    name: str
    vertices: np.ndarray  # [F,Vg,3] float32, world coordinates (metres), per frame
    faces: np.ndarray  # [Fg,3] int32 triangles (consistently oriented, outward normals)
    uv: np.ndarray  # [Vg,2] float32 texture coordinates in [0,1] (u around the waist, v from waist to hem)
    params: dict  # the parameters actually used (for the scene metadata)


def garment_params(garment: str = "skirt", params: dict | None = None) -> dict:
    """Defaults for `garment` updated with `params`; unknown keys or bad values -> ValueError naming the key."""
    if garment not in GARMENTS:
        raise ValueError(f"garment: expected one of {GARMENTS}, got {garment!r}")
    p = {**_COMMON, **_GARMENT_DEFAULTS[garment]}
    for k, v in (params or {}).items():
        if k not in p:
            raise ValueError(f"params: unknown key {k!r} for garment {garment!r}; known: {sorted(p)}")
        p[k] = v
    for k in ("n_around", "n_rings"):
        if not isinstance(p[k], (int, np.integer)) or p[k] < (6 if k == "n_around" else 3):
            raise ValueError(f"params[{k!r}]: expected an int >= {6 if k == 'n_around' else 3}, got {p[k]!r}")
        p[k] = int(p[k])
    positive = (
        "length_scale",
        "young",
        "thickness",
        "drag_tau",
        "preroll_drag_tau",
        "cloth_radius",
        "thigh_radius",
        "shin_radius",
        "hip_radius",
        "torso_radius",
        "dt_max",
        "mass",
        "contact_timeconst",
        "edge_timeconst",
    )
    for k in positive:
        if not (isinstance(p[k], (int, float)) and math.isfinite(p[k]) and p[k] > 0):
            raise ValueError(f"params[{k!r}]: expected a finite number > 0, got {p[k]!r}")
        p[k] = float(p[k])
    for k in (
        "waist_offset",
        "poisson",
        "elastic_damping",
        "friction",
        "preroll",
        "init_noise",
        "hem_level",
        "flare_deg",
    ):
        if not (isinstance(p[k], (int, float)) and math.isfinite(p[k])) or (k != "waist_offset" and p[k] < 0):
            raise ValueError(
                f"params[{k!r}]: expected a finite number{'' if k == 'waist_offset' else ' >= 0'}, got {p[k]!r}"
            )
        p[k] = float(p[k])
    if not 0.0 <= p["flare_deg"] < 80.0:
        raise ValueError(f"params['flare_deg']: expected 0 <= flare_deg < 80, got {p['flare_deg']}")
    if not isinstance(p["self_collision"], bool):
        raise ValueError(f"params['self_collision']: expected true or false, got {p['self_collision']!r}")  # noqa: TRY004 (contract: bad input -> ValueError)
    if p["waist_radius"] is not None:
        if not (
            isinstance(p["waist_radius"], (int, float))
            and math.isfinite(p["waist_radius"])
            and p["waist_radius"] > 0
        ):
            raise ValueError(
                f"params['waist_radius']: expected None or a number > 0, got {p['waist_radius']!r}"
            )
        p["waist_radius"] = float(p["waist_radius"])
    return p


def tube_topology(n_around: int, n_rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles [2*n_around*(n_rings-1),3] over the simulated vertices (index ring*n_around + i, seam shared) and
    the same triangles over output vertices (index ring*(n_around+1) + i, column n_around duplicates column 0)."""
    sim, out = [], []
    for j in range(n_rings - 1):
        for i in range(n_around):
            a, b = j * n_around + i, j * n_around + (i + 1) % n_around
            sim += [[a, a + n_around, b], [b, a + n_around, b + n_around]]
            w = n_around + 1
            a, b = j * w + i, j * w + i + 1
            out += [[a, a + w, b], [b, a + w, b + w]]
    return np.asarray(sim, np.int64), np.asarray(out, np.int32)


def _validate(joints, joint_rots, fps) -> tuple[np.ndarray, np.ndarray, float]:
    joints = np.asarray(joints, dtype=np.float64)
    joint_rots = np.asarray(joint_rots, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (24, 3) or joints.shape[0] < 1:
        raise ValueError(f"joints: expected shape [F,24,3] with F >= 1, got {joints.shape}")
    if joint_rots.shape != (joints.shape[0], 24, 3, 3):
        raise ValueError(
            f"joint_rots: expected shape [{joints.shape[0]},24,3,3] (matching joints), got {joint_rots.shape}"
        )
    if not np.isfinite(joints).all():
        raise ValueError("joints: contains non-finite values")
    if not np.isfinite(joint_rots).all():
        raise ValueError("joint_rots: contains non-finite values")
    R0 = joint_rots[:, _PELVIS]  # [F,3,3]
    ortho = np.abs(np.einsum("fji,fjk->fik", R0, R0) - np.eye(3)).max()
    if ortho > 1e-3 or (np.linalg.det(R0) < 0).any():
        raise ValueError(
            f"joint_rots: pelvis orientations must be rotation matrices (max |R^T R - I| = {ortho:.2g})"
        )
    if (
        isinstance(fps, bool)
        or not isinstance(fps, (int, float, np.integer, np.floating))
        or not math.isfinite(fps)
        or fps <= 0
    ):
        raise ValueError(f"fps: expected a finite number > 0, got {fps!r}")
    return joints, joint_rots, float(fps)


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    """R: [...,3,3] -> [...,4] wxyz."""
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()  # xyzw
    return q[:, [3, 0, 1, 2]].reshape(R.shape[:-2] + (4,))


def _z_to_dir_quat(d: np.ndarray) -> np.ndarray:
    """Unit directions d: [N,3] -> wxyz quaternions [N,4] rotating +z onto d (a capsule's axis)."""
    z = np.array([0.0, 0.0, 1.0])
    c = d @ z  # [N]
    axis = np.cross(np.broadcast_to(z, d.shape), d)  # [N,3]
    q = np.concatenate([1.0 + c[:, None], axis], 1)
    flip = c < -1 + 1e-9  # antiparallel: rotate pi about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _rest_geometry(j0: np.ndarray, R0: np.ndarray, p: dict, rng: np.random.Generator):
    """Cone of cloth in the pelvis frame of the first pose: points [n_rings*n_around,3] (local), and sizes."""
    axis_w = j0[_NECK] - j0[_PELVIS]  # body up axis, world
    if np.linalg.norm(axis_w) < 0.05 or np.linalg.norm(j0[_LHIP] - j0[_RHIP]) < 0.01:
        raise ValueError(
            "joints: first frame is degenerate (neck within 5 cm of the pelvis or hips within 1 cm)"
        )
    axis_w /= np.linalg.norm(axis_w)
    hip_sep = float(np.linalg.norm(j0[_LHIP] - j0[_RHIP]))
    waist_r = p["waist_radius"] or max(0.5 * hip_sep + 0.08, p["torso_radius"] + 0.02)
    waist_w = j0[_PELVIS] + p["waist_offset"] * axis_w
    knee = 0.5 * (j0[_LKNEE] + j0[_RKNEE])
    ankle = 0.5 * (j0[_LANKLE] + j0[_RANKLE])
    hem_w = (1 - p["hem_level"]) * knee + p["hem_level"] * ankle
    length = p["length_scale"] * float((waist_w - hem_w) @ axis_w)
    if length < 0.1:
        raise ValueError(
            f"joints: garment length from waist to hem level is {length:.3f} m (< 0.1 m); "
            "expected a standing body with knees/ankles below the pelvis along pelvis->neck"
        )
    # Local frame: up = body axis in pelvis coordinates; e1 towards the left hip; e2 = e1 x up.
    up = R0.T @ axis_w
    e1 = R0.T @ (j0[_LHIP] - j0[_RHIP])
    e1 -= (e1 @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e1, up)
    centre = p["waist_offset"] * up  # waist centre relative to the pelvis joint, local
    n_a, n_r = p["n_around"], p["n_rings"]
    s = np.linspace(0.0, 1.0, n_r)[:, None]  # [n_r,1]
    phi = 2 * np.pi * np.arange(n_a)[None, :] / n_a  # [1,n_a]
    flare = math.radians(p["flare_deg"])
    r = waist_r + s * length * math.sin(flare)  # [n_r,1]
    h = -s * length * math.cos(flare)
    pts = (
        centre
        + r[..., None] * (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)
        + h[..., None] * up
    )
    pts = pts.reshape(-1, 3)  # [n_r*n_a,3]
    if p["init_noise"] > 0:  # sum of the first 16 modes around, random amplitude and phase, growing from the waist
        k = np.arange(1, 17)[:, None, None]
        amp, phase = rng.normal(size=(16, 1, 1)) / 4, rng.uniform(0, 2 * np.pi, size=(16, 1, 1))
        ripple = p["init_noise"] * s * (amp * np.cos(k * phi + phase)).sum(0)  # [n_r,n_a]
        pts += (ripple[..., None] * (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)).reshape(-1, 3)
    return pts, {"waist_radius": float(waist_r), "length": float(length), "hip_sep": hip_sep}


def _capsule_segments(joints: np.ndarray) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Collider names, endpoints a,b: [F,C,3] (thighs, shins, hips, torso)."""
    pairs = [
        ("thigh_l", _LHIP, _LKNEE),
        ("thigh_r", _RHIP, _RKNEE),
        ("shin_l", _LKNEE, _LANKLE),
        ("shin_r", _RKNEE, _RANKLE),
        ("hips", _LHIP, _RHIP),
        ("torso", _PELVIS, _SPINE2),
    ]
    names = [n for n, _, _ in pairs]
    a = joints[:, [i for _, i, _ in pairs]]
    b = joints[:, [k for _, _, k in pairs]]
    return names, a, b


def _build_xml(
    pts: np.ndarray, tris: np.ndarray, n_pin: int, p: dict, caps: list[tuple[str, float, float]], dt: float,
    gravity=(0.0, -9.81, 0.0),
) -> str:
    point = " ".join(f"{x:.6f}" for x in pts.ravel())
    element = " ".join(str(int(i)) for i in tris.ravel())
    pins = " ".join(str(i) for i in range(n_pin))
    geoms = "\n".join(
        f'<body name="{n}" mocap="true"><geom type="capsule" size="{r:.5f} {hl:.5f}" contype="1" conaffinity="0" '
        f'friction="{p["friction"]} 0.005 0.0001"/></body>'
        for n, r, hl in caps
    )
    return f"""
<mujoco model="garment">
  <option timestep="{dt:.8f}" gravity="{" ".join(f"{g:.6f}" for g in gravity)}" integrator="Euler" solver="CG" jacobian="sparse"/>
  <worldbody>
    {geoms}
    <body name="waist" gravcomp="1">
      <freejoint name="waist"/>
      <geom type="sphere" size="0.05" mass="20" contype="0" conaffinity="0"/>
      <flexcomp name="cloth" type="direct" dim="2" radius="{p["cloth_radius"]}" mass="{p["mass"]}"
                point="{point}" element="{element}">
        <edge equality="true" solref="{p["edge_timeconst"]} 1"/>
        <pin id="{pins}"/>
        <elasticity young="{p["young"]}" poisson="{p["poisson"]}" thickness="{p["thickness"]}"
                    damping="{p["elastic_damping"]}" elastic2d="bend"/>
        <contact selfcollide="{"auto" if p["self_collision"] else "none"}" contype="{int(p["self_collision"])}" conaffinity="1" friction="{p["friction"]} 0.005 0.0001"
                 solref="{p["contact_timeconst"]} 1"/>
      </flexcomp>
    </body>
  </worldbody>
</mujoco>"""


def drive_cloth(pts: np.ndarray, sim_tris: np.ndarray, n_pin: int, p: dict, radii: list[float], joints: np.ndarray,
                joint_rots: np.ndarray, fps: float, limit: float, gravity=(0.0, -9.81, 0.0),
                where: str = "simulate_garment") -> np.ndarray:
    """The cloth `pts` [n,3] (the first pose's pelvis frame; the first `n_pin` vertices are the waist, pinned to the
    pelvis), triangles `sim_tris`, material and solver settings `p` (garment_params' keys), simulated on the skeleton
    joints [F,24,3] / joint_rots [F,24,3,3] at `fps`: the waist follows the pelvis (position + orientation,
    geodesically interpolated over substeps); thighs, shins, hips and torso are kinematic capsules of `radii` (that
    order). The first pose is held for p["preroll"] seconds before frame 0. Returns vertices [F,n,3] (float32,
    world). A vertex farther than `limit` metres from the pelvis, MuJoCo's bad-acceleration warning or a blow-up
    MuJoCo stops raise RuntimeError naming `where` and the frame. The simulated skirt of the scenes (simulate_garment)
    and the model's garment (model/garment.py, its own mesh and fitted material) both run here."""
    n_frames, n_pts = joints.shape[0], len(pts)
    R_pel = joint_rots[:, _PELVIS]  # [F,3,3]

    names, seg_a, seg_b = _capsule_segments(joints)
    seg_len = np.linalg.norm(
        seg_b[0] - seg_a[0], axis=-1
    )  # [C]; bones are rigid, lengths from the first pose
    caps = [(n, r, max(0.5 * float(L), 1e-3)) for n, r, L in zip(names, radii, seg_len)]
    n_sub = max(1, math.ceil(1.0 / (fps * p["dt_max"])))
    dt = 1.0 / (fps * n_sub)
    model = mujoco.MjModel.from_xml_string(_build_xml(pts, sim_tris, n_pin, p, caps, dt, gravity))
    data = mujoco.MjData(model)
    flex_dofs = np.arange(
        6, model.nv
    )  # free joint of the waist first, then 3 slide dofs per free cloth vertex
    vert_mass = model.body_mass[model.dof_bodyid[flex_dofs]]  # [nv-6]
    drag = vert_mass / p["preroll_drag_tau"]
    mocap_ids = [model.body_mocapid[model.body(n).id] for n in names]

    def set_pose(pos, quat, v_world, w_local, cap_pos, cap_quat):
        data.qpos[:3], data.qpos[3:7] = pos, quat
        data.qvel[:3], data.qvel[3:6] = v_world, w_local
        data.mocap_pos[mocap_ids] = cap_pos
        data.mocap_quat[mocap_ids] = cap_quat

    def capsules(a, b):
        """Endpoints a, b: [S,C,3] -> centres [S,C,3], wxyz orientations [S,C,4]."""
        d = b - a
        d = d / np.linalg.norm(d, axis=-1, keepdims=True).clip(1e-9)
        return 0.5 * (a + b), _z_to_dir_quat(d.reshape(-1, 3)).reshape(d.shape[:-1] + (4,))

    def mj(call, frame: int):
        """MuJoCo's `call` (mj_step, mj_forward) at `frame`; a blow-up MuJoCo itself stops (a cloth so far out of
        shape that its contacts overflow the arena) ends as check()'s does, naming the frame."""
        try:
            call(model, data)
        except mujoco.FatalError as e:
            raise RuntimeError(
                f"{where}: cloth simulation unstable at frame {frame} (MuJoCo stopped: "
                f"{str(e).splitlines()[0]}); try a smaller params['dt_max'] or a softer params['young']"
            ) from None

    def step(frame: int):
        data.qfrc_applied[flex_dofs] = -drag * data.qvel[flex_dofs]
        mj(mujoco.mj_step, frame)

    pelvis = joints[:, _PELVIS]  # [F,3]
    q_pel = _quat_wxyz(R_pel)  # [F,4]
    zero = np.zeros(3)
    set_pose(pelvis[0], q_pel[0], zero, zero, *capsules(seg_a[0], seg_b[0]))
    mujoco.mj_forward(model, data)
    flex_start = model.flex_vertadr[0]

    def check(frame: int, when: str = ""):
        """Cloth vertices [n,3] of the current state; RuntimeError naming the frame if it diverged."""
        x = data.flexvert_xpos[flex_start : flex_start + n_pts]
        bad_warn = data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
        dist = np.linalg.norm(x - pelvis[frame], axis=1).max() if np.isfinite(x).all() else np.inf
        if bad_warn > 0 or not dist <= limit:
            raise RuntimeError(
                f"{where}: cloth simulation unstable at frame {frame}{when} (max vertex "
                f"distance from the pelvis {dist:.3g} m, limit {limit:.2f} m; MuJoCo bad-acceleration "
                f"warnings {bad_warn}); try a smaller params['dt_max'] or a softer params['young']"
            )
        return x.copy()

    def record(f: int):
        # mj_step leaves positions computed before its integration; re-pose the waist at frame f exactly and
        # recompute positions so the stored cloth (pinned ring included) belongs to frame f, not one substep earlier.
        set_pose(pelvis[f], q_pel[f], v_prev, w_prev, cap_f_pos[f], cap_f_quat[f])
        mj(mujoco.mj_forward, f)
        out[f] = check(f)

    cap_f_pos, cap_f_quat = capsules(seg_a, seg_b)  # [F,C,3], [F,C,4] at the frames themselves
    n_pre = round(p["preroll"] / dt)
    for i in range(n_pre):
        set_pose(pelvis[0], q_pel[0], zero, zero, cap_f_pos[0], cap_f_quat[0])
        step(0)
        if (i + 1) % n_sub == 0:
            check(0, f" (pre-roll, {(i + 1) * dt:.2f} s)")
    drag = vert_mass / p["drag_tau"]
    out = np.empty((n_frames, n_pts, 3), np.float32)
    v_prev, w_prev = zero, zero
    record(0)
    # Relative pelvis rotation per frame interval (must stay below pi: spins slower than fps/2 turns per second).
    rel = (
        Rotation.from_matrix(np.einsum("fji,fjk->fik", R_pel[:-1], R_pel[1:])).as_rotvec()
        if n_frames > 1
        else None
    )
    s_sub = np.arange(n_sub) / n_sub  # [S] substep fractions within a frame
    for f in range(1, n_frames):
        v_prev = (pelvis[f] - pelvis[f - 1]) * fps
        w_prev = rel[f - 1] * fps  # constant body-frame angular velocity over the frame
        R = R_pel[f - 1] @ Rotation.from_rotvec(s_sub[:, None] * rel[f - 1]).as_matrix()  # [S,3,3] geodesic
        quats = _quat_wxyz(R)
        pos = pelvis[f - 1] + s_sub[:, None] * (pelvis[f] - pelvis[f - 1])  # [S,3]
        lerp = s_sub[:, None, None]
        cap_pos, cap_quat = capsules(
            seg_a[f - 1] + lerp * (seg_a[f] - seg_a[f - 1]), seg_b[f - 1] + lerp * (seg_b[f] - seg_b[f - 1])
        )  # [S,C,3], [S,C,4]
        for k in range(n_sub):
            set_pose(pos[k], quats[k], v_prev, w_prev, cap_pos[k], cap_quat[k])
            step(f)
        record(f)
    return out


def simulate_garment(joints, joint_rots, fps, garment="skirt", params=None, seed=0) -> GarmentSequence:
    """Simulate `garment` on the skeleton `joints` [F,24,3] / `joint_rots` [F,24,3,3] (world, y up) at `fps`.

    The waist ring follows the pelvis (position + orientation, geodesically interpolated over substeps); thighs,
    shins, hips and torso are kinematic capsules. The first pose is held for `preroll` seconds before frame 0 is
    recorded. `seed` only draws the initial jitter (`init_noise`) of the free vertices; the simulation itself is
    deterministic (single-threaded MuJoCo), so equal inputs and seed give bit-identical vertices.
    """
    joints, joint_rots, fps = _validate(joints, joint_rots, fps)
    p = garment_params(garment, params)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed: expected an int, got {seed!r}")  # noqa: TRY004 (contract: bad input -> ValueError)
    rng = np.random.default_rng(int(seed))
    n_frames = joints.shape[0]
    n_a, n_r = p["n_around"], p["n_rings"]

    R_pel = joint_rots[:, _PELVIS]  # [F,3,3]
    pts, sizes = _rest_geometry(joints[0], R_pel[0], p, rng)
    sim_tris, out_tris = tube_topology(n_a, n_r)
    # Outward orientation: check the first triangle's normal against the radial direction at rest.
    t0 = pts[sim_tris[0]]
    nrm = np.cross(t0[1] - t0[0], t0[2] - t0[0])
    up_l = pts[:n_a].mean(0) - pts[-n_a:].mean(0)  # waist centre minus hem centre: the tube's axis
    up_l /= np.linalg.norm(up_l)
    radial = t0.mean(0) - pts[:n_a].mean(0)
    radial -= (radial @ up_l) * up_l
    if nrm @ radial < 0:
        sim_tris = sim_tris[:, [0, 2, 1]]
        out_tris = out_tris[:, [0, 2, 1]]

    radii = [p["thigh_radius"]] * 2 + [p["shin_radius"]] * 2 + [p["hip_radius"], p["torso_radius"]]
    limit = max(1.0, 1.5 * sizes["length"] + sizes["waist_radius"])
    x = drive_cloth(pts, sim_tris, n_a, p, radii, joints, joint_rots, fps, limit)  # [F,n_r*n_a,3]
    out = np.empty((n_frames, n_r, n_a + 1, 3), np.float32)
    out[:, :, :n_a] = x.reshape(n_frames, n_r, n_a, 3)
    out[:, :, n_a] = out[:, :, 0]
    n_sub = max(1, math.ceil(1.0 / (fps * p["dt_max"])))
    dt = 1.0 / (fps * n_sub)

    u = np.arange(n_a + 1) / n_a
    v = np.linspace(0.0, 1.0, n_r)
    uv = (
        np.stack(np.meshgrid(u, v), -1).reshape(-1, 2).astype(np.float32)
    )  # [n_r*(n_a+1),2], row-major by ring
    used = {**p, "garment": garment, "seed": int(seed), "fps": fps, "substeps": n_sub, "dt": dt, **sizes}
    return GarmentSequence(
        name=garment, vertices=out.reshape(n_frames, -1, 3), faces=out_tris, uv=uv, params=used
    )
