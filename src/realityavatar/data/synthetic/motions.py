"""Procedural SMPL-order motions modelled on I3D-Human (spin then abrupt stop, sway, arm flapping, walk with turns).

A motion gives body poses [F,24,3] with pose[0] = 0 (EasyMocap style) plus a world placement (Rh, Th) with
x_world = R(Rh) x_body + Th. The world is y up with the ground at y = 0 (the cloth simulator's gravity is -y) and the
body frame is the mannequin's (y up, facing +z), so Rh is the heading (yaw about y).
Frames [0, num_train) are the training part; [num_train, num_train + num_novel) the held-out continuation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

MOTIONS = ("spin", "sway", "flap", "walk")
TWO_PI = 2.0 * np.pi


@dataclass
class Motion:
    """One motion sampled at `fps`. All arrays float64; F = num_train + num_novel."""

    name: str
    fps: float
    pose: np.ndarray  # [F,24,3] axis-angle, body frame, pose[:,0] = 0
    Rh: np.ndarray  # [F,3] world orientation (axis-angle)
    Th: np.ndarray  # [F,3] world translation
    num_train: int
    num_novel: int
    events: dict = field(default_factory=dict)  # e.g. spin start/stop frames, for tests and the metadata

    @property
    def num_frames(self) -> int:
        return self.num_train + self.num_novel


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def rest_pose_arms(arm_down_deg: float, elbow_deg: float = 10.0) -> np.ndarray:
    """Body pose [24,3] with both arms lowered from the T pose by arm_down_deg and elbows slightly bent."""
    p = np.zeros((24, 3))
    a = np.radians(arm_down_deg)
    p[16] = (0, 0, -a)  # left shoulder: the left arm points +x; -z rotation lowers it
    p[17] = (0, 0, a)
    e = np.radians(elbow_deg)
    p[18] = (0, -e, 0)  # elbows bend forward (+z)
    p[19] = (0, e, 0)
    return p


def spin_yaw(t: np.ndarray, start: float, duration: float, turns: int, ramp: float = 0.55,
             stop: float = 0.1) -> np.ndarray:
    """Yaw [F] for `turns` full turns in `duration` s: smooth speed-up, then an abrupt stop over `stop` x duration.

    After the stop the yaw is exactly turns * 2 pi, so the orientation equals the one before the spin.
    """
    dense = np.linspace(0.0, 1.0, 4001)
    speed = np.where(dense < ramp, _smoothstep(dense / ramp), 1.0) * np.where(
        dense > 1 - stop, 1 - _smoothstep((dense - (1 - stop)) / stop), 1.0)
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(dense))])
    angle = angle / angle[-1]
    u = (t - start) / duration
    out = np.interp(np.clip(u, 0.0, 1.0), dense, angle) * turns * TWO_PI
    out[u >= 1.0] = turns * TWO_PI
    return out


def _placement(yaw: np.ndarray, pelvis_world: np.ndarray, pelvis_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rh [F,3], Th [F,3] placing the body's pelvis joint at pelvis_world [F,3] facing yaw [F] (about world y)."""
    yaw = yaw - TWO_PI * np.round(yaw / TWO_PI)  # same yaw modulo a full turn -> bit-identical Rh
    R = Rotation.from_rotvec(np.stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)], -1))
    Rh = R.as_rotvec()
    Th = pelvis_world - R.apply(pelvis_body)
    return Rh, Th


def make_motion(name: str, fps: float, num_train: int, num_novel: int, pelvis_body: np.ndarray,
                pelvis_height: float, seed: int = 0, params: dict | None = None) -> Motion:
    """Build the named motion. pelvis_body [3]: rest pelvis joint (body frame); pelvis_height: standing pelvis height (world y)."""
    if name not in MOTIONS:
        raise ValueError(f"motion: unknown motion {name!r}; expected one of {MOTIONS}")
    if fps <= 0:
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    if num_train < 2 or num_novel < 0:
        raise ValueError(f"frames: expected train_frames >= 2 and novel_frames >= 0, got {num_train}, {num_novel}")
    p = dict(params or {})
    rng = np.random.default_rng(seed)
    # Small per-seed variation of amplitudes and phases: another seed is another take of the same motion.
    jit = lambda: 1.0 + 0.1 * (rng.random() * 2 - 1)
    F = num_train + num_novel
    t = np.arange(F) / fps
    T_train = num_train / fps
    pose = np.repeat(rest_pose_arms(p.get("arm_down_deg", 55.0) * jit())[None], F, 0)
    yaw = np.zeros(F)
    pelvis = np.zeros((F, 3))
    pelvis[:, 1] = pelvis_height
    events: dict = {}

    if name == "spin":
        duration = float(p.get("spin_seconds", 1.1)) * jit()
        turns = int(p.get("turns", 1))
        start = min(0.6, 0.2 * T_train)
        if start + duration > T_train - 0.2:
            raise ValueError(
                f"spin: the training part ({num_train} frames at {fps} fps = {T_train:.2f} s) is too short for "
                f"a {duration:.2f} s spin plus settling; need at least {int(np.ceil((start + duration + 0.2) * fps))}")
        yaw = spin_yaw(t, start, duration, turns)
        stop_frame = int(np.ceil((start + duration) * fps - 1e-9))
        events = {"spin_start_frame": int(np.floor(start * fps)), "spin_stop_frame": stop_frame, "turns": turns,
                  "spin_seconds": duration}
        T_novel = num_novel / fps
        d2 = min(duration, T_novel - 0.3)
        if d2 >= 0.5:  # the continuation spins back the other way
            s2 = T_train + 0.15
            yaw = yaw - spin_yaw(t, s2, d2, turns)
            events["novel_spin_start_frame"] = int(np.floor(s2 * fps))
    elif name == "sway":
        f = p.get("sway_hz", 0.6) * jit()
        amp = np.radians(p.get("sway_deg", 35.0)) * jit()
        ph = TWO_PI * f * t + rng.random() * 0.5
        env = 1.0 + 0.3 * np.sin(TWO_PI * t / max(T_train, 1e-6) * 0.7)  # amplitude drifts: novel frames differ
        yaw = amp * env * np.sin(ph)
        pelvis[:, 0] = 0.06 * np.sin(ph + 0.5)
        # The torso counter-twists and bends sideways; knees bob at twice the sway rate.
        for j in (3, 6, 9):
            pose[:, j, 1] = -0.25 * amp * env * np.sin(ph)
            pose[:, j, 2] = 0.05 * np.sin(ph + 0.3)
        bend = 0.12 * (1 - np.cos(2 * ph))
        pose[:, 4, 0] = pose[:, 5, 0] = bend
        pose[:, 1, 0] = pose[:, 2, 0] = -0.5 * bend
        pose[:, 7, 0] = pose[:, 8, 0] = -0.5 * bend
        pelvis[:, 1] -= 0.05 * bend
    elif name == "flap":
        f = p.get("flap_hz", 1.3) * jit()
        ph = TWO_PI * f * t + rng.random() * 0.5
        lift = np.radians(p.get("flap_deg", 70.0)) * (0.5 - 0.5 * np.cos(ph))  # 0 (arms down) .. flap_deg
        base = np.radians(p.get("arm_down_deg", 55.0))
        pose[:, 16, 2] = -(base - lift)
        pose[:, 17, 2] = base - lift
        # Knees dip on each down-stroke; the bounce drives the cloth vertically.
        bend = 0.18 * (0.5 + 0.5 * np.cos(ph))
        pose[:, 4, 0] = pose[:, 5, 0] = bend
        pose[:, 1, 0] = pose[:, 2, 0] = -0.5 * bend
        pose[:, 7, 0] = pose[:, 8, 0] = -0.5 * bend
        pelvis[:, 1] -= 0.06 * bend
        yaw = 0.3 * np.sin(TWO_PI * 0.2 * t)
    elif name == "walk":
        speed = p.get("walk_speed", 0.7) * jit()
        length = p.get("walk_length", 0.6)
        turn_s = p.get("turn_seconds", 0.8)
        step_hz = p.get("step_hz", 1.8) * jit()
        walk_s = length / speed
        cycle = walk_s + turn_s
        k = np.floor(t / cycle)
        u = t - k * cycle
        walking = u < walk_s
        # Back and forth along world x (yaw pi/2 faces +x), turning 180 degrees to the left at each end.
        s = np.where(walking, u / walk_s, 1.0)
        direction = np.where(k % 2 == 0, 1.0, -1.0)
        pelvis[:, 0] = direction * (-length / 2 + length * s)
        turn = np.where(walking, 0.0, _smoothstep((u - walk_s) / turn_s))
        yaw = np.pi / 2 + np.pi * (k + turn)
        ph = TWO_PI * step_hz * t
        amp = np.where(walking, 1.0, 0.4)  # small steps while turning on the spot
        hip = 0.45 * amp * np.sin(ph)
        pose[:, 1, 0] = -hip
        pose[:, 2, 0] = hip
        pose[:, 4, 0] = 0.6 * amp * np.clip(np.sin(ph - 1.2), 0, None)
        pose[:, 5, 0] = 0.6 * amp * np.clip(-np.sin(ph - 1.2), 0, None)
        # Arms swing against the legs: compose a swing about x with the lowered-arm rotation.
        down = np.radians(p.get("arm_down_deg", 65.0))
        for j, side in ((16, -1.0), (17, 1.0)):
            sw = (0.35 if j == 16 else -0.35) * amp * np.sin(ph)
            swing = Rotation.from_rotvec(np.stack([sw, 0 * sw, 0 * sw], -1))
            pose[:, j] = (swing * Rotation.from_rotvec([0.0, 0.0, side * down])).as_rotvec()
        pose[:, 3, 1] = 0.1 * amp * np.sin(ph)
        pelvis[:, 1] -= 0.02 * (1 - np.cos(2 * ph)) * amp
        events = {"cycle_seconds": cycle}
    Rh, Th = _placement(yaw, pelvis, np.asarray(pelvis_body, dtype=np.float64))
    pose[:, 0] = 0.0
    return Motion(name, float(fps), pose, Rh, Th, num_train, num_novel, events)
