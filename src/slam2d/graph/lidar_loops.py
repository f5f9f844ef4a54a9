"""Verification of one loop candidate of the lidar back end (:mod:`slam2d.graph.lidar`).

A candidate is a new keyframe's scan and an old keyframe's local map (in the old keyframe's frame) with a guess of
their relative pose from the current estimate. :func:`verify_loop` runs the scan-only gates: correlative match
(score, ambiguity), ICP refinement (fitness, residual, covariance), chi-square between the two, and optionally the
wide-window uniqueness search. The result is a :class:`LoopCheck` that says which gate rejected it (``reason``)
and carries every gate's value, so that loop decisions can be audited (``benchmarks/lidar_loop_audit.py``).

:func:`confirmed_mask` picks static structure out of several keyframe scans: the back end verifies a loop in a
self-similar place again on it alone. Why: on the warehouse's middle aisle every false loop (7 of 14 over seeds
0-9) slid 1-2 m along the aisle, matched on a forklift -- the walls say nothing along the aisle, the forklift was
the only thing that did, and it had moved. The correlative ambiguity (0.81-0.88) stayed under its gate, ICP's
covariance looked certain (sigma 2-3 mm), and two such loops agreed with each other because both saw the same
forklift. :func:`weakest_support` (a diagnostic, not a gate) counts the points that constrain a loop in its
weakest direction; it does not separate those loops from right ones (ACES has right corridor loops with fewer).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Generator
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam2d.frontend.correlative import CorrelativeConfig, correlative_match, correlative_stages, run_stages
from slam2d.frontend.icp import ICPTarget, estimate_normals, icp, prepare_target
from slam2d.geometry import se2
from slam2d.graph.lidar_config import LidarSLAMConfig

__all__ = [
    "LoopCheck",
    "StageCosts",
    "agreeing",
    "at_window_edge",
    "confirmed_mask",
    "enqueue",
    "keyframe_points",
    "loop_candidates",
    "loops_agree",
    "loops_agree_many",
    "static_stages",
    "verify_loop",
    "verify_loop_stages",
    "wants_retry",
    "wide_correlative",
]

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class LoopCheck:
    """The outcome of one candidate's verification. ``transform`` is T_old_new (the ICP result when ICP ran, else
    the correlative one), ``information`` (3,3) its information (zeros when rejected before ICP), ``reason`` the
    first gate that rejected it ("" when it passed). Gates not reached hold NaN."""

    transform: Array
    information: Array
    ok: bool
    reason: str
    score: float
    ambiguity: float
    fitness: float = float("nan")
    rmse_m: float = float("nan")
    sigma_m: float = float("nan")
    chi2: float = float("nan")
    support: float = float("nan")

    def rejected(self, reason: str) -> LoopCheck:
        """This check with a later gate's rejection."""
        return replace(self, ok=False, reason=reason)


class StageCosts:
    """CPU times of the last verification stages of each kind ("grid", "scores", "normals", "icp", "mask", the
    values the staged checks yield): the predicted cost of a stage is the longest of the last ``keep`` of its kind
    (0 before the first), so that a 1 ms slice of scores still fits in a scan where a 10 ms mask would not."""

    def __init__(self, keep: int = 4) -> None:
        self._keep = keep
        self._last: dict[str, deque[float]] = {}

    def record(self, kind: str, ms: float) -> None:
        self._last.setdefault(kind, deque(maxlen=self._keep)).append(ms)

    def predicted_ms(self, kind: str) -> float:
        return max(self._last.get(kind, ()), default=0.0)


def verify_loop(pts: Array, target: Array, guess: Array, cfg: LidarSLAMConfig, *, wide: bool = False) -> LoopCheck:
    """Scan-only gates of a loop candidate: the scan ``pts`` (N,2) in its own frame against ``target`` (M,2) in the
    old keyframe's frame, searched around ``guess`` = T_old_new (3,). ``wide``: the second search of a candidate
    the first found nothing for (:func:`wide_correlative`). All at once; :func:`verify_loop_stages` in stages."""
    return run_stages(verify_loop_stages(pts, target, guess, cfg, wide=wide))


def verify_loop_stages(pts: Array, target: Array, guess: Array, cfg: LidarSLAMConfig, *,
                       wide: bool = False) -> Generator[str, None, LoopCheck]:
    """:func:`verify_loop` in stages that pause in between, each pause yielding the kind of the stage that follows:
    the correlative search (its likelihood grid, then its scores split by rotation into ``loop_search_stages``,
    ``loop_retry_stages`` for the wide search: "scores"), then, when the score and ambiguity gates pass, the ICP
    target's normals ("normals"), and ICP with the later gates ("icp")."""
    cc = wide_correlative(cfg) if wide else cfg.correlative
    cm = yield from correlative_stages(pts[::cfg.loop_retry_stride] if wide else pts, target, guess, cc,
                                       stages=cfg.loop_retry_stages if wide else cfg.loop_search_stages)
    base = LoopCheck(cm.transform, np.zeros((3, 3)), False, "", cm.score, cm.ambiguity)
    if cm.score < cfg.loop_min_score:
        return base.rejected("score")
    if wide and at_window_edge(cm.transform, guess, cc):
        return base.rejected("edge")  # the scores still rise at the window's edge: the peak may lie beyond it
    if cm.ambiguity > cfg.loop_max_ambiguity:
        return base.rejected("ambiguity")
    yield "normals"
    prep = prepare_target(target, cfg.loop_icp)
    yield "icp"
    res = icp(pts, prep, initial=cm.transform, config=cfg.loop_icp)
    sigma = float(np.sqrt(np.linalg.eigvalsh(res.covariance[:2, :2])[-1])) \
        if np.all(np.isfinite(res.covariance)) else float("inf")
    base = replace(base, fitness=res.fitness, rmse_m=res.rmse_m, sigma_m=sigma,
                   support=weakest_support(pts, prep, res.transform, cfg))
    if not res.converged:
        return base.rejected("icp")
    if res.fitness < cfg.loop_min_fitness:
        return base.rejected("fitness")
    if res.rmse_m > cfg.loop_max_rmse_m:
        return base.rejected("rmse")
    if not sigma <= cfg.loop_max_sigma_m:
        return base.rejected("sigma")
    floor = np.diag([cfg.min_sigma_xy_m**2, cfg.min_sigma_xy_m**2, cfg.min_sigma_theta_rad**2])
    info = np.asarray(np.linalg.inv(res.covariance + floor), dtype=np.float64)
    e = se2.local(res.transform, cm.transform)
    out = replace(base, transform=res.transform, chi2=float(e @ info @ e),
                  information=se2.covariance_in_frame(info, res.transform[2]))  # in the between factor's frame
    if out.chi2 > cfg.loop_chi2:
        return out.rejected("chi2")
    if cfg.loop_wide_window_m > 0 and not unique_in_wide_window(pts, target, res.transform, cfg):
        return out.rejected("wide")
    return replace(out, ok=True)


def keyframe_points(kf_points: list[Array], poses: Array, lo: int, hi: int, frame: Array | None = None) -> Array:
    """The points of keyframes lo..hi-1 (``kf_points``: each in its own frame) placed at ``poses``, in ``frame``
    (world when None)."""
    pts = [se2.transform_points(poses[j], kf_points[j]) for j in range(max(lo, 0), min(hi, len(poses)))]
    out = np.vstack(pts) if pts else np.zeros((0, 2))
    return out if frame is None else se2.inverse_transform_points(frame, out)


def static_stages(kf_points: list[Array], poses: Array, c: int, k: int, chk: LoopCheck, cfg: LidarSLAMConfig, *,
                  wide: bool = False) -> Generator[str, None, LoopCheck]:
    """Loop (old keyframe ``c``, new keyframe ``k``) in a self-similar place, verified again on what two keyframes
    saw on the same surface (:func:`confirmed_mask`; a moving object may be all that breaks the tie): the old
    keyframe's local map, the new scan against the keyframes just before it. ``kf_points``: each keyframe's scan
    points in its frame, ``poses`` the keyframe poses, ``chk`` the check so far (returned as it is when
    ``loop_static_radius_m`` is 0). Stages: the new scan's mask ("mask"), the old local map's ("mask"), then the
    check (its likelihood grid: "grid", then see :func:`verify_loop_stages`)."""
    if cfg.loop_static_radius_m <= 0:
        return chk
    yield "mask"
    m, r, a, s = cfg.loop_map_keyframes, cfg.loop_static_radius_m, cfg.loop_static_normal_rad, cfg.loop_static_seen_m
    old = [keyframe_points(kf_points, poses, j, j + 1, poses[c]) for j in range(max(c - m, 0), min(c + m + 1, k))]
    pts = kf_points[k]
    new = [pts] + [keyframe_points(kf_points, poses, j, j + 1, poses[k]) for j in range(max(k - m, 0), k)]
    static_pts = pts[confirmed_mask(new, r, a, s)[:len(pts)]]
    yield "mask"
    static_old = np.vstack(old)[confirmed_mask(old, r, a, s)]
    yield "grid"
    return (yield from verify_loop_stages(static_pts, static_old, se2.between(poses[c], poses[k]), cfg, wide=wide))


def loop_candidates(poses: Array, k: int, pose: Array, cfg: LidarSLAMConfig) -> list[int]:
    """Old keyframes (of the keyframe ``poses``) to verify against new keyframe ``k`` at ``pose``: within
    ``loop_radius_m``, at least ``loop_min_separation`` keyframes older, nearest first, one per local map, at most
    ``loop_candidates``."""
    old = k - cfg.loop_min_separation
    if old <= 0:
        return []
    dist = np.hypot(*(poses[:old, :2] - pose[:2]).T)
    near = np.flatnonzero(dist < cfg.loop_radius_m)
    cand: list[int] = []
    for c in near[np.argsort(dist[near], kind="stable")].tolist():
        if all(abs(c - o) > cfg.loop_map_keyframes for o in cand):
            cand.append(c)
        if len(cand) == cfg.loop_candidates:
            break
    return cand


def enqueue(queue: deque[tuple[int, int, Array, int, bool, bool]],
            entry: tuple[int, int, Array, int, bool, bool]) -> None:
    """Insert a loop candidate (old kf, new kf, poses, due scan, wide retry?, may it be retried?) into ``queue`` in
    the order (due scan, first search before wide retry, arrival): the order decisions are made in, which no stage
    timing may move."""
    at = next((i for i, e in enumerate(queue) if (e[3], e[4]) > (entry[3], entry[4])), len(queue))
    queue.insert(at, entry)


def wants_retry(chk: LoopCheck, guess: Array, cfg: LidarSLAMConfig) -> bool:
    """Should a candidate's first check ``chk`` be followed by the wide search (``loop_retry_window_m``)? When it
    matched nothing but its best try lay at the window's edge: the scores were still rising, the match may lie
    beyond (a return after a long drive)."""
    return cfg.loop_retry_window_m > 0 and chk.reason == "score" and chk.score > 0 and at_window_edge(
        chk.transform, guess, cfg.correlative)


def at_window_edge(t: Array, guess: Array, cc: CorrelativeConfig) -> bool:
    """Is the correlative match ``t`` within one coarse step of the edge of its search window around ``guess``?
    Then the scores were still rising there, and the best alignment may lie beyond the window."""
    return bool(np.max(np.abs(t[:2] - guess[:2])) > cc.window_xy_m - cc.coarse_cells * cc.resolution_m)


def wide_correlative(cfg: LidarSLAMConfig) -> CorrelativeConfig:
    """The correlative search of a loop candidate's second try: +- ``loop_retry_window_m``, and only rivals that are
    peaks of their own count toward the ambiguity (``CorrelativeConfig.ambiguity_peaks``). A return after a long
    drive can be farther off than the first window; the wider window then holds a corridor's axis, along which the
    scores stay high (plain ambiguity 0.92-0.98 on ACES's return) but fall off from the right match without a second
    peak, where a parallel identical aisle or a repeating rack is a peak of its own."""
    return replace(cfg.correlative, window_xy_m=cfg.loop_retry_window_m, ambiguity_peaks=True,
                   coarse_cells=cfg.loop_retry_step_cells)


def confirmed_mask(clouds: list[Array], radius_m: float, max_normal_angle_rad: float,
                   seen_m: float) -> NDArray[np.bool_]:
    """Which points of ``clouds`` (keyframe scans in one frame; mask over their concatenation) are not contradicted
    by another cloud. A point is contradicted when another cloud has points within ``seen_m`` of it (it looked
    there) but none within ``radius_m`` whose normal is within ``max_normal_angle_rad`` of the point's (it saw no
    such surface there). A moving object is seen at a different place by each keyframe and drops out (a parked one
    stays); a surface seen by one keyframe only stays; the normal test keeps the end face of an object that slid
    along its own side from being confirmed by that side."""
    if not clouds:
        return np.zeros(0, dtype=bool)
    normals = np.concatenate([estimate_normals(c) if len(c) >= 2 else np.zeros((len(c), 2)) for c in clouds])
    points = np.concatenate(clouds)
    owner = np.repeat(np.arange(len(clouds)), [len(c) for c in clouds])
    cos_max = np.cos(max_normal_angle_rad)
    seen = np.zeros(len(points), dtype=bool)
    confirmed = np.zeros(len(points), dtype=bool)
    start = 0
    for j, cj in enumerate(clouds):  # every other cloud's points against cloud j, in one query
        nj, start = normals[start:start + len(cj)], start + len(cj)
        if not len(cj):
            continue
        others = np.flatnonzero(owner != j)
        kk = min(4, len(cj))
        d, idx = cKDTree(cj).query(points[others], k=kk, distance_upper_bound=seen_m)
        d, idx = d.reshape(len(others), kk), idx.reshape(len(others), kk)
        seen[others] |= np.isfinite(d[:, 0])
        near = d < radius_m
        nb = nj[np.minimum(idx, len(cj) - 1)]  # (N,k,2); missing neighbours are masked by near
        confirmed[others] |= np.any(near & (np.abs(np.einsum("nkd,nd->nk", nb, normals[others])) >= cos_max), axis=1)
    return confirmed | ~seen


def weakest_support(pts: Array, target: ICPTarget, t: Array, cfg: LidarSLAMConfig) -> float:
    """How many matched points constrain the alignment ``t`` in its weakest translational direction ``u`` (the
    eigenvector of sum n n^T over the ICP's final matches, n the target normal at each match): the matches whose
    normal lies within 60 degrees of ``u``. An aisle's walls constrain nothing along it, and the point-to-line
    Hessian does not show it: with 5-neighbour normals a few degrees off, a wall's hundred points add up to a
    dozen points' worth of constraint along the aisle, and ICP's covariance, scaled by a 1 cm residual, looks sure."""
    if target.normals is None or not len(pts):
        return 0.0
    c = cfg.loop_icp
    d, j = target.tree.query(se2.transform_points(t, pts), distance_upper_bound=c.max_correspondence_m)
    ok = np.flatnonzero(np.isfinite(d))
    ok = ok[np.argsort(d[ok], kind="stable")[:max(int(np.ceil(c.trim_fraction * len(ok))), 1)]]
    n = target.normals[j[ok]]
    u = np.linalg.eigh(n.T @ n)[1][:, 0]
    return float(np.count_nonzero(np.abs(n @ u) >= 0.5))


def unique_in_wide_window(pts: Array, target: Array, t: Array, cfg: LidarSLAMConfig) -> bool:
    """Is ``t`` the only good alignment within ``loop_wide_window_m``? A coarse correlative search over the wide
    window (every third point, coarse steps of ``loop_wide_step_cells`` cells): a parallel identical aisle lies
    outside the verification window but inside this one, and scores as well."""
    wide = replace(cfg.correlative, window_xy_m=cfg.loop_wide_window_m, coarse_cells=cfg.loop_wide_step_cells,
                   max_refined=1)
    return correlative_match(pts[::3], target, t, wide).ambiguity <= cfg.loop_wide_max_ambiguity


def loops_agree(old: tuple[int, int, Array], new: tuple[int, int, Array], p: Array, cfg: LidarSLAMConfig) -> bool:
    """Do two verified loops (c1, k1, T_c1_k1) and (c2, k2, T_c2_k2) agree? Going from c1 to the new keyframe
    through the first loop and the tracked chain must land where the old chain c1 -> c2 and the second loop
    put it (a wrong loop among identical places agrees with a right one only by accident). ``p``: the keyframe
    poses when the second loop was queued (k1 <= k2, so they hold every keyframe involved)."""
    (c1, k1, t1), (c2, k2, t2) = old, new
    return bool(loops_agree_many(np.array([c1]), np.array([k1]), np.asarray(t1)[None], (c2, k2, t2), p, cfg)[0])


def loops_agree_many(c1: NDArray[np.int64], k1: NDArray[np.int64], t1: Array, new: tuple[int, int, Array], p: Array,
                     cfg: LidarSLAMConfig) -> NDArray[np.bool_]:
    """:func:`loops_agree` of M first loops (c1 (M,), k1 (M,), T_c1_k1 (M,3)) with one second loop at once."""
    c2, k2, t2 = new
    lhs = np.where((k1 == k2)[:, None], t1, se2.compose(t1, se2.between(p[k1], p[k2])))
    rhs = se2.compose(se2.between(p[c1], p[c2]), t2)
    e = se2.local(lhs, rhs)
    return ~((c1 == c2) & (k1 == k2)) & (np.hypot(e[:, 0], e[:, 1]) <= cfg.loop_pair_xy_m) \
        & (np.abs(e[:, 2]) <= cfg.loop_pair_theta_rad)


def agreeing(pool: list[tuple[int, int, Array, Array, bool, Array]], loop: tuple[int, int, Array], snap: Array,
             cfg: LidarSLAMConfig) -> list[bool]:
    """Which loops of ``pool`` (entries (c, k, T, information, accepted, keyframe poses when queued)) agree with
    the verified ``loop`` (c, k, T) queued at keyframe poses ``snap`` (:func:`loops_agree`). A retry is decided
    after loops of later keyframes: each pair is judged on the later one's poses."""
    c, k, _ = loop
    out = [False] * len(pool)
    earlier = [i for i, q in enumerate(pool) if q[1] <= k]
    if earlier:  # judged on this loop's poses: all at once
        many = loops_agree_many(np.array([pool[i][0] for i in earlier]), np.array([pool[i][1] for i in earlier]),
                                np.array([pool[i][2] for i in earlier]), loop, snap, cfg)
        for i, a in zip(earlier, many.tolist(), strict=True):
            out[i] = a
    for i, q in enumerate(pool):
        if q[1] > k:
            out[i] = loops_agree(loop, q[:3], q[5], cfg)
    return out
