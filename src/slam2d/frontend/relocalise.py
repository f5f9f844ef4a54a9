"""Global relocalisation against a saved map: start at an unknown pose, keep several hypotheses, decide only when one
clearly wins.

The map (:class:`~slam2d.maps.store.MapSnapshot`) gives a likelihood field (the static occupancy layer's occupied
cells, one Euclidean distance transform: ``log(exp(-d^2 / 2 sigma^2) + floor)`` per beam endpoint), keyframes
(pose, scan, place descriptor) and, when the map has them, floor markers (layer ``floor_markers``: row ``i`` is
marker ``i``, NaN where unknown).

Hypotheses (H map-frame poses of the robot *now*) come from

* keyframe descriptors: the keyframes whose descriptor is nearest the current scan's; the heading relative to a
  keyframe from the circular cross-correlation of the two range profiles (an all-round lidar: a rotation is a shift
  of the beams), the position from a small grid of offsets around the keyframe, each then refined on the scan;
* floor markers: an ID'd marker read at ``z`` in the robot frame puts the robot on ``m - R(theta) z`` for every
  heading ``theta``; a ring of headings, refined on the scan (the right heading wins).

Every hypothesis moves with the odometry. Evidence is collected every ``evidence_every_m`` of travel (scans taken at
the same spot are not independent evidence): the scan (``beams`` beams) and the marker readings since the last one.
A hypothesis' score is the tempered log-likelihood of the *whole evidence window* (the last ``window`` evidence
scans, each placed by the hypothesis and the odometry between then and now), so hypotheses born late are judged on
the same evidence as old ones. All of it is one array operation over (hypotheses, scans, beams).

Decision: the best hypothesis is accepted only when (1) at least ``min_evidence`` scans are in the window, (2) its
score beats every *distinct* hypothesis (farther than ``distinct_xy_m`` / ``distinct_theta_rad``) by
``accept_margin``, (3) when the map has floor markers and they are in use (``require_marker``), a marker reading in
the window agrees with it, (4) the rival check passes: an exhaustive search of the whole map for the best
explanations of the evidence window (:mod:`slam2d.frontend.relocalise_search`; the tracked hypotheses came from
descriptors and markers, so a mirror-image place no candidate seeded was simply missing and rule (2) held
trivially) adds its best distinct peaks, refined on the window, to the hypotheses, and the winner must still lead
them by ``accept_margin``; without a marker confirming the winner, so must its images under the map's own quarter,
half and three-quarter turn (``twin_rivals``: the coarse search can rank the half-turn twin below ten look-alikes
in a large warehouse), (5) without a marker confirming it, the lead must survive leaving out the
``robust_objects`` places (``robust_cell_m`` cells) that favour the winner most: in a self-similar warehouse two
places differ by pallets and forklifts, which is what moves between flights, and (6) a verification passes: ICP of
the current scan against the map's occupied cells converges near it with enough inliers. Otherwise the status is
"undecided" and it keeps trying (new candidates are injected every ``inject_every`` evidence scans). In a perfectly
symmetric place two hypotheses keep equal scores and nothing is ever accepted. Measured on the small benchmark
warehouse (half-turn symmetric racks, forklifts, moved pallets; ``benchmarks/warehouse_flights.py``): rules (1)-(3)
and (6) alone accepted the mirror-image place in 1 and 3 of 20 starts without markers; with (4) and (5), none. In
the 100 x 100 m one (``--full``) two starts still accepted the half-turn twin; with ``twin_rivals``, none.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_positive
from slam2d.frontend.icp import ICPConfig, icp, prepare_target
from slam2d.frontend.relocalise_search import CorrelativeSearch, LikelihoodField, rotational_self_matches
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle
from slam2d.log import Step
from slam2d.maps.store import MapSnapshot, range_histogram

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class RelocaliseConfig:
    """Settings of global relocalisation."""

    beams: int = 72
    """beams of each scan used for scoring (evenly subsampled)."""
    sigma_m: float = 0.15
    """spread of the likelihood field around occupied cells (m)."""
    likelihood_floor: float = 0.05
    """added to the field's Gaussian before the log: a beam on a forklift or a moved pallet costs log(floor), not
    minus infinity."""
    occupied_probability: float = 0.65
    """static-layer cells above this probability are walls."""
    through_penalty: float = 0.0
    """extra cost (nats, before tempering) of a beam that passes through a mapped wall before its endpoint. A short
    reading (a forklift, a pallet that arrived) only misses the field; a reading through the map's walls (a pallet
    that left, or the wrong place) is stronger evidence against the pose. 0 (default): off; measured on the small
    warehouse it cost 6x the time and accepted more wrong mirror poses, not fewer."""
    through_margin_m: float = 0.3
    """the pass-through check stops this short of the endpoint (m)."""
    scan_weight: float = 0.1
    """temper of a scan's summed log-likelihood (beams of one scan are not independent)."""
    evidence_every_m: float = 0.25
    """travel between two evidence scans (m) ..."""
    evidence_every_rad: float = 0.25
    """... or turn (rad)."""
    window: int = 40
    """evidence scans a hypothesis is scored on (the newest)."""
    min_evidence: int = 8
    """evidence scans needed before any decision."""
    accept_margin: float = 12.0
    """the winner's score must beat every distinct hypothesis by this (tempered nats)."""
    distinct_xy_m: float = 1.0
    """hypotheses farther apart than this (m) ..."""
    distinct_theta_rad: float = 0.3
    """... or turned more than this (rad) are different answers."""
    merge_xy_m: float = 0.25
    """hypotheses closer than this (m) and ``merge_theta_rad`` are merged (the better kept)."""
    merge_theta_rad: float = 0.08
    """see ``merge_xy_m`` (rad)."""
    max_hypotheses: int = 300
    """at most this many hypotheses are kept (the best)."""
    prune_margin: float = 60.0
    """hypotheses scoring this far below the best are dropped."""
    descriptor_candidates: int = 200
    """keyframes (nearest descriptors) that seed hypotheses."""
    heading_peaks: int = 2
    """headings per keyframe (peaks of the range-profile correlation; an aisle looks alike both ways)."""
    offset_m: float = 0.5
    """positions +- this around a keyframe are tried (m) ..."""
    offset_step_m: float = 0.25
    """... on this grid (m)."""
    marker_headings: int = 72
    """headings tried around a read marker."""
    marker_std_m: float = 0.05
    """standard deviation of a marker reading against a hypothesis (reading noise and odometry drift) (m)."""
    marker_floor: float = -20.0
    """log-likelihood of a marker reading the hypothesis cannot explain (floor)."""
    use_markers: bool = True
    """use floor-marker readings (when the map has markers)."""
    require_marker: bool = True
    """with markers in use: accept only a winner that a marker reading in the window confirms (within 3 sigma).
    Scans alone can prefer the wrong one of two mirror-image places when forklifts and moved pallets spoil the
    evidence (measured: benchmarks/warehouse_flights.py); a read marker id cannot."""
    inject_every: int = 6
    """evidence scans between two rounds of new descriptor candidates while undecided."""
    refine_step_m: float = 0.1
    """first hill-climbing step in x and y (m; halved each round)."""
    refine_step_rad: float = 0.04
    """first hill-climbing step in heading (rad; halved each round)."""
    refine_rounds: int = 3
    """hill-climbing rounds per evidence scan."""
    verify_min_fitness: float = 0.6
    """verification: fraction of the scan's points ICP must match to the map."""
    verify_max_shift_m: float = 0.3
    """verification: ICP may move the winner by at most this (m) ..."""
    verify_max_turn_rad: float = 0.1
    """... and this (rad)."""
    icp: ICPConfig = field(default_factory=lambda: ICPConfig(max_correspondence_m=0.4, trim_fraction=0.8,
                                                             tolerance=1e-4))
    """verification scan matcher."""
    rival_search: bool = True
    """before accepting, search the whole map for the best distinct explanation of the evidence window
    (:mod:`slam2d.frontend.relocalise_search`) and accept only if the winner beats it by ``accept_margin`` too."""
    rival_cell_m: float = 0.2
    """cell of the rival search's position grid (m; a multiple of the map's cell is used)."""
    rival_headings: int = 180
    """headings of the rival search (evenly spaced)."""
    rival_sigma_m: float = 0.3
    """spread of the rival search's coarse likelihood field (m): about its cell and heading step."""
    rival_reach_m: float = 10.0
    """evidence points farther than this from the robot are left out of the rival search (m)."""
    rival_count: int = 10
    """rivals (best distinct coarse peaks) refined on the window and added to the hypotheses."""
    rival_every: int = 4
    """evidence scans between two rival searches (the rivals found are tracked as hypotheses meanwhile; a winner
    with no distinct hypothesis left is always searched)."""
    robust_objects: int = 3
    """without a floor-marker confirmation the winner must beat every distinct hypothesis by ``accept_margin``
    even after the ``robust_objects`` places (cells of ``robust_cell_m``) that favour it most are left out: in a
    self-similar warehouse the places differ by pallets and forklifts, exactly what moves between flights, so a
    win that rests on a few objects is no proof (0: off)."""
    robust_cell_m: float = 2.0
    """size of the places of ``robust_objects`` (m, about a pallet bay)."""
    robust_rivals: int = 20
    """distinct hypotheses (best first) the robust margin is checked against."""
    twin_rivals: bool = True
    """without a floor-marker confirmation, the winner's images under the map's rotational self-matches
    (:func:`~slam2d.frontend.relocalise_search.rotational_self_matches`: a quarter, half and three-quarter turn),
    hill-climbed on the window, join the hypotheses before rule (5), so the winner must beat its symmetric twin by
    ``accept_margin``, also with the ``robust_objects`` places left out. The rival search ranks its peaks on a
    coarse field and can miss that twin in a large warehouse (measured: benchmarks/warehouse_flights.py --full)."""

    def __post_init__(self) -> None:
        check_positive(self, "sigma_m", "likelihood_floor", "scan_weight", "evidence_every_m", "evidence_every_rad",
                       "accept_margin", "distinct_xy_m", "distinct_theta_rad", "merge_xy_m", "merge_theta_rad",
                       "prune_margin", "offset_step_m", "through_margin_m", "marker_std_m", "refine_step_m",
                       "refine_step_rad", "rival_cell_m", "rival_sigma_m", "rival_reach_m", "robust_cell_m",
                       "verify_min_fitness", "verify_max_shift_m", "verify_max_turn_rad")
        for n in ("beams", "window", "min_evidence", "max_hypotheses", "descriptor_candidates", "heading_peaks",
                  "marker_headings", "inject_every", "refine_rounds",
                  "rival_headings", "rival_count", "robust_rivals", "rival_every"):
            if getattr(self, n) < 1:
                raise ValueError(f"RelocaliseConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.min_evidence > self.window:
            raise ValueError(f"RelocaliseConfig.min_evidence ({self.min_evidence}) must be <= window ({self.window})")
        if not 0 < self.occupied_probability < 1:
            raise ValueError("RelocaliseConfig.occupied_probability must be in (0, 1)")
        if self.through_penalty < 0:
            raise ValueError("RelocaliseConfig.through_penalty must be >= 0")
        if self.robust_objects < 0:
            raise ValueError("RelocaliseConfig.robust_objects must be >= 0")
        if self.marker_floor >= 0:
            raise ValueError("RelocaliseConfig.marker_floor must be < 0")


@dataclass(frozen=True)
class RelocaliseStatus:
    """Where relocalisation stands after a step: ``decided`` with ``pose`` (map frame, now) and ``information``
    (3,3) of the verification, else the best guess so far; ``margin`` of the best over the best distinct rival
    (inf when there is none), hypothesis and evidence counts."""

    decided: bool
    pose: Array | None
    margin: float
    hypotheses: int
    evidence: int
    information: Array | None = None


def _scan_xy(ranges: Array, angles: Array, max_range: float,
             idx: NDArray[np.intp]) -> tuple[Array, NDArray[np.bool_]]:
    """Subsampled beam endpoints (len(idx), 2) in the robot frame and their validity mask (hit, finite)."""
    r, a = ranges[idx], angles[idx]
    ok = np.isfinite(r) & (r > 0.05) & (r < max_range)
    r = np.where(ok, r, 0.0)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=-1), ok


class Relocaliser:
    """Multi-hypothesis global relocalisation against one map (see the module docstring).

    ``step(step)`` once per log step (odometry, scan, marker readings) returns a :class:`RelocaliseStatus`;
    ``history`` records every evidence update (step, time, hypotheses, margin, best pose) for reports.
    """

    def __init__(self, snapshot: MapSnapshot, config: RelocaliseConfig | None = None, *,
                 rng: np.random.Generator) -> None:
        self.config = cfg = config or RelocaliseConfig()
        self.map = snapshot
        self.rng = rng  # candidate generation is deterministic today; kept for subsampling ties
        self.field = LikelihoodField(snapshot, sigma_m=cfg.sigma_m, floor=cfg.likelihood_floor,
                                     occupied_probability=cfg.occupied_probability)
        self._icp_target = prepare_target(self.field.points, cfg.icp) if len(self.field.points) else None
        f = self.field
        self._search = CorrelativeSearch(
            f.occupied, f.origin, f.res, coarse_m=cfg.rival_cell_m, sigma_m=cfg.rival_sigma_m,
            floor=cfg.likelihood_floor, reach_m=cfg.rival_reach_m, headings=cfg.rival_headings) \
            if cfg.rival_search and f.occupied.any() else None
        self.rival_searches = 0
        self._twins = rotational_self_matches(f.occupied, f.origin, f.res, cfg.rival_cell_m) \
            if cfg.twin_rivals and f.occupied.any() else np.zeros((0, 4))
        self._searched_at = -(10**9)  # evidence count of the last rival search
        self.robust_margin = float("nan")  # of the last decision that reached the robust check
        markers = snapshot.layers.get("floor_markers")
        self.markers = None if markers is None else np.asarray(markers, dtype=np.float64).reshape(-1, 2)
        self.kf_poses = snapshot.keyframe_poses
        self.kf_desc = self._descriptors()
        self.hyp = np.zeros((0, 3))
        self.score = np.zeros(0)
        self.odo = np.zeros(3)  # robot pose in the session (odometry) frame
        self._last_evidence: Array | None = None
        self._ev_odo: list[Array] = []  # per evidence scan: session pose, points (B,2), mask (B,)
        self._ev_pts: list[Array] = []
        self._ev_ok: list[NDArray[np.bool_]] = []
        self._mk: list[tuple[int, Array, Array, NDArray[np.int64]]] = []  # (evidence no., session pose, xy, ids)
        self.evidence_count = 0
        self.history: list[dict[str, object]] = []
        self.status = RelocaliseStatus(False, None, 0.0, 0, 0)

    # ------------------------------------------------------------------ candidates
    def _descriptors(self) -> Array:
        s = self.map
        d = range_histogram(s.keyframe_scans, s.scan_max_range_m)
        return d if s.descriptors.shape[1] != d.shape[1] else np.asarray(s.descriptors, dtype=np.float64)

    def _circular(self, angles: Array) -> bool:
        """Do the beams cover the whole circle evenly (a rotation is then a shift of the beam index)?"""
        b = len(angles)
        if b < 8 or len(self.map.scan_angles_rad) != b or not np.allclose(angles, self.map.scan_angles_rad):
            return False
        step = 2 * np.pi / b
        return bool(np.allclose(np.diff(angles), step, atol=1e-6))

    def _descriptor_candidates(self, ranges: Array, angles: Array, max_range: float) -> Array:
        """Poses (N,3) around the keyframes whose descriptors are nearest the scan's."""
        cfg = self.config
        if len(self.kf_poses) == 0:
            return np.zeros((0, 3))
        desc = range_histogram(ranges, self.map.scan_max_range_m)
        dist = np.abs(self.kf_desc - desc).sum(axis=1)
        top = np.argsort(dist, kind="stable")[: cfg.descriptor_candidates]
        if self._circular(angles):
            r = np.where(np.isfinite(ranges) & (ranges < max_range), ranges, max_range)
            kf = np.asarray(self.map.keyframe_scans[top], dtype=np.float64)
            kf = np.where(np.isfinite(kf) & (kf < self.map.scan_max_range_m), kf, self.map.scan_max_range_m)
            cur = np.fft.rfft(r - r.mean())
            prof = np.fft.rfft(kf - kf.mean(axis=1, keepdims=True), axis=1)
            corr = np.fft.irfft(np.conj(cur)[None] * prof, n=len(r), axis=1)  # (M, B): shift s -> theta_k + s*step
            b = len(r)
            headings = []
            for _ in range(cfg.heading_peaks):
                s = np.argmax(corr, axis=1)
                headings.append(self.kf_poses[top, 2] + s * 2 * np.pi / b)
                band = (np.arange(b)[None] - s[:, None]) % b
                corr = np.where((band < b // 8) | (band > b - b // 8), -np.inf, corr)
            th = np.stack(headings, axis=1)  # (M, P)
        else:
            th = self.kf_poses[top, 2][:, None] + np.linspace(-np.pi, np.pi, 16, endpoint=False)[None]
        n = round(cfg.offset_m / cfg.offset_step_m)
        off = np.arange(-n, n + 1) * cfg.offset_step_m
        ox, oy = np.meshgrid(off, off, indexing="ij")
        xy = self.kf_poses[top, None, None, :2] + np.stack([ox.ravel(), oy.ravel()], axis=-1)[None, None]
        xy = np.broadcast_to(xy, (len(top), th.shape[1], ox.size, 2))
        tt = np.broadcast_to(th[:, :, None], xy.shape[:3])
        return np.concatenate([xy, tt[..., None]], axis=-1).reshape(-1, 3)

    def _marker_candidates(self, xy: Array, ids: NDArray[np.int64]) -> Array:
        """Poses (N,3) that put the read marker where the map has it, for a ring of headings."""
        if self.markers is None:
            return np.zeros((0, 3))
        ok = (ids >= 0) & (ids < len(self.markers))
        ok[ok] &= np.all(np.isfinite(self.markers[ids[ok]]), axis=1)
        if not ok.any():
            return np.zeros((0, 3))
        th = np.linspace(-np.pi, np.pi, self.config.marker_headings, endpoint=False)
        m, z = self.markers[ids[ok]], xy[ok]
        c, s = np.cos(th)[None], np.sin(th)[None]
        x = m[:, None, 0] - (c * z[:, None, 0] - s * z[:, None, 1])
        y = m[:, None, 1] - (s * z[:, None, 0] + c * z[:, None, 1])
        return np.stack([x, y, np.broadcast_to(th, x.shape)], axis=-1).reshape(-1, 3)

    # ------------------------------------------------------------------ scoring
    def _scan_score(self, poses: Array, pts: Array, ok: NDArray[np.bool_]) -> Array:
        """Tempered log-likelihood of one scan at poses (..., 3) -> (...)."""
        cfg = self.config
        w = se2.transform_points(poses[..., None, :], pts)  # (..., B, 2)
        ll = self.field(w)
        if cfg.through_penalty > 0:
            ll = ll - cfg.through_penalty * self.field.through(poses[..., :2], w, cfg.through_margin_m)
        return cfg.scan_weight * np.sum(ll * ok, axis=-1)

    def _refine(self, poses: Array, pts: Array, ok: NDArray[np.bool_]) -> Array:
        """Hill-climb every pose on one scan: the best of 27 moves per round, steps halved each round."""
        return self._climb(poses, lambda c: self._scan_score(c, pts, ok), self.config.refine_rounds)

    def _climb(self, poses: Array, score: Callable[[Array], Array], rounds: int) -> Array:
        """Hill-climb poses (H,3) on ``score`` ((..., 3) -> (...)): the best of 27 moves a round, steps halved."""
        cfg = self.config
        g = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
        step = np.array([cfg.refine_step_m, cfg.refine_step_m, cfg.refine_step_rad])
        for _ in range(rounds):
            cand = poses[:, None, :] + (g * step)[None]  # (H, 27, 3)
            best = np.argmax(score(cand), axis=1)
            poses = cand[np.arange(len(poses)), best]
            step = step / 2
        poses[:, 2] = wrap_angle(poses[:, 2])
        return poses

    def _window_points(self) -> Array:
        """Every valid point of the evidence window in the robot frame now (each scan placed by the odometry)."""
        rel = se2.between(self.odo[None], np.asarray(self._ev_odo))  # (W,3): evidence pose in the frame now
        w = se2.transform_points(rel[:, None, :], np.asarray(self._ev_pts))  # (W,B,2)
        return w[np.asarray(self._ev_ok)]

    def _rivals(self, best: Array) -> Array:
        """The best explanations of the evidence window anywhere in the map that are distinct from ``best``:
        coarse peaks of the exhaustive search, hill-climbed on the whole window (see ``rival_search``)."""
        cfg = self.config
        assert self._search is not None
        self.rival_searches += 1
        pts = self._window_points()
        # one peak per 2 x distinct_xy_m: a corridor's slides along itself do not fill the list
        peaks = self._search.best(pts, np.full(len(pts), cfg.scan_weight), cfg.rival_count + 1,
                                  2 * cfg.distinct_xy_m, cfg.distinct_theta_rad)[:, :3]
        d = se2.between(best[None], peaks)
        far = (np.hypot(d[:, 0], d[:, 1]) > cfg.distinct_xy_m) | (np.abs(d[:, 2]) > cfg.distinct_theta_rad)
        peaks = peaks[far][: cfg.rival_count]
        if not len(peaks):
            return peaks
        return self._climb(peaks, lambda c: self._window_score(c.reshape(-1, 3)).reshape(c.shape[:-1]),
                           cfg.refine_rounds + 1)

    def _twin_rivals(self, best: Array) -> Array:
        """``best`` carried by each of the map's rotational self-matches, hill-climbed on the window (T,3)."""
        phi, tx, ty = self._twins[:, 0], self._twins[:, 1], self._twins[:, 2]
        cos, sin = np.cos(phi), np.sin(phi)
        twins = np.stack([cos * best[0] - sin * best[1] + tx, sin * best[0] + cos * best[1] + ty,
                          wrap_angle(best[2] + phi)], axis=-1)
        return self._climb(twins, lambda c: self._window_score(c.reshape(-1, 3)).reshape(c.shape[:-1]),
                           self.config.refine_rounds + 1)

    def _window_score(self, hyp: Array) -> Array:
        """Score of every hypothesis on the whole evidence window (and the buffered marker readings)."""
        cfg = self.config
        if not self._ev_odo:
            return np.zeros(len(hyp))
        t_map_session = se2.compose(hyp, se2.inverse(self.odo))  # (H,3)
        odo = np.asarray(self._ev_odo)  # (W,3)
        poses = se2.compose(t_map_session[:, None, :], odo[None])  # (H,W,3)
        score = self._scan_score(poses, np.asarray(self._ev_pts)[None], np.asarray(self._ev_ok)[None]).sum(axis=1)
        if self._mk and self.markers is not None and cfg.use_markers:
            # every buffered reading at once: (H, R) predicted vs read marker positions in the robot frame
            pose_r = np.vstack([np.broadcast_to(p, (len(i), 3)) for _, p, _, i in self._mk])
            xy = np.vstack([x for _, _, x, _ in self._mk])
            ids = np.concatenate([i for _, _, _, i in self._mk])
            known = (ids >= 0) & (ids < len(self.markers))
            known[known] &= np.all(np.isfinite(self.markers[ids[known]]), axis=1)
            if known.any():
                p = se2.compose(t_map_session[:, None, :], pose_r[known][None])  # (H,R,3)
                pred = se2.inverse_transform_points(p, self.markers[ids[known]][None])
                e2 = np.sum((pred - xy[known][None]) ** 2, axis=-1) / cfg.marker_std_m**2
                score = score + np.maximum(-0.5 * e2, cfg.marker_floor).sum(axis=1)
        return np.asarray(score, dtype=np.float64)

    def _merge(self, hyp: Array, score: Array) -> tuple[Array, Array]:
        """Best first; drop hypotheses in an occupied merge cell, far below the best, or over the budget."""
        cfg = self.config
        order = np.argsort(-score, kind="stable")
        hyp, score = hyp[order], score[order]
        key = np.stack([np.floor(hyp[:, 0] / cfg.merge_xy_m), np.floor(hyp[:, 1] / cfg.merge_xy_m),
                        np.floor(wrap_angle(hyp[:, 2]) / cfg.merge_theta_rad)], axis=-1)
        _, first = np.unique(key, axis=0, return_index=True)
        keep = np.sort(first)
        hyp, score = hyp[keep], score[keep]
        if len(score):
            live = score >= score[0] - cfg.prune_margin
            hyp, score = hyp[live], score[live]
        return hyp[: cfg.max_hypotheses], score[: cfg.max_hypotheses]

    # ------------------------------------------------------------------ the step
    def step(self, step: Step) -> RelocaliseStatus:
        """Move every hypothesis by the odometry; on an evidence step rescore, inject, refine and decide."""
        cfg = self.config
        self.odo = se2.compose(self.odo, step.odometry)
        if len(self.hyp):
            self.hyp = se2.compose(self.hyp, step.odometry).reshape(-1, 3)
        new = np.zeros((0, 3))
        if cfg.use_markers and step.markers is not None and len(step.markers):
            self._mk.append((self.evidence_count, self.odo.copy(), step.markers.xy_m.copy(), step.markers.ids.copy()))
            new = self._marker_candidates(step.markers.xy_m, step.markers.ids)
        scan = step.scan
        moved = self._last_evidence is None or (
            np.hypot(*se2.between(self._last_evidence, self.odo)[:2]) >= cfg.evidence_every_m
            or abs(se2.between(self._last_evidence, self.odo)[2]) >= cfg.evidence_every_rad)
        if scan is None or not (moved or len(new)):
            self.status = RelocaliseStatus(False, self.status.pose if not len(self.hyp) else self.hyp[0].copy(),
                                           self.status.margin, len(self.hyp), len(self._ev_odo))
            return self.status
        ranges = np.asarray(scan.ranges_m, dtype=np.float64)
        angles = np.asarray(scan.angles_rad, dtype=np.float64)
        idx = np.unique(np.linspace(0, len(ranges) - 1, min(cfg.beams, len(ranges))).round().astype(np.intp))
        pts, ok = _scan_xy(ranges, angles, float(scan.max_range_m), idx)
        if moved:
            self._last_evidence = self.odo.copy()
            self.evidence_count += 1
            self._ev_odo.append(self.odo.copy())
            self._ev_pts.append(pts)
            self._ev_ok.append(ok)
            if len(self._ev_odo) > cfg.window:
                del self._ev_odo[0], self._ev_pts[0], self._ev_ok[0]
            oldest = self.evidence_count - len(self._ev_odo)
            self._mk = [m for m in self._mk if m[0] >= oldest]
            if (self.evidence_count - 1) % cfg.inject_every == 0:
                new = np.vstack([new, self._descriptor_candidates(ranges, angles, float(scan.max_range_m))])
        if len(new):
            # keep the best of each candidate batch on this scan before refining (refinement costs 27x)
            quick = self._scan_score(new, pts, ok)
            top = np.argsort(-quick, kind="stable")[: 4 * cfg.max_hypotheses]
            self.hyp = np.vstack([self.hyp, new[top]])
        if len(self.hyp):
            self.hyp = self._refine(self.hyp, pts, ok)
            self.hyp, self.score = self._merge(self.hyp, self._window_score(self.hyp))
        self.status = self._decide(step, ranges, angles, float(scan.max_range_m))
        best = None if not len(self.hyp) else self.hyp[0]
        self.history.append({"step": int(step.index), "time_s": float(step.time_s), "hypotheses": len(self.hyp),
                             "evidence": len(self._ev_odo), "margin": float(self.status.margin),
                             "best": None if best is None else [float(v) for v in best],
                             "decided": self.status.decided})
        return self.status

    def _marker_confirmed(self, best: Array) -> bool:
        """True when markers are not required, else when a buffered marker reading agrees with ``best``."""
        cfg = self.config
        if not (cfg.use_markers and cfg.require_marker and self.markers is not None):
            return True
        return self._marker_agrees(best)

    def _marker_agrees(self, best: Array) -> bool:
        """Does a buffered marker reading agree with ``best`` (within 3 sigma)?"""
        cfg = self.config
        if not cfg.use_markers or self.markers is None:
            return False
        t_map_session = se2.compose(best, se2.inverse(self.odo))
        for _, pose_j, xy, ids in self._mk:
            known = (ids >= 0) & (ids < len(self.markers))
            m = self.markers[ids[known]]
            good = np.all(np.isfinite(m), axis=1)
            pred = se2.inverse_transform_points(se2.compose(t_map_session, pose_j), m[good])
            if np.any(np.sum((pred - xy[known][good]) ** 2, axis=-1) <= (3 * cfg.marker_std_m) ** 2):
                return True
        return False

    def _margin(self) -> float:
        """Score of the best hypothesis minus the best distinct one's (inf when there is none)."""
        cfg = self.config
        d = se2.between(self.hyp[0][None], self.hyp[1:]) if len(self.hyp) > 1 else np.zeros((0, 3))
        distinct = (np.hypot(d[:, 0], d[:, 1]) > cfg.distinct_xy_m) | (np.abs(d[:, 2]) > cfg.distinct_theta_rad)
        rival = self.score[1:][distinct]
        return float(self.score[0] - rival.max()) if rival.size else float("inf")

    def _robust_margin(self) -> float:
        """The best hypothesis' lead over the distinct ones when the ``robust_objects`` places that favour it most
        are left out (the minimum over the ``robust_rivals`` best distinct hypotheses; inf when there is none)."""
        cfg = self.config
        d = se2.between(self.hyp[0][None], self.hyp[1:])
        distinct = np.flatnonzero((np.hypot(d[:, 0], d[:, 1]) > cfg.distinct_xy_m)
                                  | (np.abs(d[:, 2]) > cfg.distinct_theta_rad))[: cfg.robust_rivals] + 1
        if not len(distinct):
            return float("inf")
        hyp = self.hyp[np.concatenate([[0], distinct])]
        t_map_session = se2.compose(hyp, se2.inverse(self.odo))  # (R+1,3)
        poses = se2.compose(t_map_session[:, None, :], np.asarray(self._ev_odo)[None])  # (R+1,W,3)
        w = se2.transform_points(poses[..., None, :], np.asarray(self._ev_pts)[None])  # (R+1,W,B,2)
        ll = cfg.scan_weight * self.field(w) * np.asarray(self._ev_ok)[None]
        lead = (ll[0][None] - ll[1:]).reshape(len(distinct), -1)  # (R, W*B) per beam, in the winner's favour
        cell = np.floor(w[0].reshape(-1, 2) / cfg.robust_cell_m).astype(np.int64)
        _, place = np.unique(cell, axis=0, return_inverse=True)
        n = int(place.max()) + 1
        rows = np.arange(len(distinct))[:, None] * n + place.ravel()[None]
        per = np.bincount(rows.ravel(), lead.ravel(), minlength=len(distinct) * n).reshape(len(distinct), n)
        per = -np.sort(-per, axis=1)
        return float(per[:, cfg.robust_objects:].sum(axis=1).min())

    def _join(self, rivals: Array, best: Array, n_ev: int) -> RelocaliseStatus | None:
        """``rivals`` join the hypotheses (tracked from now on); "undecided" unless ``best`` still leads every distinct
        one by ``accept_margin`` (None: it does)."""
        cfg = self.config
        if not len(rivals):
            return None
        self.hyp, self.score = self._merge(np.vstack([self.hyp, rivals]),
                                           np.concatenate([self.score, self._window_score(rivals)]))
        margin = self._margin()
        moved = se2.between(best, self.hyp[0])
        if margin < cfg.accept_margin or np.hypot(moved[0], moved[1]) > cfg.distinct_xy_m \
                or abs(moved[2]) > cfg.distinct_theta_rad:
            return RelocaliseStatus(False, self.hyp[0].copy(), margin, len(self.hyp), n_ev)
        return None

    def _decide(self, step: Step, ranges: Array, angles: Array, max_range: float) -> RelocaliseStatus:
        cfg = self.config
        n_ev = len(self._ev_odo)
        if not len(self.hyp):
            return RelocaliseStatus(False, None, 0.0, 0, n_ev)
        best = self.hyp[0]
        margin = self._margin()
        if n_ev < cfg.min_evidence or margin < cfg.accept_margin or self._icp_target is None \
                or not self._marker_confirmed(best):
            return RelocaliseStatus(False, best.copy(), margin, len(self.hyp), n_ev)
        if self._search is not None and (self.evidence_count - self._searched_at >= cfg.rival_every
                                         or not np.isfinite(margin)):
            self._searched_at = self.evidence_count
            # the rivals join the hypotheses (tracked from now on); the winner must beat them too
            refused = self._join(self._rivals(best), best, n_ev)
            if refused is not None:
                return refused
        confirmed = self._marker_agrees(best)
        if not confirmed and len(self._twins):
            refused = self._join(self._twin_rivals(best), best, n_ev)
            if refused is not None:
                return refused
        if cfg.robust_objects > 0 and not confirmed:
            self.robust_margin = self._robust_margin()
            if self.robust_margin < cfg.accept_margin:
                return RelocaliseStatus(False, best.copy(), margin, len(self.hyp), n_ev)
        ok = np.isfinite(ranges) & (ranges > 0.05) & (ranges < max_range)
        src = np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])], axis=-1)
        res = icp(src, self._icp_target, initial=best, config=cfg.icp)
        e = se2.local(best, res.transform)
        passed = bool(res.converged and res.fitness >= cfg.verify_min_fitness
                      and np.hypot(e[0], e[1]) <= cfg.verify_max_shift_m and abs(e[2]) <= cfg.verify_max_turn_rad
                      and np.all(np.isfinite(res.covariance)))
        if not passed:
            return RelocaliseStatus(False, best.copy(), margin, len(self.hyp), n_ev)
        floor = np.diag([0.02**2, 0.02**2, 0.005**2])
        info = np.asarray(np.linalg.inv(res.covariance + floor), dtype=np.float64)
        return RelocaliseStatus(True, res.transform.copy(), margin, len(self.hyp), n_ev, info)
