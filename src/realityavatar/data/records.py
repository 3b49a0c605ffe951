"""What every reader produces (image records, splits, pose table) and the image path: decode, undistort, resize.

Readers (i3d.py, zju.py) turn an on-disk layout into a `SceneData`; the DataModule turns records into samples.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from realityavatar.data.poses import PoseTable

SPLITS = ("train", "novel_view", "novel_pose")


class SceneFormatError(ValueError):
    """A scene/dataset file exists but its content is not what the layout promises (names the file and field)."""


@dataclass(frozen=True)
class ImageRecord:
    """One image of one camera at one frame. K [3,3] and viewmat [4,4] (world-to-camera, OpenCV) at file resolution."""

    frame: int
    view: int
    image_path: Path
    mask_path: Path
    K: np.ndarray
    viewmat: np.ndarray
    dist: np.ndarray | None = None  # [5] OpenCV (k1, k2, p1, p2, k3) or None
    mask_rule: str = "threshold"  # "threshold": >= 128 of 0..255 (or 1 of 0/1); "nonzero": any label != 0
    garment_path: Path | None = None  # synthetic scenes: the pixels that show the garment (evaluation only)


@dataclass
class SceneData:
    """A whole sequence: image records per split and the poses of every frame of every split."""

    splits: dict[str, list[ImageRecord]]
    poses: PoseTable
    source: str
    meta: dict = field(default_factory=dict)

    def frames(self, split: str) -> np.ndarray:
        return np.unique(np.array([r.frame for r in self.splits.get(split, [])], dtype=np.int64))

    def views(self, split: str) -> list[int]:
        return sorted({r.view for r in self.splits.get(split, [])})


def load_pickle(path: Path, hint: str = "") -> object:
    """Unpickle with errors that name the file (missing file, truncated/corrupt pickle, missing modules)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found{(': ' + hint) if hint else ''}")
    try:
        with open(path, "rb") as f:
            return pickle.load(f, encoding="latin1")
    except ModuleNotFoundError as e:
        raise SceneFormatError(f"{path}: unpickling needs the module {e.name!r}, which is not installed") from e
    except Exception as e:
        raise SceneFormatError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from e


def require_key(d: dict, key: str, path: Path, where: str, expected: str) -> np.ndarray:
    """d[key] as a float64 array, or a SceneFormatError naming the file, the entry and the expected field."""
    if not isinstance(d, dict) or key not in d:
        have = sorted(d.keys()) if isinstance(d, dict) else type(d).__name__
        raise SceneFormatError(f"{path}: {where} lacks key {key!r} (expected {expected}); it has {have}")
    try:
        return np.asarray(d[key], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SceneFormatError(f"{path}: {where}[{key!r}] is not numeric (expected {expected})") from e


def rotation_problem(R: np.ndarray) -> str | None:
    """Why R [3,3] is not a rotation (a camera's world-to-camera block), or None: R R^T = I to 1e-3, det R > 0."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > 1e-3:
        return f"is not a rotation (|R R^T - I| = {err:.3g})"
    return "is a reflection (det < 0), not a rotation" if np.linalg.det(R) < 0 else None


def _last_row_problem(M: np.ndarray) -> str | None:
    """Why M's last row is not that of the identity ([0, 0, 1] of K, [0, 0, 0, 1] of a rigid transform), or None."""
    want = np.eye(M.shape[0])[-1]
    return None if np.allclose(M[-1], want) else f"has a last row {M[-1].tolist()}, not {want.astype(int).tolist()}"


def intrinsics_problem(K: np.ndarray) -> str | None:
    """Why K [3,3] is not a pinhole camera's intrinsics, or None: focal lengths > 0, last row [0, 0, 1]."""
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"has focal lengths fx, fy = {K[0, 0]:g}, {K[1, 1]:g}, expected both > 0"
    return _last_row_problem(K)


def camera_problems(R: np.ndarray, K: np.ndarray) -> list[str]:
    """What is wrong with a camera's world-to-camera rotation R [3,3] and intrinsics K [3,3], each "<field> <why>"."""
    return [f"{field} {why}" for field, why in (("R", rotation_problem(R)), ("K", intrinsics_problem(K))) if why]


def extrinsics_problem(E: np.ndarray) -> str | None:
    """Why E [4,4] is not a rigid world-to-camera transform, or None: a rotation block, last row [0, 0, 0, 1]."""
    return rotation_problem(E[:3, :3]) or _last_row_problem(E)


def check_shape(a: np.ndarray, shape: tuple, path: Path, where: str) -> np.ndarray:
    if a.size == int(np.prod(shape)) and a.shape != shape:
        a = a.reshape(shape)  # e.g. T stored as [3,1] or D as [1,5]
    if a.shape != shape:
        raise SceneFormatError(f"{path}: {where} has shape {a.shape}, expected {shape}")
    if not np.isfinite(a).all():
        raise SceneFormatError(f"{path}: {where} has non-finite values (NaN/inf)")
    return a


# ----------------------------------------------------------------------------------------------------------------
# Image path


def read_image(path: Path) -> np.ndarray:
    """Decode an image file to uint8 [H,W,C] (C = 1, 3 or 4), with an error naming the file when it is unreadable."""
    from PIL import Image

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image {path} not found")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I", "F"):
                a = np.asarray(im).astype(np.float64)
                a = (a / max(a.max(), 1.0) * 255.0).astype(np.uint8)
            elif im.mode in ("L", "RGB", "RGBA"):
                a = np.asarray(im)
            elif im.mode == "P":
                a = np.asarray(im.convert("RGB"))
            else:
                a = np.asarray(im.convert("RGB"))
    except Exception as e:
        raise OSError(f"image {path} is corrupt or not an image ({type(e).__name__}: {e})") from e
    if a.ndim == 2:
        a = a[..., None]
    return np.array(a, copy=True)  # writable: torch.from_numpy needs it


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise FileNotFoundError(f"image {path} not found") from None
    except Exception as e:
        raise OSError(f"image {path} is corrupt or not an image ({type(e).__name__}: {e})") from e


def mask_from_array(m: np.ndarray, rule: str, path: Path) -> np.ndarray:
    """uint8 [H,W,C] -> bool [H,W]."""
    m = m[..., 0] if m.shape[-1] in (1, 3) else m[..., 3]  # RGBA: the alpha channel is the mask
    if rule == "nonzero":
        return m != 0
    if rule == "threshold":
        return m >= (128 if m.max() > 1 else 1)
    raise ValueError(f"{path}: unknown mask rule {rule!r}")


def undistort_grid(K: np.ndarray, dist: np.ndarray, height: int, width: int) -> torch.Tensor:
    """Sampling grid [1,H,W,2] (grid_sample, align_corners=True) that undistorts with the same K, like cv2.undistort."""
    d = np.zeros(5)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if dist.size > 5 and np.abs(dist[5:]).max() > 0:
        raise ValueError(f"distortion {dist.tolist()}: only the 5-parameter model (k1,k2,p1,p2,k3) is supported")
    d[: min(5, dist.size)] = dist[:5]
    k1, k2, p1, p2, k3 = d
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    x, y = (u - cx) / fx, (v - cy) / fy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    ud, vd = fx * xd + cx, fy * yd + cy  # where each undistorted pixel lies in the distorted image
    grid = np.stack([ud / max(width - 1, 1) * 2 - 1, vd / max(height - 1, 1) * 2 - 1], -1)
    return torch.as_tensor(grid, dtype=torch.float32)[None]


_GRID_CACHE: dict[tuple, torch.Tensor] = {}


def load_record(rec: ImageRecord, scale: float = 1.0, undistort: bool = True):
    """Decode, undistort and resize one record.

    Returns image uint8 [H',W',3], mask bool [H',W'], K [3,3] (float64, for the returned resolution).
    """
    img = read_image(rec.image_path)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, -1)
    img = img[..., :3]
    mask = mask_from_array(read_image(rec.mask_path), rec.mask_rule, rec.mask_path)
    if mask.shape != img.shape[:2]:
        raise SceneFormatError(
            f"mask {rec.mask_path} is {mask.shape[1]}x{mask.shape[0]} but image {rec.image_path} is "
            f"{img.shape[1]}x{img.shape[0]}"
        )
    H, W = img.shape[:2]
    K = np.array(rec.K, dtype=np.float64)
    t_img = torch.from_numpy(img).permute(2, 0, 1)[None].float()  # [1,3,H,W]
    grid = _undistortion(rec, K, H, W) if undistort else None
    if grid is not None:
        t_img = F.grid_sample(t_img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    if scale != 1.0:
        h2, w2 = max(1, round(H * scale)), max(1, round(W * scale))
        t_img = F.interpolate(t_img, size=(h2, w2), mode="bilinear", antialias=True, align_corners=False)
        K[0] *= w2 / W  # pixel-area convention (gsplat): scaling the image scales fx, cx exactly
        K[1] *= h2 / H
    img_u8 = t_img[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
    return img_u8, _region(mask, grid, scale), K


def load_garment(rec: ImageRecord, scale: float = 1.0, undistort: bool = True) -> np.ndarray:
    """The record's garment label (synthetic scenes: the pixels that show the garment) as bool [H',W'], undistorted
    and resized as load_record does its mask."""
    label = mask_from_array(read_image(rec.garment_path), "threshold", rec.garment_path)
    H, W = label.shape
    return _region(label, _undistortion(rec, np.asarray(rec.K, dtype=np.float64), H, W) if undistort else None, scale)


def _undistortion(rec: ImageRecord, K: np.ndarray, H: int, W: int) -> torch.Tensor | None:
    """The sampling grid that undistorts record `rec`'s images (cached per camera), None without distortion."""
    if rec.dist is None or not np.abs(rec.dist).max() > 0:
        return None
    key = (K.tobytes(), np.asarray(rec.dist, dtype=np.float64).tobytes(), H, W)
    if key not in _GRID_CACHE:
        _GRID_CACHE[key] = undistort_grid(K, rec.dist, H, W)
    return _GRID_CACHE[key]


def _region(region: np.ndarray, grid: torch.Tensor | None, scale: float) -> np.ndarray:
    """A bool [H,W] mask undistorted (nearest) and resized (area-weighted, then > 0.5) like its image."""
    t = torch.from_numpy(region)[None, None].float()  # [1,1,H,W]
    if grid is not None:
        t = F.grid_sample(t, grid, mode="nearest", padding_mode="zeros", align_corners=True)
    if scale != 1.0:
        H, W = region.shape
        t = F.interpolate(t, size=(max(1, round(H * scale)), max(1, round(W * scale))), mode="bilinear",
                          antialias=True, align_corners=False)
    return (t[0, 0] > 0.5).numpy()


def mask_distance(mask: torch.Tensor | np.ndarray) -> torch.Tensor:
    """mask [H,W] (1 inside) -> Euclidean distance in pixels of every pixel to the nearest mask pixel [H,W] float32
    (zeros for an empty mask). On the host, once per image: the dataset puts it in each sample as `mask_dist`."""
    from scipy.ndimage import distance_transform_edt

    m = np.asarray(mask) > 0.5
    if not m.any():
        return torch.zeros(m.shape, dtype=torch.float32)
    return torch.from_numpy(distance_transform_edt(~m)).float()
