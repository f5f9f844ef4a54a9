"""Image and grid features: Harris corners, DoG/LoG blobs, Canny edges, BRIEF binary descriptors and matching.

The detectors themselves are scikit-image's (``corner_harris``/``corner_peaks``, ``blob_dog``/``blob_log``,
``canny``, ``BRIEF``, ``match_descriptors``); this module adds what they lack for SLAM use: frozen configs with the
thresholds as named fields, occupancy grids as detector input (:func:`grid_image`), pixel <-> world coordinates
for a grid, and a precision/recall scorer against known points (:func:`match_points`).

Keypoints are ``(row, col)`` float arrays, as in scikit-image. For an occupancy grid, row = y index and col = x index
(see :mod:`slam2d.maps.occupancy`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from skimage.feature import BRIEF, blob_dog, blob_log, canny, corner_harris, corner_peaks, match_descriptors

from slam2d.config import check_nonnegative, check_positive

Array = NDArray[np.float64]


class GridLike(Protocol):
    """What the grid helpers need (``slam2d.maps.occupancy.OccupancyGrid`` has it; frontend does not import maps)."""

    origin: Array

    @property
    def resolution(self) -> float: ...

    def probability(self) -> Array: ...


@dataclass(frozen=True, slots=True, kw_only=True)
class HarrisConfig:
    """Harris corner detection."""

    sigma_px: float = 1.0
    """Gaussian window of the structure tensor (pixels)."""
    k: float = 0.05
    """Harris sensitivity factor in det(M) - k trace(M)^2."""
    threshold_rel: float = 0.1
    """keep peaks whose response is at least this fraction of the strongest response (0..1)."""
    min_distance_px: int = 3
    """minimum separation between corners (pixels)."""

    def __post_init__(self) -> None:
        check_positive(self, "sigma_px", "k")
        if not 0 <= self.threshold_rel <= 1:
            raise ValueError(f"HarrisConfig.threshold_rel must be in [0, 1] (got {self.threshold_rel})")
        if self.min_distance_px < 1:
            raise ValueError(f"HarrisConfig.min_distance_px must be >= 1 (got {self.min_distance_px})")


@dataclass(frozen=True, slots=True, kw_only=True)
class BlobConfig:
    """Blob detection by difference of Gaussians or Laplacian of Gaussian."""

    method: Literal["dog", "log"] = "dog"
    """'dog' (fast approximation) or 'log' (scale-normalised Laplacian)."""
    min_sigma_px: float = 1.0
    """smallest blob scale (pixels); a blob of radius r has sigma ~ r / sqrt(2)."""
    max_sigma_px: float = 8.0
    """largest blob scale (pixels)."""
    threshold: float = 0.1
    """minimum scale-space response of a blob."""

    def __post_init__(self) -> None:
        if self.method not in ("dog", "log"):
            raise ValueError(f"BlobConfig.method must be 'dog' or 'log' (got {self.method!r})")
        check_positive(self, "min_sigma_px", "max_sigma_px")
        check_nonnegative(self, "threshold")
        if self.max_sigma_px < self.min_sigma_px:
            raise ValueError("BlobConfig.max_sigma_px must be >= min_sigma_px")


def grid_image(grid: GridLike) -> Array:
    """An occupancy grid as a float image in [0, 1]: 1 occupied, 0 free, 0.5 unknown. Shape (rows, cols)."""
    return grid.probability()


def pixels_to_world(grid: GridLike, rc: ArrayLike) -> Array:
    """(row, col) pixel coordinates of ``grid`` to world (x, y) at cell centres. Shapes: (K,2) -> (K,2)."""
    p = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    return grid.origin + (p[:, ::-1] + 0.5) * grid.resolution


def world_to_pixels(grid: GridLike, xy: ArrayLike) -> Array:
    """World (x, y) to fractional (row, col) of ``grid``. Shapes: (K,2) -> (K,2)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return ((p - grid.origin) / grid.resolution - 0.5)[:, ::-1]


def harris_corners(image: ArrayLike, config: HarrisConfig | None = None) -> Array:
    """Harris corners as (row, col), strongest first. Shapes: (H,W) -> (K,2)."""
    cfg = config or HarrisConfig()
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"harris_corners: image must be 2-D (got shape {img.shape})")
    if not np.all(np.isfinite(img)):
        raise ValueError("harris_corners: image contains NaN or inf")
    resp = corner_harris(img, method="k", k=cfg.k, sigma=cfg.sigma_px)
    if resp.max() <= 0:
        return np.zeros((0, 2))
    peaks = corner_peaks(resp, min_distance=cfg.min_distance_px, threshold_rel=cfg.threshold_rel,
                         exclude_border=False)
    order = np.argsort(-resp[peaks[:, 0], peaks[:, 1]], kind="stable")
    return np.asarray(peaks[order], dtype=np.float64).reshape(-1, 2)


def blobs(image: ArrayLike, config: BlobConfig | None = None) -> Array:
    """Blobs as (row, col, sigma). Shapes: (H,W) -> (K,3)."""
    cfg = config or BlobConfig()
    img = np.asarray(image, dtype=np.float64)
    fn = blob_dog if cfg.method == "dog" else blob_log
    out = fn(img, min_sigma=cfg.min_sigma_px, max_sigma=cfg.max_sigma_px, threshold=cfg.threshold)
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


def edges(image: ArrayLike, sigma_px: float = 1.0, low: float | None = None, high: float | None = None
          ) -> NDArray[np.bool_]:
    """Canny edge map. Shapes: (H,W) -> (H,W) bool."""
    return np.asarray(canny(np.asarray(image, dtype=np.float64), sigma=sigma_px, low_threshold=low,
                            high_threshold=high), dtype=bool)


def brief_descriptors(image: ArrayLike, keypoints: ArrayLike, bits: int = 256, patch_px: int = 25,
                      seed: int = 1) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """BRIEF binary descriptors at keypoints (row, col).

    Returns ``(descriptors (K', bits) bool, kept (K,) bool)``: keypoints too close to the border for a full patch
    are dropped. ``seed`` fixes the random test pattern, so descriptors from different images are comparable.
    """
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    if len(kp) == 0:
        return np.zeros((0, bits), dtype=bool), np.zeros(0, dtype=bool)
    ext = BRIEF(descriptor_size=bits, patch_size=patch_px, rng=seed)
    ext.extract(np.asarray(image, dtype=np.float64), kp)
    return np.asarray(ext.descriptors, dtype=bool), np.asarray(ext.mask, dtype=bool)


def match_binary(d1: ArrayLike, d2: ArrayLike, max_ratio: float = 0.8, max_hamming: float = 0.25
                 ) -> NDArray[np.intp]:
    """Hamming-distance matching with cross-check and Lowe's ratio test. Returns index pairs (M,2).

    ``max_hamming`` is the largest accepted distance as a fraction of the descriptor length.
    """
    a, b = np.asarray(d1, dtype=bool), np.asarray(d2, dtype=bool)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), dtype=np.intp)
    return np.asarray(match_descriptors(a, b, metric="hamming", cross_check=True, max_ratio=max_ratio,
                                        max_distance=max_hamming), dtype=np.intp).reshape(-1, 2)


@dataclass(frozen=True)
class PointMatchScore:
    """Detections vs truth at a distance tolerance (one-to-one)."""

    precision: float
    recall: float
    true_positives: int
    detections: int
    truths: int


def match_points(detected: ArrayLike, truth: ArrayLike, tolerance: float) -> PointMatchScore:
    """One-to-one assignment of detections to true points within ``tolerance`` (Hungarian on distance)."""
    d = np.asarray(detected, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    tp = 0
    if len(d) and len(t):
        dist = np.hypot(*(d[:, None] - t[None]).transpose(2, 0, 1))
        cost = np.where(dist <= tolerance, dist, 1e9)
        r, c = linear_sum_assignment(cost)
        tp = int(np.sum(cost[r, c] <= tolerance))
    return PointMatchScore(tp / len(d) if len(d) else 0.0, tp / len(t) if len(t) else 0.0, tp, len(d), len(t))
