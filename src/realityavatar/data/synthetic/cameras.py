"""Calibrated cameras on a ring around the subject (world y up; OpenCV: x right, y down, z forward; world-to-camera)."""

from __future__ import annotations

import numpy as np


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera [4,4] for a camera at eye [3] looking at target [3] with world `up` pointing up in the image."""
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, float))
    r /= np.linalg.norm(r)
    d = np.cross(f, r)  # image y points down
    E = np.eye(4)
    E[:3, :3] = np.stack([r, d, f])
    E[:3, 3] = -E[:3, :3] @ np.asarray(eye, float)
    return E


def novel_view_ids(num_cameras: int, num_novel: int) -> list[int]:
    """Held-out cameras spread evenly around the ring, each between training cameras."""
    if not 0 <= num_novel < num_cameras:
        raise ValueError(f"novel_view_cameras: expected 0 <= count < cameras ({num_cameras}), got {num_novel}")
    return sorted({int(np.floor((k + 0.5) * num_cameras / num_novel)) for k in range(num_novel)})


def ring_cameras(num_cameras: int, radius: float, height: float, target_height: float, width: int, height_px: int,
                 subject_height: float = 1.75, fill: float = 0.7, phase_deg: float = 0.0):
    """Ks [C,3,3], viewmats [C,4,4] (world-to-camera) for C cameras evenly on a circle of `radius` at `height`.

    The focal length makes a subject of `subject_height` metres at the ring centre span `fill` of the image height.
    """
    if num_cameras < 1:
        raise ValueError(f"cameras: expected at least 1 camera, got {num_cameras}")
    if width < 8 or height_px < 8:
        raise ValueError(f"resolution: expected width and height >= 8 px, got {width}x{height_px}")
    if radius <= 0:
        raise ValueError(f"camera_radius: expected a positive distance, got {radius}")
    focal = fill * height_px * radius / subject_height
    K = np.array([[focal, 0, width / 2], [0, focal, height_px / 2], [0, 0, 1]], dtype=np.float64)
    Ks, views = [], []
    for i in range(num_cameras):
        a = np.radians(phase_deg) + 2 * np.pi * i / num_cameras
        eye = np.array([radius * np.sin(a), height, radius * np.cos(a)])  # camera 0 in front (+z) of the subject
        views.append(look_at(eye, np.array([0.0, target_height, 0.0])))
        Ks.append(K.copy())
    return np.stack(Ks), np.stack(views)


def eval_cameras(train_viewmats: np.ndarray, heldout_viewmats: np.ndarray, count: int, radius: float, height: float,
                 target_height: float, K: np.ndarray, elevation_deg: float = 40.0, min_sep_deg: float = 30.0):
    """Ks [count,3,3], viewmats [count,4,4] of held-out cameras for evaluation only, as far from the look-at point as
    the ring's: half on the ring's height, half `elevation_deg` above the look-at point, each picked (every 5 degrees
    around) as far as possible from the training cameras, the ring's held-out cameras and the ones already picked, and
    none within `min_sep_deg` of a training camera (the angle between the directions from the look-at point)."""
    import torch

    from realityavatar.geometry import camera_centres

    if count < 0 or count % 2:
        raise ValueError(f"eval_cameras: expected an even count >= 0 (half at each elevation), got {count}")
    target = np.array([0.0, target_height, 0.0])

    def directions_of(points):  # [P,3] -> unit directions from the target [P,3]
        d = points - target
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def directions(viewmats):  # [C,4,4] world-to-camera -> unit directions from the target to the cameras [C,3]
        return directions_of(camera_centres(torch.as_tensor(np.asarray(viewmats, np.float64))).numpy())

    az = np.radians(np.arange(0, 360, 5))
    dist = float(np.hypot(radius, height - target_height))  # the ring cameras' distance: the subject at their scale
    taken = list(directions(train_viewmats))
    n_train = len(taken)
    taken += list(directions(heldout_viewmats))
    views = []
    for e in (np.arctan2(height - target_height, radius), np.radians(elevation_deg)):
        ring = target + dist * np.stack([np.cos(e) * np.sin(az), np.full_like(az, np.sin(e)), np.cos(e) * np.cos(az)], 1)
        cand = directions_of(ring)  # [A,3]; from the points, as the scenes were built (it breaks the ties of equal
        # separation, e.g. 35 and 85 degrees on the demo's ring)
        for _ in range(count // 2):
            sep = np.degrees(np.arccos(np.clip(cand @ np.stack(taken).T, -1, 1)))  # [A,taken]
            ok = sep[:, :n_train].min(1) >= min_sep_deg
            if not ok.any():
                raise ValueError(f"eval_cameras: no place on the ring {min_sep_deg} deg from every training camera")
            i = int(np.argmax(np.where(ok, sep.min(1), -1)))
            taken.append(cand[i])
            views.append(look_at(ring[i], target))
    return np.repeat(np.asarray(K)[None], count, 0), np.stack(views) if views else np.zeros((0, 4, 4))
