"""The map as the relocaliser scores it: the likelihood field, an exhaustive search of the whole map for the best
explanations of a point set (the rival check), and the map's rotational self-matches (its symmetric twins).

Before the relocaliser accepts a pose it asks: is there another place in the map that explains the same evidence
(nearly) as well? The hypotheses it tracks came from keyframe descriptors and markers, so a place no candidate
seeded (the half-turn image of an aisle, far from any keyframe) is simply missing, and "beats every distinct
hypothesis" then holds trivially. This module answers the question over every pose of a coarse grid.

The evidence window is one point set in the robot frame *now* (each evidence scan placed by the odometry between
then and now). Its score at pose (x, y, theta) is ``sum_k F(x + R(theta) p_k)`` over a coarse likelihood field F.
For one heading that is a cross-correlation of F with the image of the rotated points binned to F's cells, so
every position is scored by one FFT product per heading: the cost is (headings) x (FFT of the map), whatever the
number of points. Positions are cell centres of the coarse grid, headings ``headings`` evenly spaced; the best
local maxima (non-maximum suppression in position and heading) are returned for the caller to refine and judge
with its exact score.

The search's coarse peaks are ranked on a coarse field, so in a large warehouse of identical aisles the one rival
that matters most, the winner's image under the map's own half-turn symmetry, can rank below ten look-alikes and be
missed. :func:`rotational_self_matches` finds the map's symmetries once, so the relocaliser can test that twin by
name.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import fft, ndimage, signal

from slam2d.maps.store import MapSnapshot

Array = NDArray[np.float64]


class LikelihoodField:
    """``log(exp(-d^2 / 2 sigma^2) + floor)`` of the static layer's occupied cells, looked up for many points."""

    def __init__(self, snapshot: MapSnapshot, *, sigma_m: float, floor: float, occupied_probability: float) -> None:
        lo = snapshot.occupancy_logodds.astype(np.float64)
        thr = np.log(occupied_probability / (1 - occupied_probability))
        self.occupied = lo > thr
        self.origin = snapshot.occupancy_origin.astype(np.float64)
        self.res = float(snapshot.occupancy_resolution_m)
        d = np.asarray(ndimage.distance_transform_edt(~self.occupied), dtype=np.float64) * self.res
        self.table = np.log(np.exp(-0.5 * (d / sigma_m) ** 2) + floor).astype(np.float32)
        self.outside = float(np.log(floor))
        iy, ix = np.nonzero(self.occupied)
        self.points = self.origin + (np.stack([ix, iy], axis=-1) + 0.5) * self.res

    def _cells(self, xy: Array) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
        ix = np.floor((xy[..., 0] - self.origin[0]) / self.res).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.origin[1]) / self.res).astype(np.int64)
        ny, nx = self.table.shape
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        return np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1), ok

    def __call__(self, xy: Array) -> Array:
        """Log-likelihood of world points (..., 2) -> (...)."""
        iy, ix, ok = self._cells(xy)
        return np.where(ok, self.table[iy, ix].astype(np.float64), self.outside)

    def through(self, origin: Array, xy: Array, margin_m: float) -> NDArray[np.bool_]:
        """Does the segment from ``origin`` (..., 2) to each endpoint ``xy`` (..., B, 2), stopped ``margin_m``
        short, cross an occupied cell? Checked at 4 points along it. -> (..., B)."""
        d = xy - origin[..., None, :]
        r = np.hypot(d[..., 0], d[..., 1])
        scale = np.maximum(r - margin_m, 0.0) / np.maximum(r, 1e-9)
        hit = np.zeros(xy.shape[:-1], dtype=bool)
        for f in (0.25, 0.5, 0.75, 1.0):  # four samples, each one array operation over every beam
            iy, ix, ok = self._cells(origin[..., None, :] + (f * scale)[..., None] * d)
            hit |= ok & self.occupied[iy, ix]
        return hit


def pooled(occupied: NDArray[np.bool_], res_m: float, coarse_m: float) -> tuple[NDArray[np.bool_], float]:
    """``occupied`` pooled to cells of a whole multiple of ``res_m`` near ``coarse_m`` (a coarse cell is occupied when
    any of its cells is; same corner), and that cell's size."""
    f = max(round(coarse_m / res_m), 1)
    ny, nx = occupied.shape
    py, px = -ny % f, -nx % f
    occ = np.pad(occupied, ((0, py), (0, px))).reshape((ny + py) // f, f, (nx + px) // f, f).any(axis=(1, 3))
    return np.asarray(occ, dtype=bool), res_m * f


class CorrelativeSearch:
    """Scores a robot-frame point set at every pose of a coarse grid over the map (see the module docstring).

    ``occupied`` (ny, nx) bool: the map's walls on cells of ``res_m`` with corner ``origin``; ``coarse_m``: the
    search grid's cell (a multiple of ``res_m`` is used); ``sigma_m``, ``floor``: the coarse field
    ``log(exp(-d^2 / 2 sigma^2) + floor)``; ``reach_m``: points farther than this from the robot are left out
    (it bounds the FFT padding); ``headings``: headings tried."""

    def __init__(self, occupied: NDArray[np.bool_], origin: Array, res_m: float, *, coarse_m: float, sigma_m: float,
                 floor: float, reach_m: float, headings: int) -> None:
        occ, self.res = pooled(occupied, res_m, coarse_m)
        self.origin = np.asarray(origin, dtype=np.float64)
        d = np.asarray(ndimage.distance_transform_edt(~occ), dtype=np.float64) * self.res
        # minus the value outside the map, so that the zero padding of the FFT is "outside"
        table = np.log(np.exp(-0.5 * (d / sigma_m) ** 2) + floor) - np.log(floor)
        self.shape = table.shape
        self.reach = int(np.ceil(reach_m / self.res))
        self.fft_shape = (fft.next_fast_len(self.shape[0] + self.reach + 1, real=True),
                          fft.next_fast_len(self.shape[1] + self.reach + 1, real=True))
        self._table_f = fft.rfft2(table, s=self.fft_shape, workers=1)
        self.headings = np.linspace(-np.pi, np.pi, headings, endpoint=False)
        self.reach_m = reach_m

    def best(self, points: Array, weights: Array, count: int, min_xy_m: float, min_theta_rad: float) -> Array:
        """The ``count`` best poses (count, 4: x, y, theta, coarse score) of robot-frame ``points`` (N,2) with
        ``weights`` (N,), best first, no two of them within ``min_xy_m`` and ``min_theta_rad`` of each other."""
        keep = np.hypot(points[:, 0], points[:, 1]) < self.reach_m
        p, w = points[keep], weights[keep]
        ny, nx = self.shape
        fy, fx = self.fft_shape
        per = 4 * count
        found: list[Array] = []
        for th in self.headings:  # one FFT product per heading; the points are one array operation
            c, s = np.cos(th), np.sin(th)
            u = np.rint((c * p[:, 0] - s * p[:, 1]) / self.res).astype(np.int64) % fx
            v = np.rint((s * p[:, 0] + c * p[:, 1]) / self.res).astype(np.int64) % fy
            kernel = np.bincount(v * fx + u, w, minlength=fy * fx).reshape(fy, fx)
            sc = fft.irfft2(np.conj(fft.rfft2(kernel, workers=1)) * self._table_f, s=self.fft_shape,
                            workers=1)[:ny, :nx]
            # this heading's local maxima in position (5 x 5 cells), the best ``per`` of them
            iy, ix = np.nonzero(sc >= ndimage.maximum_filter(sc, size=5, mode="nearest"))
            val = sc[iy, ix]
            top = np.argsort(-val, kind="stable")[:per]
            found.append(np.stack([self.origin[0] + (ix[top] + 0.5) * self.res,
                                   self.origin[1] + (iy[top] + 0.5) * self.res, np.full(len(top), th), val[top]], -1))
        cand = np.vstack(found)
        cand = cand[np.argsort(-cand[:, 3], kind="stable")]
        kept: list[Array] = []
        for c in cand:  # greedy suppression, best first, until ``count`` are kept
            if all(np.hypot(c[0] - k[0], c[1] - k[1]) > min_xy_m
                   or abs(np.angle(np.exp(1j * (c[2] - k[2])))) > min_theta_rad for k in kept):
                kept.append(c)
                if len(kept) == count:
                    break
        return np.asarray(kept, dtype=np.float64).reshape(-1, 4)


def rotational_self_matches(occupied: NDArray[np.bool_], origin: Array, res_m: float, coarse_m: float) -> Array:
    """The map's best match with itself turned by a quarter, half and three-quarter turn: rows (phi, tx, ty,
    overlap), where ``T(p) = R(phi) p + t`` carries the map onto itself and ``overlap`` is the share of its occupied
    coarse cells that land on occupied ones. Racks in identical aisles are typically half-turn symmetric: a pose
    and its image under T then see the same shelves, and only the stock tells them apart.

    Occupied cells are pooled to cells of about ``coarse_m`` (a map drawn with drift is not exactly symmetric);
    each turn's best translation is one FFT correlation of the map with its turned cell centres."""
    occ, res = pooled(occupied, res_m, coarse_m)
    iy, ix = np.nonzero(occ)
    if not len(iy):
        return np.zeros((0, 4))
    # turned about the first cell's centre ``a``, cell centres land on cell centres: integer (x, y) indices
    a = np.asarray(origin, dtype=np.float64) + 0.5 * res
    idx = np.stack([ix, iy], axis=-1)
    out = []
    for k in (1, 2, 3):
        rot = np.array([[0, -1], [1, 0]]) if k == 1 else (-np.eye(2, dtype=np.int64) if k == 2
                                                            else np.array([[0, 1], [-1, 0]]))
        j = idx @ rot.T
        low = j.min(axis=0)
        j = j - low
        image = np.zeros((j[:, 1].max() + 1, j[:, 0].max() + 1))
        image[j[:, 1], j[:, 0]] = 1.0
        # count[n] = sum_k occ[k + n - (shape - 1)] * image[k]: occupied cells hit by the image shifted by that
        count = signal.fftconvolve(occ.astype(np.float64), image[::-1, ::-1], mode="full")
        n = np.array(np.unravel_index(int(np.argmax(count)), count.shape))
        d = n[::-1] - (np.array(image.shape)[::-1] - 1) - low  # the shift in cells, (x, y)
        t = a - rot @ a + d * res  # T(p) = R (p - a) + a + d res
        out.append([k * np.pi / 2, *t, float(np.rint(count.max())) / len(idx)])
    return np.asarray(out, dtype=np.float64)
