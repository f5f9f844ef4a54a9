"""Lidar SLAM as an estimator (``--estimator lidar``): scan-to-local-map tracking, keyframes, verified loop closures
and an incremental pose graph; its map is an occupancy grid.

Per step (one scan):

1. tracking (:mod:`slam2d.graph.lidar_tracking`): point-to-line ICP against the local map (the newest
   ``local_map_keyframes`` keyframes at their current estimates) from the previous pose composed with the step's
   odometry; a poor fit is redone from a correlative search; a failed match keeps the odometry guess (counted);
2. keyframes: when the tracked pose moved ``keyframe_distance_m`` or turned ``keyframe_angle_rad`` since the last
   keyframe, the scan becomes a keyframe: a node of the pose graph with a relative-pose edge from the previous
   keyframe (the tracking covariance rotated into that keyframe's frame, floored);
3. loop closures (every ``loop_every`` keyframes): old keyframes within ``loop_radius_m`` of the new one (and at
   least ``loop_min_separation`` keyframes older) are queued as candidates; each scan runs
   ``loop_verify_per_scan`` verification stages (more while the next one is predicted to end under
   ``loop_budget_ms`` of CPU), against a local map around the old keyframe: correlative matching over a window
   (:mod:`slam2d.frontend.correlative`; a high score and no rival alignment nearly as good: identical aisles,
   corridor axes; ``loop_retry_window_m``: a search that matched nothing, its best try at the window's edge, runs
   again over that window as a candidate of its own, only rival peaks counting), ICP refinement; a loop in a
   self-similar place (ambiguity above ``loop_static_ambiguity``) is verified again on static structure only, the
   points no other keyframe contradicts (:mod:`slam2d.graph.lidar_loops`: a moving forklift can break an aisle's
   tie); a verified loop is accepted once a second one agrees with it; its decision enters the graph a fixed
   ``loop_queue`` scans after queueing (results independent of the schedule);
4. the keyframe and its edges enter :class:`~slam2d.graph.incremental.IncrementalPoseGraph`: a local solve when a
   loop enters, then ``loop_full_iterations`` whole-graph Gauss-Newton iterations, one per scan, one every
   ``graph.full_every`` keyframes, the whole graph to convergence in ``finalize`` (bounded work per scan).

Floor markers (when steps carry readings): marker nodes in the graph, each reading a factor from its keyframe, a
marker read again long after a loop-like solve (:mod:`slam2d.graph.lidar_markers`).

Every scan's pose is its keyframe's estimate composed with its tracked pose relative to that keyframe, so the whole
trajectory follows the graph, and its ``pose_cov`` is its marginal there (:mod:`~slam2d.graph.lidar_covariance`).
Steps without a scan are placed by odometry.

**Lifelong mode** (``layers`` set, ``--estimator lidar-lifelong``): every scan is localised against the static layer
of :mod:`slam2d.maps.layers`, keyframes are culled by coverage, loop closure is off (:mod:`slam2d.graph.lidar_lifelong`
says how and why).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Generator

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import Diagnostics, Estimate, EstimatorLifecycle, LoopEvent
from slam2d.frontend.correlative import run_stages
from slam2d.frontend.icp import ICPTarget, prepare_target
from slam2d.frontend.scan import scan_points
from slam2d.geometry import se2
from slam2d.graph import lidar_loops
from slam2d.graph.incremental import IncrementalPoseGraph
from slam2d.graph.lidar_config import LidarSLAMConfig, LifelongLidarConfig
from slam2d.graph.lidar_covariance import PoseCovariance
from slam2d.graph.lidar_lifelong import LifelongMarkers, MarkerSurvey
from slam2d.graph.lidar_loops import LoopCheck, enqueue, static_stages, verify_loop_stages, wants_retry
from slam2d.graph.lidar_markers import KeyframeMarkers, MarkerPoseGraph
from slam2d.graph.lidar_tracking import good_fit, track_scan
from slam2d.log import Scan, Step
from slam2d.maps.layers import DYNAMIC, LayerStats, MapLayers, PoseBuffer
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid

__all__ = ["LidarSLAM", "LidarSLAMConfig", "LifelongLidarConfig", "scan_points"]

Array = NDArray[np.float64]


class LidarSLAM(EstimatorLifecycle):
    """The lidar SLAM back end (see the module docstring)."""

    def __init__(self, config: LidarSLAMConfig | None = None) -> None:
        self.config = config or LidarSLAMConfig()
        self.layers: MapLayers | None = None

    # ------------------------------------------------------------------ lifecycle
    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        self._lifecycle_reset()
        self._pose = np.asarray(initial_pose, dtype=np.float64).copy()
        self._cov, self._index = np.zeros((3, 3)), -1  # the last scan match's covariance (world); last step index
        self._pose_cov_of = PoseCovariance(self.config.min_sigma_xy_m, self.config.min_sigma_theta_rad)
        self._motion = np.zeros(3)  # the last tracked motion (scan to scan): the steady guess repeats it
        self.graph: IncrementalPoseGraph | None = None  # created with the first keyframe
        self._kf_step: list[int] = []  # step index of each keyframe
        self._kf_points: list[Array] = []  # scan-frame points of each keyframe
        self._kf_scans: list[Scan] = []
        self._driven_m: list[float] = []  # distance driven (along the keyframe edges) up to each keyframe
        self._last_loop_kf = 0  # newest keyframe of a loop that entered the graph: drift restarts there
        self._owner = [-1]  # per pose (step 0..t): its keyframe (-1: none yet, ``_rel`` is then the world pose)
        self._rel = [self._pose.copy()]
        self._target: ICPTarget | None = None
        self._target_poses, self._target_span = np.zeros((0, 3)), (0, 0)  # the keyframes the target was made for
        self._version, self._target_version = 0, -1  # bumped whenever keyframe estimates change; the target's
        self._traj_cache: tuple[int, Array] | None = None
        self._new_loops: tuple[LoopEvent, ...] = ()
        # verified loops of the last ``loop_pair_keyframes`` keyframes: (old kf, new kf, T, information, accepted)
        self._pool: list[tuple[int, int, Array, Array, bool, Array]] = []  # ..., the poses it was verified at
        # loop candidates awaiting verification: (old kf, new kf, the keyframe poses when they were queued, the scan
        # their decision enters the graph, wide retry?, may it be retried?), and decisions awaiting that scan: (scan,
        # events, loops)
        self._queue: deque[tuple[int, int, Array, int, bool, bool]] = deque()
        self._active: tuple[int, int, Array, int, Generator[str, None, LoopCheck]] | None = None  # in verification
        self._next_stage, self._stage_costs = "grid", lidar_loops.StageCosts()  # next stage's kind; costs by kind
        self._decided: deque[tuple[int, list[LoopEvent], list[tuple[int, int, Array, Array]]]] = deque()
        self._full_pending, self._started = 0, 0.0  # whole-graph GN iterations owed after a loop; step's start
        self.loops_dropped = self.loops_retried = 0  # candidates refused (loop_queue in flight), searched again wider
        self._live: deque[int] = deque()  # when the candidates in flight are due
        self.tracking_failures = self.rematches = 0  # rematches: replaced by a correlative re-match (lidar_tracking)
        self.loops_accepted = self.loops_rejected = self.steps = 0
        self.layers = None if self.config.layers is None else MapLayers(self.config.layers)
        self._poses = PoseBuffer()  # lifelong mode: every pose (the keyframes never move there)
        self._poses.append(self._pose)
        self._labels: tuple[Array, NDArray[np.int8]] = (np.zeros((0, 2)), np.zeros(0, np.int8))
        self._kf_xy, self.dynamic_points_total = np.zeros((0, 2)), 0
        self.markers = KeyframeMarkers(self.config.markers)  # floor markers (graph/lidar_markers.py)
        c = self.config
        self._lifelong_markers = None if not (c.surveyed_markers or c.map_unsurveyed_markers) else LifelongMarkers(
            MarkerSurvey(c.surveyed_markers), map_unsurveyed=c.map_unsurveyed_markers,
            camera_var=c.markers.camera.std_m**2, survey_var=c.survey_sigma_m**2,
            match_floor=np.diag([c.marker_match_sigma_xy_m**2, c.marker_match_sigma_xy_m**2,
                                 c.marker_match_sigma_theta_rad**2]))

    @property
    def keyframe_poses(self) -> Array:
        return np.zeros((0, 3)) if self.graph is None else self.graph.poses

    @property
    def keyframe_steps(self) -> NDArray[np.int64]:
        return np.asarray(self._kf_step, dtype=np.int64)

    def step(self, step: Step) -> None:
        self._check_step()
        self._started = time.thread_time()  # the loop work's budget counts from here (loop_budget_ms)
        self._index = step.index
        self._step_scan(step)
        if step.markers is not None and self.config.markers.enabled and self.layers is None \
                and isinstance(self.graph, MarkerPoseGraph) \
                and self.markers.observe(self.graph, self._owner[-1], self._rel[-1], step.markers):
            self._version += 1  # a re-sighting moved the keyframes
            self._pose = se2.compose(self.graph.poses[self._owner[-1]], self._rel[-1])

    def _step_scan(self, step: Step) -> None:
        cfg = self.config
        self.steps += 1
        self._new_loops = ()
        guess = se2.compose(self._pose, step.odometry)
        pts = None if step.scan is None else scan_points(step.scan, cfg.min_range_m, cfg.max_range_m)
        if self.layers is not None:
            self._step_lifelong(step, guess, pts)
            return
        if pts is None or len(pts) < cfg.icp.min_matches:
            self._place(step.index, guess)
            return
        if self.graph is None:  # the first scan anchors the graph at its odometry pose
            self._pose = guess
            self._add_keyframe(step.index, guess, pts, step.scan, None, np.zeros((3, 3)))
            return
        prior = None if cfg.track_prior_xy == cfg.track_prior_theta == 0.0 else \
            np.array([cfg.track_prior_xy, cfg.track_prior_xy, cfg.track_prior_theta])
        tr = track_scan(pts, self._local_target(), guess, cfg.icp, cfg.min_fitness, cfg.track_rematch_rmse_m,
                        cfg.track_correlative, cfg.track_rematch_points, se2.compose(self._pose, self._motion), prior)
        self.rematches += tr.replaced
        res = tr.match
        if good_fit(res, cfg.min_fitness, np.inf):
            pose, cov = res.transform, res.covariance
        else:
            self.tracking_failures += 1
            pose, cov = guess, np.diag([0.2, 0.2, 0.05]) ** 2  # the odometry guess, loosely
        self._motion = se2.between(self._pose, pose)
        last = self.graph.poses[-1]
        d = se2.between(last, pose)
        if np.hypot(d[0], d[1]) >= cfg.keyframe_distance_m or abs(d[2]) >= cfg.keyframe_angle_rad:
            self._add_keyframe(step.index, pose, pts, step.scan, d, cov)
        else:
            self._place(step.index, pose)
        self._cov = cov
        self._loop_work(cfg.loop_verify_per_scan)

    # ------------------------------------------------------------------ lifelong mode
    def _step_lifelong(self, step: Step, guess: Array, pts: Array | None) -> None:
        """Track against the static layer, label the points, update both layers, keyframe by coverage."""
        cfg, lay = self.config, self.layers
        assert lay is not None
        pose, cov = guess, self._cov
        if pts is not None and len(pts) >= cfg.icp.min_matches:
            first = lay.integrations == 0  # the first scan is the map: nothing to localise against yet
            if not first:
                sel = pts[np.unique(np.linspace(0, len(pts) - 1, min(len(pts), cfg.match_points)).astype(np.int64))]
                m = lay.match(sel[lay.classify(guess, sel) != DYNAMIC], guess)  # dynamic points never pull
                if m.constrained and m.inliers >= cfg.min_inliers:
                    pose, cov = m.pose, m.covariance
                else:
                    self.tracking_failures += 1
                    cov = np.diag([0.2, 0.2, 0.05]) ** 2
            if step.markers is not None and self._lifelong_markers is not None and cfg.markers.enabled:
                # the pose corrected by the floor-marker readings, before drawing: the layers follow the survey
                pose, cov = self._lifelong_markers.correct(pose, cov, step.markers.ids, step.markers.xy_m)
            labels = lay.classify(pose, pts)
            lay.integrate(pose, pts, labels, step.time_s, bootstrap=first)
            self._labels = (pts, labels)
            self.dynamic_points_total += int(np.count_nonzero(labels == DYNAMIC))
            near = np.einsum("ij,ij->i", self._kf_xy - pose[:2], self._kf_xy - pose[:2])
            self._pose_cov_of.in_layer(near, cov, new := not len(near) or float(near.min()) >= cfg.coverage_m**2)
            if new:
                self._add_coverage_keyframe(step.index, pose, pts, step.scan, cov)
        self._pose, self._cov = pose, cov
        self._poses.append(pose)

    def _add_coverage_keyframe(self, index: int, pose: Array, pts: Array, scan: Scan | None, cov: Array) -> None:
        """A keyframe on new ground, joined to the previous keyframe by the tracked relative pose."""
        cfg = self.config
        k = len(self._kf_step)
        if self.graph is None:
            self.graph = MarkerPoseGraph(pose, cfg.graph)
        else:
            prev = self.graph.poses[-1]
            info = np.asarray(np.linalg.inv(self._pose_cov_of.edge(prev, cov)[None]), np.float64)
            self.graph.add_step(k, np.array([k - 1]), np.array([k]), se2.between(prev, pose)[None], info)
        assert scan is not None
        self._kf_step.append(index)
        self._kf_points.append(pts)
        self._kf_scans.append(scan)
        self._kf_xy = np.vstack([self._kf_xy, pose[None, :2]])

    def map_layers(self) -> MapLayers:
        """The static and dynamic layers (lifelong mode only)."""
        if self.layers is None:
            raise ValueError("LidarSLAM.map_layers: lifelong mode is off (set LidarSLAMConfig.layers)")
        return self.layers

    def last_labels(self) -> tuple[Array, NDArray[np.int8]]:
        """The last processed scan's robot-frame points (K,2) and their labels (K,) (lifelong mode; see
        :meth:`slam2d.maps.layers.MapLayers.classify`)."""
        return self._labels

    def layer_stats(self) -> LayerStats:
        """Counters of the lifelong mode (zeros when it is off)."""
        lay = self.layers
        if lay is None:
            return LayerStats()
        return LayerStats(keyframes=len(self._kf_step), static_cells=int(np.count_nonzero(lay.static)),
                          promoted=lay.promoted, demoted=lay.demoted,
                          dynamic_points_last=int(np.count_nonzero(self._labels[1] == DYNAMIC)),
                          dynamic_points_total=self.dynamic_points_total, grid_bytes=lay.nbytes(),
                          tracking_failures=self.tracking_failures,
                          marker_fixes=0 if self._lifelong_markers is None else self._lifelong_markers.fixes,
                          markers_mapped=0 if self._lifelong_markers is None else self._lifelong_markers.mapped)

    def _pose_cov(self) -> Array:
        """The pose's marginal in the graph, in lifelong mode its uncertainty in the static layer
        (:mod:`~slam2d.graph.lidar_covariance`); before the first keyframe, the last scan match's covariance."""
        if self.layers is not None:
            return self._pose_cov_of.current.copy()
        if self.graph is None or self._owner[-1] < 0:
            return self._cov.copy()
        k = self._owner[-1]
        return self._pose_cov_of.at(self.graph.poses[k], self._rel[-1], self._cov, self._kf_step[k] == self._index)

    def _place(self, index: int, pose: Array) -> None:
        """A non-keyframe pose: stored relative to the newest keyframe."""
        self._pose = pose
        self._owner.append(-1 if self.graph is None else len(self._kf_step) - 1)
        self._rel.append(pose.copy() if self.graph is None else se2.between(self.graph.poses[-1], pose))

    def _add_keyframe(self, index: int, pose: Array, pts: Array, scan: Scan | None, z: Array | None,
                      cov: Array) -> None:
        cfg = self.config
        k = len(self._kf_step)
        if self.graph is None:
            self.graph = MarkerPoseGraph(pose, cfg.graph)
        self._kf_step.append(index)
        self._kf_points.append(pts)
        assert scan is not None
        self._kf_scans.append(scan)
        self._driven_m.append(0.0 if z is None else self._driven_m[-1] + float(np.hypot(z[0], z[1])))
        self._owner.append(k)
        self._rel.append(np.zeros(3))
        if z is None:
            self._pose = pose
            return
        prev = self.graph.poses[-1]
        edge_cov = self._pose_cov_of.edge(prev, cov)
        info = np.asarray(np.linalg.inv(edge_cov[None]), np.float64)
        before = self.graph.local_solves, self.graph.full_solves
        self.graph.add_step(k, np.array([k - 1]), np.array([k]), np.asarray(z)[None], info)
        self._pose_cov_of.keyframe_added(prev, np.asarray(z), edge_cov, self.graph.newest_covariance())
        if (self.graph.local_solves, self.graph.full_solves) != before:
            self._version += 1
        self._pose = self.graph.poses[-1].copy()
        if cfg.loop_closure and k % cfg.loop_every == 0:
            cands = lidar_loops.loop_candidates(self.graph.poses, k, pose, cfg)
            snap = self.graph.poses.copy() if cands else None  # what a verification right now would see
            while self._live and self._live[0] <= self.steps:
                self._live.popleft()
            for c in cands:  # at most loop_queue in flight (queued, not yet due), however fast they are verified
                if len(self._live) >= cfg.loop_queue:
                    self.loops_dropped += 1
                    continue
                assert snap is not None
                self._live.append(self.steps + cfg.loop_queue)
                enqueue(self._queue, (c, k, snap, self.steps + cfg.loop_queue, False, self._may_retry(k)))

    # ------------------------------------------------------------------ loop work, bounded per scan
    def _loop_work(self, verifications: int, *, flush: bool = False) -> None:
        """One scan's share of the loop work: a whole-graph Gauss-Newton iteration if a loop still owes some, the
        decisions that are due entered (``flush``: everything now), ``verifications`` verification stages of queued
        candidates and more while the scan's CPU time plus the next stage's predicted cost
        (:class:`~slam2d.graph.lidar_loops.StageCosts`) is under ``loop_budget_ms``: no scan pays for a whole search.
        Schedule independence: a candidate is verified against the keyframe poses of the moment it was queued,
        and its decision enters the graph exactly ``loop_queue`` scans after that moment (a candidate still
        unverified then is finished at once), so the loops and the trajectory do not depend on how the stages
        were spread over scans (a candidate is refused when ``loop_queue`` are in flight; counted)."""
        assert self.graph is not None
        moved = False
        if self._full_pending:
            summary = self.graph.solve_full(1)
            # converged (the step changed the cost too little): the rest of the owed iterations are not needed
            self._full_pending = 0 if summary.termination != "max iterations" else self._full_pending - 1
            moved = True
            exact = self.graph.newest_covariance() if not self._full_pending else None  # once the loop is in
            if exact is not None:
                self._pose_cov_of.keyframe = exact
        # due decisions enter first, so that the budget below counts their graph update (7-13 ms a scan on fr079)
        events, entered = self._enter_due(flush)
        done, budget = 0, self.config.loop_budget_ms  # verification stages run in this scan, CPU budget (ms)
        while (self._active or self._queue) and (
                done < verifications or flush or (self._active or self._queue[0])[3] <= self.steps
                or 1e3 * (time.thread_time() - self._started)
                + self._stage_costs.predicted_ms(self._next_stage if self._active else "grid") < budget):
            if self._active is None:
                if not flush and self._queue[0][3] - self.config.loop_queue > self.steps:
                    break  # a wide retry waits until no candidate queued later can be due before it
                c, k, snap, due, wide, may_retry = self._queue.popleft()
                self._active = (c, k, snap, due, self._check_stages(c, k, snap, wide, may_retry=may_retry))
            done += 1
            kind, began, chk = self._next_stage, time.thread_time(), None
            try:
                self._next_stage = next(self._active[4])
            except StopIteration as stop:
                self._next_stage, chk = "grid", stop.value
            self._stage_costs.record(kind, 1e3 * (time.thread_time() - began))
            if chk is not None:
                c, k, snap, due, _ = self._active
                self._active = None
                if chk.reason == "retry":  # a candidate of its own, due loop_queue scans later: no crowded due scan
                    enqueue(self._queue, (c, k, snap, due + self.config.loop_queue, True, True))
                    self.loops_retried += 1
                    continue
                self._decided.append((due, *self._decide(c, k, chk.transform, chk.information, chk.ok, snap)))
        late, entered_late = self._enter_due(flush)  # those of candidates finished at once in this scan
        events, moved = events + late, moved or entered or entered_late
        self.loops_accepted += sum(e.accepted for e in events)
        self.loops_rejected += sum(not e.accepted for e in events)
        self._new_loops = tuple(events)
        if moved:  # the current pose follows its keyframe
            self._version += 1
            self._pose = se2.compose(self.graph.poses[self._owner[-1]], self._rel[-1])

    def _enter_due(self, flush: bool) -> tuple[list[LoopEvent], bool]:
        """Enter the decisions due by now (``flush``: all) in the order made: their events, whether a loop entered."""
        assert self.graph is not None
        events: list[LoopEvent] = []
        entered = False
        while self._decided and (flush or self._decided[0][0] <= self.steps):
            _, evs, loops = self._decided.popleft()
            events += evs
            for c, k, t_ck, info in loops:
                self.graph.add_loop(c, k, t_ck, info)
                self._last_loop_kf = max(self._last_loop_kf, k)
                entered = True
                self._full_pending = self.config.loop_full_iterations
        return events, entered

    def _decide(self, c: int, k: int, t_ck: Array, info: Array, ok: bool,
                snap: Array) -> tuple[list[LoopEvent], list[tuple[int, int, Array, Array]]]:
        """Accept a verified loop (c, k) once another verified loop agrees with it (``loop_confirmations``); a
        waiting loop that this one confirms enters too. ``snap``: the keyframe poses when (c, k) was queued.
        Returns the decisions and the loops (old kf, new kf, T, information) to enter the graph."""
        cfg = self.config
        self._pool = [q for q in self._pool if k - q[1] <= cfg.loop_pair_keyframes]
        partners = [q for q, agree in zip(self._pool, lidar_loops.agreeing(self._pool, (c, k, t_ck), snap, cfg),
                                          strict=True) if agree] if ok else []
        accept = ok and (cfg.loop_confirmations == 0 or bool(partners))
        events = [LoopEvent(self._kf_step[c], self._kf_step[k], accept, t_ck)]
        loops = [(c, k, t_ck, info)] if accept else []
        for q in partners:
            if not q[4]:  # a waiting loop confirmed by this one enters the graph too
                loops.append((q[0], q[1], q[2], q[3]))
                events.append(LoopEvent(self._kf_step[q[0]], self._kf_step[q[1]], True, q[2]))
                self._pool[self._pool.index(q)] = (*q[:4], True, q[5])
                accept = True
        if ok:
            self._pool.append((c, k, t_ck, info, accept, snap))
        return events, loops

    # ------------------------------------------------------------------ maps
    def _local_target(self) -> ICPTarget:
        key = hash((len(self._kf_step), self._version))
        if self._target is not None and self._target_version == key:
            return self._target
        assert self.graph is not None
        n = len(self._kf_step)
        lo = max(n - self.config.local_map_keyframes, 0)
        now = self.graph.poses[lo:n]
        old = self._target_poses
        if self._target is not None and len(old) == len(now) and self._target_span == (lo, n):
            # the keyframes only moved (a graph solve): when they moved together, move the target with them
            d = se2.compose(now, se2.inverse(old))
            dev = se2.local(d[0], d)
            if np.all(np.hypot(dev[:, 0], dev[:, 1]) < 1e-3) and np.all(np.abs(dev[:, 2]) < 2e-4):
                self._target = self._target.moved(d[0])
                self._target_poses, self._target_version = now.copy(), key
                return self._target
        pts = lidar_loops.keyframe_points(self._kf_points, self.graph.poses, lo, n)
        self._target = prepare_target(pts, self.config.icp)
        self._target_poses, self._target_span, self._target_version = now.copy(), (lo, n), key
        return self._target

    # ------------------------------------------------------------------ loops
    def _may_retry(self, k: int) -> bool:
        """May keyframe ``k``'s loop candidates get the wide retry? Only after ``loop_retry_after_m`` of driving
        since the newest loop entered the graph: sooner, the drift cannot have outgrown the first window."""
        return self._driven_m[k] - self._driven_m[self._last_loop_kf] >= self.config.loop_retry_after_m

    def _search_loops(self, k: int) -> list[tuple[int, LoopCheck]]:
        """Verify every candidate of keyframe ``k`` now: (old keyframe, its check)."""
        assert self.graph is not None
        snap, may_retry = self.graph.poses.copy(), self._may_retry(k)
        cands = lidar_loops.loop_candidates(snap, k, snap[k], self.config)
        return [(c, self._check_candidate(c, k, snap, may_retry)) for c in cands]

    def _check_candidate(self, c: int, k: int, poses: Array, may_retry: bool = True) -> LoopCheck:
        """Every gate of a loop candidate, with the values it saw, all stages at once (see ``_check_stages``)."""
        return run_stages(self._check_stages(c, k, poses, may_retry=may_retry))

    def _check_stages(self, c: int, k: int, poses: Array, wide: bool | None = None, *,
                      may_retry: bool = True) -> Generator[str, None, LoopCheck]:
        """Every gate of a loop candidate (:mod:`slam2d.graph.lidar_loops`), as stages that pause in between, each
        pause yielding the kind of the stage that follows (:class:`~slam2d.graph.lidar_loops.StageCosts`; the first
        is "grid": the local map and its likelihood grid); returns the check. ``poses`` are the keyframe poses when
        the candidate was queued: the guess, the old local map and the new keyframe's neighbours all come from them,
        so a candidate verified scans later is decided exactly as it would have been at once (the graph moves in
        between). ``wide``: None runs a wide retry inline (a check at once), False returns it as a "retry" rejection
        for the scheduler to queue, True is that queued retry; ``may_retry`` False: no retry at all."""
        cfg = self.config
        m, pose, pts = cfg.loop_map_keyframes, poses[k], self._kf_points[k]
        guess = se2.between(poses[c], pose)
        target = lidar_loops.keyframe_points(self._kf_points, poses, c - m, c + m + 1, poses[c])
        if not wide:
            chk = yield from verify_loop_stages(pts, target, guess, cfg)
            if not (may_retry and wants_retry(chk, guess, cfg)):
                if chk.ok and chk.ambiguity > cfg.loop_static_ambiguity:
                    chk = yield from static_stages(self._kf_points, poses, c, k, chk, cfg)
                return chk
            if wide is False:  # best try at the window's edge: the wide search is queued as a candidate of its own
                return chk.rejected("retry")
        chk = yield from verify_loop_stages(pts, target, guess, cfg, wide=True)
        return (yield from static_stages(self._kf_points, poses, c, k, chk, cfg, wide=True)) if chk.ok else chk

    def close_loop_now(self, z: Array) -> bool:
        """Search loops for the newest keyframe now (the lab's "close loop now"); ``z`` (the newest landmark
        observations) is not used: the scan of the newest keyframe is matched. True when a loop was accepted."""
        self._check_step()
        if self.graph is None or len(self._kf_step) < 2:
            return False
        k = len(self._kf_step) - 1
        found = [(c, chk) for c, chk in self._search_loops(k) if chk.ok]
        events = [LoopEvent(self._kf_step[c], self._kf_step[k], True, chk.transform) for c, chk in found]
        if found:
            # the incremental graph takes edges only with a new pose: re-anchor through a whole-graph solve
            for c, chk in found:
                self.graph.add_loop(c, k, chk.transform, chk.information)
            self._version += 1
            self._pose = self.graph.poses[-1].copy()
            self.loops_accepted += len(found)
        self._new_loops = self._new_loops + tuple(events)
        return bool(found)

    # ------------------------------------------------------------------ outputs
    def trajectory(self) -> Array:
        """Every pose so far (T+1,3): each scan's keyframe estimate composed with its pose relative to it."""
        if self.layers is not None:
            return self._poses.array()
        n = len(self._owner)
        if self._traj_cache is not None and self._traj_cache[0] == hash((n, self._version, len(self._kf_step))):
            return self._traj_cache[1]
        owner = np.asarray(self._owner, dtype=np.int64)
        rel = np.asarray(self._rel, dtype=np.float64).reshape(-1, 3)
        out = rel.copy()
        has = owner >= 0
        if has.any():
            out[has] = se2.compose(self.keyframe_poses[owner[has]], rel[has])
        self._traj_cache = (hash((n, self._version, len(self._kf_step))), out)
        return out

    def estimate(self) -> Estimate:
        self._check_ready()
        return Estimate(
            pose=self._pose.copy(),
            pose_cov=self._pose_cov(),
            trajectory=self.trajectory().copy() if self._finalized else None,
            new_loops=self._new_loops,
            diagnostics=Diagnostics(optimizations=0 if self.graph is None else self.graph.local_solves
                                    + self.graph.full_solves, loops_accepted=self.loops_accepted,
                                    loops_rejected=self.loops_rejected,
                                    dropped_observations=self.tracking_failures),
        )

    def finalize(self) -> None:
        if self._lifecycle_finalize() and self.graph is not None and self.graph.num_poses > 1 \
                and self.layers is None:
            self._loop_work(0, flush=True)  # the candidates of the last keyframes are still owed a decision
            self.graph.finalize()
            self._version += 1
            self._pose = self.trajectory()[-1].copy()
        self._new_loops = ()

    def occupancy_grid(self, resolution_m: float | None = None) -> OccupancyGrid:
        """The map: every keyframe scan at its estimated pose in a log-odds grid (no-return beams clear nothing:
        through windows and doors they would paint fans of free space outside)."""
        if self.graph is None:
            raise ValueError("LidarSLAM.occupancy_grid: no scan yet")
        if self.layers is not None:
            return self.layers.static_grid()
        poses = self.keyframe_poses
        world = lidar_loops.keyframe_points(self._kf_points, poses, 0, len(poses))
        grid = OccupancyGrid.around(np.vstack([world, poses[:, :2]]), 1.0,
                                    OccupancyConfig(resolution_m=resolution_m or self.config.map_resolution_m,
                                                    free_range_cap_m=0.0))
        for p, s in zip(poses, self._kf_scans, strict=True):
            grid.update(p, s.ranges_m, s.angles_rad, min(s.max_range_m, self.config.max_range_m))
        return grid

    # ------------------------------------------------------------------ saved maps
    # (one block, added for saved maps and relocalisation; used by slam2d.graph.lidar_session)
    def keyframe_scans(self) -> list[Scan]:
        """The scan of every keyframe, in keyframe order."""
        return list(self._kf_scans)

    def pose_graph_edges(self) -> tuple[NDArray[np.int64], Array, Array]:
        """The keyframe graph's edges: keyframe pairs (E,2), relative poses (E,3), information (E,3,3)."""
        g = None if self.graph is None else self.graph.graph()
        if g is None or "between" not in g.kinds():
            return np.zeros((0, 2), np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
        b = g.block("between")
        return np.asarray(b.keys.T, dtype=np.int64).reshape(-1, 2), b.z.copy(), b.information

    def seed_prior_layers(self, layers: MapLayers, keyframe_poses: Array) -> None:
        """Lifelong mode from a saved map: right after ``reset(pose)`` at the relocalised pose, localise against
        ``layers`` (a saved static layer, :meth:`MapLayers.from_saved`) instead of bootstrapping a new one. The
        map's keyframes (``keyframe_poses`` (K,3)) only count as coverage: no keyframe is added on ground they
        cover; the keyframes of this run form their own graph (the map never moves in this mode)."""
        self._check_step()
        if self.layers is None:
            raise ValueError("LidarSLAM.seed_prior_layers: lifelong mode is off (set LidarSLAMConfig.layers)")
        if self.graph is not None or self.steps:
            raise ValueError("LidarSLAM.seed_prior_layers: call it right after reset(), before any step")
        self.layers = layers
        self._kf_xy = np.asarray(keyframe_poses, dtype=np.float64).reshape(-1, 3)[:, :2].copy()
        self._pose_cov_of.coverage = [np.zeros((3, 3))] * len(self._kf_xy)  # the saved map is the frame

    def seed_prior_map(self, poses: Array, scans: list[Scan], scan: Scan, pose: Array, information: Array,
                       step_index: int) -> None:
        """Start from a saved map: right after ``reset(pose)``, make the map's keyframes (``poses`` (K,3), their
        ``scans``) the oldest keyframes, and the current ``scan`` at the relocalised ``pose`` (information (3,3) of
        that pose in the map frame) the newest. The old keyframes enter farthest first, joined by stiff edges at
        their saved relative poses (the old map is held as it was saved), so the nearest ones form the tracking
        target; loop closures then tie the new keyframes to the old ones. Their keyframe steps are -1 - k (not
        steps of this run)."""
        self._check_step()
        if self.graph is not None or self.steps:
            raise ValueError("LidarSLAM.seed_prior_map: call it right after reset(), before any step")
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if len(poses) == 0 or len(scans) != len(poses):
            raise ValueError("LidarSLAM.seed_prior_map: need one scan per prior keyframe (and at least one)")
        cfg = self.config
        order = np.argsort(-np.hypot(*(poses[:, :2] - pose[:2]).T), kind="stable")
        stiff = np.diag([1 / 0.01**2, 1 / 0.01**2, 1 / 0.002**2])[None]
        self.graph = MarkerPoseGraph(poses[order[0]], cfg.graph)
        for n, k in enumerate(order.tolist()):
            if n:
                z = se2.between(poses[order[n - 1]], poses[k])[None]
                self.graph.add_step(n, np.array([n - 1]), np.array([n]), z, stiff)
            self._kf_step.append(-1 - k)
            self._kf_points.append(scan_points(scans[k], cfg.min_range_m, cfg.max_range_m))
            self._kf_scans.append(scans[k])
        n = len(order)
        cov = se2.covariance_in_frame(np.linalg.inv(information), float(poses[order[-1], 2]))
        self.graph.add_step(n, np.array([n - 1]), np.array([n]), se2.between(poses[order[-1]], pose)[None],
                            np.asarray(np.linalg.inv(cov), dtype=np.float64)[None])
        self._kf_step.append(step_index)
        self._kf_points.append(scan_points(scan, cfg.min_range_m, cfg.max_range_m))
        self._kf_scans.append(scan)
        # the saved keyframes were not driven in this run, and relocalising tied this one to them like a loop
        self._driven_m, self._last_loop_kf = [0.0] * (n + 1), n
        self._owner[0], self._rel[0] = n, np.zeros(3)
        self._pose_cov_of.keyframe = np.asarray(np.linalg.inv(information), np.float64)  # relocalised, map frame
        self._pose = self.graph.poses[-1].copy()
        self._version += 1
