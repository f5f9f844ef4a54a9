"""A lidar ray caster for big worlds: only the (beam, segment) pairs that can intersect are tested.

``slam2d.models.lidar.cast_rays`` tests every beam against every segment, O(B x W): fine for a room, ~20 ms per
360-beam scan against the ~2,000 segments of racks, uprights and pallets within 30 m in the challenge warehouse.
Seen from the sensor, a segment covers an arc of directions bounded by its endpoints (shorter than pi unless the
segment passes through the sensor), so with evenly spaced beams it can only be hit by the beams in that arc. We list
those pairs (plus one beam either side against rounding), then run the same intersection arithmetic as
``cast_rays`` on just them: the ranges are bit-identical to the dense caster (tests/unit/test_warehouse.py checks it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.models.lidar import LidarConfig, cast_rays

Array = NDArray[np.float64]


def _candidate_pairs(pose: Array, angles: Array, seg: Array) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """(beam index, segment index) pairs whose beam lies in the segment's arc; None if the beams are not evenly
    spaced (the caller then falls back to the dense caster)."""
    n = len(angles)
    if n < 8:
        return None
    step = (angles[-1] - angles[0]) / (n - 1)
    if step <= 0 or not np.allclose(np.diff(angles), step, rtol=0, atol=1e-9):
        return None
    period = 2 * np.pi / step  # beams per full turn (need not be an integer)
    rel = seg.reshape(-1, 2, 2) - pose[:2]
    phi = np.arctan2(rel[..., 1], rel[..., 0]) - (pose[2] + angles[0])  # (W, 2) endpoint directions
    span = np.mod(phi[:, 1] - phi[:, 0] + np.pi, 2 * np.pi) - np.pi
    lo = np.mod(np.where(span >= 0, phi[:, 0], phi[:, 1]), 2 * np.pi) / step
    first = np.floor(lo).astype(np.int64) - 1
    count = np.ceil(lo + np.abs(span) / step).astype(np.int64) + 1 - first + 1
    # a segment through (or touching) the sensor covers any direction: test it against every beam
    a, e = seg[:, :2] - pose[:2], seg[:, 2:] - seg[:, :2]
    touch = np.abs(a[:, 0] * e[:, 1] - a[:, 1] * e[:, 0]) <= 1e-9 * np.maximum(np.sum(e * e, axis=1), 1e-300)
    first = np.where(touch, 0, first)
    count = np.where(touch, n, count)
    segs = np.repeat(np.arange(len(seg)), count)
    offs = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    k = np.repeat(first, count) + offs
    # the arc may run past the last beam and wrap round to the first ones (or start just below 0): the same
    # directions one turn (period beams, not always a whole number) lower or higher
    beams, owners = [k], [segs]
    for shift in (-period, period):
        below = np.floor(k + shift).astype(np.int64)
        beams += [below, below + 1]
        owners += [segs, segs]
    kb, ob = np.concatenate(beams), np.concatenate(owners)
    ok = (kb >= 0) & (kb < n)
    return kb[ok], ob[ok]


def cast_rays_culled(pose: ArrayLike, angles: ArrayLike, segments: ArrayLike, max_range: float) -> Array:
    """Same contract and same numbers as :func:`slam2d.models.lidar.cast_rays`, cost O(pairs in view)."""
    pose = np.asarray(pose, dtype=np.float64)
    angles = np.asarray(angles, dtype=np.float64)
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    pairs = _candidate_pairs(pose, angles, seg) if len(seg) else None
    if pairs is None:
        return cast_rays(pose, angles, seg, max_range)
    k, j = pairs
    ang = pose[2] + angles[k]
    d0, d1 = np.cos(ang), np.sin(ang)
    a = seg[j, :2]
    e0, e1 = seg[j, 2] - seg[j, 0], seg[j, 3] - seg[j, 1]
    w0, w1 = a[:, 0] - pose[0], a[:, 1] - pose[1]
    denom = d0 * e1 - d1 * e0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w0 * e1 - w1 * e0) / denom
        s = (w0 * d1 - w1 * d0) / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0) & (s >= 0) & (s <= 1)
    out = np.full(len(angles), np.inf)
    np.minimum.at(out, k[hit], t[hit])
    return np.minimum(out, max_range)


def simulate_scan_culled(pose: ArrayLike, segments: ArrayLike, config: LidarConfig,
                         rng: np.random.Generator) -> Array:
    """:func:`slam2d.models.lidar.simulate_scan` on the culled caster (same noise draws, same numbers)."""
    r = cast_rays_culled(pose, config.angles(), segments, config.max_range_m)
    noise = rng.standard_normal(r.shape) * config.range_std_m
    hit = r < config.max_range_m
    return np.where(hit, np.clip(r + noise, 0.0, config.max_range_m), config.max_range_m)
