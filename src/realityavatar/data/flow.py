"""Optical flow between consecutive training images of one camera, for the flow loss (`flow=dis`).

The photometric loss pulls a Gaussian along the cloth only inside its footprint and only where the texture it covers
differs from its neighbours', so the garment's Gaussians can slide over the cloth (measured: 3.7 cm median material
drift over the spin, `ablations/probe.py`). Image flow says where each pixel's material was one frame earlier; the
module renders the Gaussians' own image motion and matches it (`losses.FlowLoss`).

Flow is OpenCV's DIS (Kroeger et al. 2016) on the luminance, both ways, kept where the two agree (forward-backward
check), inside the eroded mask of the later frame and where the earlier frame's mask holds the match.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

PRESETS = ("ultrafast", "fast", "medium")
SOURCES = ("dis", "files")


@dataclass(frozen=True)
class FlowSpec:
    """How flow pairs are formed and checked (the data side of `flow=dis`)."""

    frame_gap: int = 1  # flow from frame t to frame t - frame_gap of the same camera
    source: str = "dis"  # "dis": computed here; "files": read from `dir` (<dir>/<view:02d>/<frame:06d>.npz)
    dir: str | None = None  # source "files": flow [H,W,2] (pixels, to the earlier frame) and valid [H,W] per image
    preset: str = "medium"  # DIS preset
    fb_tol: float = 1.0  # forward-backward disagreement (pixels, at the training resolution) above which flow is dropped
    erode: int = 1  # pixels of the later frame's mask border left out (flow across the silhouette edge is unreliable)

    def __post_init__(self) -> None:
        if int(self.frame_gap) < 1:
            raise ValueError(f"flow.frame_gap: expected an int >= 1, got {self.frame_gap!r}")
        if self.source not in SOURCES:
            raise ValueError(f"flow.source: expected one of {SOURCES}, got {self.source!r}")
        if self.source == "files" and not (self.dir and Path(self.dir).is_dir()):
            raise ValueError(f"flow.dir: source 'files' needs a folder of <view:02d>/<frame:06d>.npz flow files, "
                             f"got {self.dir!r}")
        if self.preset not in PRESETS:
            raise ValueError(f"flow.preset: expected one of {PRESETS}, got {self.preset!r}")
        if not (np.isfinite(self.fb_tol) and self.fb_tol > 0):
            raise ValueError(f"flow.fb_tol: expected a number > 0, got {self.fb_tol!r}")
        if int(self.erode) < 0:
            raise ValueError(f"flow.erode: expected an int >= 0, got {self.erode!r}")


def _cv2():
    try:
        import cv2
    except ImportError as e:  # pragma: no cover - the dependency is in pyproject.toml
        raise ImportError("flow=dis needs OpenCV: pip install opencv-python-headless (or the package's [flow] extra)") from e
    return cv2


def _gray(img: np.ndarray) -> np.ndarray:
    """[H,W,3] uint8 or float in [0,1] -> [H,W] uint8 luminance."""
    x = img.astype(np.float32)
    if img.dtype != np.uint8:
        x = x * 255.0
    g = 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]
    return np.clip(g + 0.5, 0, 255).astype(np.uint8)


def dis_flow(a: np.ndarray, b: np.ndarray, preset: str = "medium") -> np.ndarray:
    """Dense flow [H,W,2] (x, y in pixels) from image a to image b: pixel p of a shows what b shows at p + flow(p)."""
    cv2 = _cv2()
    code = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
            "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[preset]
    dis = cv2.DISOpticalFlow_create(code)
    return dis.calc(_gray(a), _gray(b), None).astype(np.float32)


def flow_pair(img_t: np.ndarray, mask_t: np.ndarray, img_p: np.ndarray, mask_p: np.ndarray,
              spec: FlowSpec = FlowSpec()) -> tuple[np.ndarray, np.ndarray]:
    """Flow from the later image (t) to the earlier one (p) and where it can be trusted.

    img_* [H,W,3], mask_* [H,W] (bool or 0..1). Returns flow [H,W,2] float32 (pixels) and valid [H,W] bool:
    inside mask_t eroded by spec.erode, forward-backward consistent within spec.fb_tol, and landing inside mask_p.
    """
    cv2 = _cv2()
    if img_t.shape != img_p.shape or img_t.shape[:2] != np.shape(mask_t)[:2] or img_p.shape[:2] != np.shape(mask_p)[:2]:
        raise ValueError(f"flow_pair: image/mask shapes differ: {img_t.shape}, {np.shape(mask_t)}, {img_p.shape}, "
                         f"{np.shape(mask_p)}")
    H, W = img_t.shape[:2]
    fwd = dis_flow(img_t, img_p, spec.preset)  # t -> p
    bwd = dis_flow(img_p, img_t, spec.preset)  # p -> t
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    mx, my = xs + fwd[..., 0], ys + fwd[..., 1]
    back = cv2.remap(bwd, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1e3)
    fb = np.linalg.norm(fwd + back, axis=-1)
    m_t = np.asarray(mask_t) > 0.5
    if spec.erode > 0:
        k = np.ones((2 * spec.erode + 1, 2 * spec.erode + 1), np.uint8)
        m_t = cv2.erode(m_t.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    m_p = (np.asarray(mask_p) > 0.5).astype(np.float32)
    landed = cv2.remap(m_p, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0.99
    valid = m_t & (fb < spec.fb_tol) & landed
    return fwd, valid


def read_flow_file(folder: str | Path, view: int, frame: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flow source "files": <folder>/<view:02d>/<frame:06d>.npz with `flow` [H,W,2] (pixels, from this image to the
    earlier one) and `valid` [H,W]. A missing file means no valid pixel; a wrong size is an error naming the file."""
    path = Path(folder) / f"{int(view):02d}" / f"{int(frame):06d}.npz"
    H, W = shape
    if not path.is_file():
        return np.zeros((H, W, 2), np.float16), np.zeros((H, W), bool)
    with np.load(path) as z:
        if "flow" not in z or "valid" not in z:
            raise ValueError(f"{path}: expected arrays 'flow' [H,W,2] and 'valid' [H,W], found {sorted(z.files)}")
        flow, valid = z["flow"], z["valid"]
    if flow.shape != (H, W, 2) or valid.shape != (H, W):
        raise ValueError(f"{path}: flow {flow.shape} / valid {valid.shape}, but the training image is {W}x{H} "
                         "(flow files must be at the training resolution, data.image_scale included)")
    if not np.isfinite(flow[valid.astype(bool)]).all():
        raise ValueError(f"{path}: non-finite flow at valid pixels")
    return flow.astype(np.float16), valid.astype(bool)
