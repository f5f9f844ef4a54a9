"""Online graph SLAM: a pose per step, odometry and landmark factors, place-recognition loop closures.

Every step adds the new pose (initialised from odometry), an odometry factor and the step's range-bearing factors
(through the association module); every ``optimize_every`` steps, and whenever a loop closure is accepted, the
whole graph is re-optimised from the current estimate (warm start) by a reused :class:`~slam2d.graph.optimizer.
Optimizer`, whose symbolic analysis is redone only when the structure has grown. Loop closures come from a
:class:`~slam2d.frontend.loop_closure.LoopCloser`: place recognition over keyframes (landmark-constellation
descriptors), geometric verification (RANSAC with an honest covariance), and a chi-square gate against the current
estimate and its joint marginal covariance; accepted loop factors also carry a robust kernel so that a wrong one that
slipped through is down-weighted.

State (all of it created in ``reset``): the graph and its values grow by one pose per step (full smoothing); the
keyframes, ``last_seen`` and ``alias`` grow per keyframe / landmark (map state); nothing keeps per-step history.

With ``loop_closure`` off the robot also forgets landmarks it has not seen for ``revisit_gap_steps``: a re-sighting
after such a gap starts a new landmark, exactly as if the place were not recognised.

Unknown association (every method but ``known``) gates each candidate with the innovation covariance of the JOINT
belief over [newest pose, candidate landmarks], cross-covariances included (:class:`~slam2d.graph.local_belief.
LocalBelief`: the joint marginal recovered at each optimisation, propagated through odometry in between). A new
landmark is tentative until it has been associated ``confirm_after`` times: its sightings are held aside, and only
then are its point and all its factors added to the graph; a tentative landmark missed too often while in view
(``tentative_max_misses``) is discarded with its sightings, so clutter never enters the graph.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

import slam2d.association as association
from slam2d.association import CLUTTER, NEW, Candidates, candidates_from_belief, resolve_method
from slam2d.association.tracks import LandmarkTracks, in_view
from slam2d.estimator import Diagnostics, Estimate, EstimatorLifecycle, GraphView, LoopEvent
from slam2d.frontend.loop_closure import LoopCandidate, LoopCloser
from slam2d.frontend.place_recognition import observation_points
from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff
from slam2d.graph.factors import between_error_jacobians
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.local_belief import LocalBelief
from slam2d.graph.marginals import marginal_covariances
from slam2d.graph.online_config import GraphSLAMConfig as GraphSLAMConfig
from slam2d.graph.optimizer import Optimizer, OptimizerConfig
from slam2d.graph.problem import chi2_per_dof
from slam2d.graph.sliding_window import WindowSolve, solve_window
from slam2d.log import Step
from slam2d.models.motion import ODOMETRY_FLOOR_VAR, odometry_factor
from slam2d.models.sensors import (
    range_bearing,
    range_bearing_inverse,
    range_bearing_inverse_jacobians,
    range_bearing_jacobians,
)

Array = NDArray[np.float64]



class GraphSLAM(EstimatorLifecycle):
    """Online graph SLAM estimator (implements the estimator protocol)."""

    def __init__(self, config: GraphSLAMConfig | None = None) -> None:
        self.config = config or GraphSLAMConfig()

    # ------------------------------------------------------------------ protocol
    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        cfg = self.config
        self.rng = rng
        self.graph = FactorGraph()
        self.values = Values(np.array([0]), np.asarray(initial_pose, dtype=np.float64).reshape(1, 3))
        self.optimizer = Optimizer(self.graph, OptimizerConfig(method="lm", max_iterations=cfg.iterations))
        self.index = 0
        # joint covariance of [newest pose, nearby landmarks]: last optimisation + odometry since (pose only with
        # known association, which needs no landmark covariance)
        self.belief = LocalBelief()
        self.point_covs = np.zeros((0, 2, 2))  # marginal of each point, aligned with values.point_keys
        self.point_seen = np.zeros(0, dtype=np.int64)  # last step each point was observed (same alignment)
        self._point_order = np.zeros(0, dtype=np.int64)
        self.last_seen: dict[int, int] = {}
        self.alias: dict[int, int] = {}  # source id -> landmark key (loop closure off: forgotten ids re-keyed)
        self.next_key = 0
        self._assoc = cfg.association  # "auto" is resolved at the first step with observations
        # tentative landmarks (unknown association): key, first sighting (pose key, z), mean, and their tracks
        # (sightings, consecutive misses in view; one map, slots aligned with tent_keys)
        self.tent_keys = np.zeros(0, dtype=np.int64)
        self.tent_src = np.zeros(0, dtype=np.int64)
        self.tent_z = np.zeros((0, 2))
        self.tent_pts = np.zeros((0, 2))  # their means: first sighting, then corrected by the local updates
        self.tent_tracks = LandmarkTracks(cfg.tracks())
        # their sightings, held aside until they are confirmed: pose key, landmark key, z
        self.held_pose = np.zeros(0, dtype=np.int64)
        self.held_key = np.zeros(0, dtype=np.int64)
        self.held_z = np.zeros((0, 2))
        self.tentative_dropped = 0
        self.loops = LoopCloser(cfg.place, cfg.loop_gate_probability, rng)  # its keyframes are map state
        self.new_loops: list[LoopEvent] = []  # decisions of the current step (history is the runner's)
        self.loops_accepted = 0
        self.loops_rejected = 0
        self.last_assignment = np.zeros(0, dtype=np.int64)
        self.optimizations = 0
        # window mode: each pose's marginal covariance when it was the newest (the boundary priors of the window)
        self._pose_covs = np.zeros((64, 3, 3))
        self._last_full = 0
        self._lifecycle_reset()

    @property
    def association_method(self) -> str:
        """The association method in use (``auto`` until the first step with observations resolves it)."""
        return self._assoc.method

    @property
    def pose_cov(self) -> Array:
        """Marginal covariance of the newest pose (3x3): last optimisation + odometry since."""
        return self.belief.pose_cov.copy()

    def step(self, step: Step) -> None:
        self._check_step()
        cfg = self.config
        t = step.index
        self.index = t
        self.new_loops = []
        prev = self.values.poses[-1]
        u = np.asarray(step.odometry, dtype=np.float64)
        pose = se2.compose(prev, u)
        # a noise model without a floor makes a standstill "certain"; 0.1 mm / 0.1 mrad keeps the information finite
        _, info = odometry_factor(u, cfg.motion, floor_var=ODOMETRY_FLOOR_VAR)
        info = info * cfg.odometry_info_scale
        # predict the belief with exactly what the new factor says: x_t = x_{t-1} (+) u with error e ~ N(0, info^-1)
        # in the factor's own (g2o, end-of-motion) frame: dx_t = -Jj^-1 Ji dx_{t-1} + Jj^-1 e
        ji, jj = between_error_jacobians(prev, pose, u)
        jj_inv = np.linalg.inv(jj)
        self.belief.predict(-jj_inv @ ji, jj_inv @ np.linalg.inv(info) @ jj_inv.T)
        self.values.add_poses([t], [pose])
        self.graph.add_between([t - 1], [t], u[None], info[None])

        obs = step.observations
        loop_added = False
        if self._assoc.method == "auto" and len(obs):
            self._assoc = resolve_method(self._assoc, bool(np.any(obs.landmark_id >= 0)))
        if len(obs):
            if self._assoc.method == "known":
                self._add_landmark_factors(t, pose, obs)
            else:
                self._observe_unknown(t, obs)
            if t % cfg.keyframe_every == 0:
                if not cfg.loop_closure:
                    self._remember_keyframe(t, obs.z)
                elif self._windowed:  # bounded work: its candidates are verified one per step (below)
                    self.loops.queue(t, *observation_points(obs.z, cfg.sensor.covariance))
                else:
                    loop_added = self._detect_loop(t, obs.z)
        else:
            self.last_assignment = np.zeros(0, dtype=np.int64)
            if self._assoc.method != "known" and self.tent_keys.size:
                drop = self._count_tentative_misses()
                self._retire_tentatives(np.zeros_like(drop), drop)
        if self._windowed:
            # window mode: one queued loop candidate verified per step, never on a window solve's step; a loop waits
            # for the next window solve (which folds it in) unless a whole-graph solve is due
            window_due = (t + cfg.optimize_every // 2) % cfg.optimize_every == 0
            if cfg.loop_closure and not window_due:
                loop_added = self._add_loops(self.loops.verify_queued(self._pose_of, self._loop_joint_cov))
            if loop_added and t - self._last_full >= cfg.full_every:
                self._optimize(cfg.iterations * 4)
            elif window_due:
                self._optimize(cfg.window_iterations, local=True)
        elif loop_added or t % cfg.optimize_every == 0:
            self._optimize(cfg.iterations * (4 if loop_added else 1))
        if self._windowed:
            if t >= len(self._pose_covs):
                self._pose_covs = np.concatenate([self._pose_covs, np.zeros_like(self._pose_covs)])
            self._pose_covs[t] = self.belief.pose_cov

    def estimate(self) -> Estimate:
        self._check_ready()
        order = np.argsort(self.values.point_keys)
        return Estimate(
            pose=self.values.poses[-1].copy(),
            pose_cov=self.pose_cov.copy(),
            landmarks=self.values.points[order].copy(),
            landmark_covs=self.point_covs[order].copy(),
            landmark_ids=self.values.point_keys[order].copy(),
            state_dim=int(3 * len(self.values.poses) + 2 * len(self.values.points)),
            trajectory=self.values.poses.copy(),
            association=self.last_assignment.copy(),
            tentative_landmarks=self._tentative_points(),
            tentative_ids=self.tent_keys.copy(),
            new_loops=tuple(self.new_loops),
            diagnostics=Diagnostics(tentative_dropped=self.tentative_dropped, optimizations=self.optimizations,
                                    loops_accepted=self.loops_accepted, loops_rejected=self.loops_rejected),
        )

    def finalize(self) -> None:
        """Optimise to convergence (called by the runner after the last step)."""
        if self._lifecycle_finalize():
            self._optimize(self.config.final_iterations, all_points=True)

    def close_loop_now(self, z: Array) -> bool:
        """Try to close a loop from observations ``z`` (K,2) taken at the newest pose, whatever ``loop_closure``
        says, and optimise to convergence if one is accepted (the lab's "close loop" button)."""
        self.new_loops = []
        added = self._detect_loop(self.index, np.asarray(z, dtype=np.float64).reshape(-1, 2), add_keyframe=False)
        if added:
            self._optimize(self.config.final_iterations)
        return added

    def chi2_per_dof(self) -> dict[str, float]:
        """``slam2d.graph.problem.chi2_per_dof`` of the current graph and estimate."""
        return chi2_per_dof(self.graph, self.values)

    def graph_view(self) -> GraphView:
        """Nodes and edges for drawing: pose/point positions and per factor kind the key pairs of its edges."""
        self._check_ready()
        edges = {b.kind: b.keys.T.copy() for b in self.graph.blocks()}
        return GraphView(self.values.poses.copy(), self.values.pose_keys.copy(), self.values.points.copy(),
                         self.values.point_keys.copy(), edges)

    # ------------------------------------------------------------------ internals
    def _marginals(self, pose_keys: Any = (), point_keys: Any = (), window: WindowSolve | None = None) -> Array:
        """Joint marginal covariance of the selected variables (poses first), reusing the optimiser's analysis; from
        the local problem with boundary priors after a window solve."""
        if window is not None:
            return window.marginals(np.asarray(pose_keys, np.int64), np.asarray(point_keys, np.int64),
                                    lambda keys: self._pose_covs[self._pose_rows(keys)])
        an = self.optimizer.analysis
        an = an if an is not None and an.compatible(self.graph, self.values) else None
        return marginal_covariances(self.graph, self.values, pose_keys, point_keys, analysis=an,
                                    solver=self.optimizer.solver).joint

    def _optimize(self, iterations: int, *, all_points: bool = False, local: bool = False) -> None:
        """Optimise the whole graph, or with ``local`` in window mode only the window (bounded work)."""
        window = self._solve_window(iterations) if local and self._windowed else None
        if window is None:
            cfg = self.optimizer.config
            if cfg.max_iterations != iterations:
                self.optimizer.config = OptimizerConfig(method="lm", max_iterations=iterations)
            self.values, _ = self.optimizer.optimize(self.values)
            self._last_full = self.index
            if self._windowed:  # the next window's prior pose: exact again after a whole-graph solve
                keys = self.values.pose_keys[-self.config.window - 1:]
                joint = self._marginals(keys)
                self._pose_covs[keys] = joint.reshape(keys.size, 3, keys.size, 3)[np.arange(keys.size), :,
                                                                                   np.arange(keys.size), :]
        self.optimizations += 1
        # refresh the uncertainty used by association (landmarks only when it is not the oracle) and the loop gate
        if self._assoc.method == "known":
            self._refresh_known(window, all_points)
        else:
            self._refresh_belief(all_points)

    def _near_points(self, all_points: bool) -> NDArray[np.int64]:
        """Landmarks within max_range_m + candidate_margin_m + belief_margin_m of the newest pose (or all)."""
        if all_points:
            return self.values.point_keys
        cfg = self.config
        reach = cfg.sensor.max_range_m + cfg.candidate_margin_m + cfg.belief_margin_m
        return self.values.point_keys[self._reachable(int(self.values.pose_keys[-1]), self.values.poses[-1], reach)]

    def _refresh_known(self, window: WindowSolve | None, all_points: bool) -> None:
        """Known association: the newest pose's marginal (the loop gate's) and, after a whole-graph solve, the exact
        marginals of the landmarks near it by the unknown path's rule (all with ``all_points``, and in window mode,
        where whole-graph solves come at most every ``full_every`` steps), one factorisation. A window solve
        refreshes the pose only: its marginal treats the held poses as independent priors, which measured tighter
        than the whole graph's exact landmark marginals (overconfident)."""
        t = int(self.values.pose_keys[-1])
        near = self._near_points(all_points or self._windowed) if window is None else np.zeros(0, np.int64)
        m = self._marginals([t], near, window=window)
        self.belief.set(np.zeros(0, np.int64), m[:3, :3])
        if near.size:
            idx = 3 + 2 * np.arange(near.size)[:, None] + np.arange(2)
            self.point_covs[self._point_rows(near)] = m[idx[:, :, None], idx[:, None, :]]

    @property
    def _windowed(self) -> bool:
        """Window mode applies with known association; unknown association gates with the joint belief of the
        whole graph (measured: a window's conservative belief there cost most of the loops and doubled the map)."""
        return bool(self.config.window) and self._assoc.method == "known"

    def _solve_window(self, iterations: int) -> WindowSolve:
        """Optimise the newest ``window`` poses and the landmarks they saw."""
        cfg = self.config
        free_poses = self.values.pose_keys[-cfg.window:]
        rb = self.graph.block("range_bearing") if "range_bearing" in self.graph.kinds() else None
        free_points = np.unique(rb.keys[1][np.isin(rb.keys[0], free_poses)]) if rb is not None else \
            np.zeros(0, np.int64)
        ws = solve_window(self.graph, self.values, free_poses, free_points, iterations, cfg.window_sightings)
        out = ws.values
        free = np.isin(out.pose_keys, free_poses)
        self.values.poses[self._pose_rows(out.pose_keys[free])] = out.poses[free]
        if out.point_keys.size:
            self.values.points[self._point_rows(out.point_keys)] = out.points
        return ws

    def _refresh_belief(self, all_points: bool = False) -> None:
        """The joint marginal of [newest pose, landmarks near it, tentative landmarks], from one factorisation.

        A tentative landmark is not in the graph; it is l = g(x_s, z) of its first sighting z from pose x_s, so its
        rows follow from those of x_s (``Sigma_l. = Gp Sigma_s.``, plus ``Gz R Gz^T`` on its own block).
        """
        cfg = self.config
        t = int(self.values.pose_keys[-1])
        near_keys = self._near_points(all_points)
        src = np.unique(self.tent_src[self.tent_src != t])
        pose_keys = np.concatenate([[t], src]).astype(np.int64)
        m = self._marginals(pose_keys, near_keys)
        n_p, n_l, n_t = pose_keys.size, near_keys.size, self.tent_keys.size
        base = np.r_[0:3, 3 * n_p: 3 * n_p + 2 * n_l]  # [x_t, l_near] in m
        cov = np.empty((base.size + 2 * n_t,) * 2)
        cov[:base.size, :base.size] = m[np.ix_(base, base)]
        if n_t:
            # l_tent = g(x_src, z): its rows are Gp times the rows of its source pose (+ Gz R Gz^T on its own block)
            slot = np.searchsorted(pose_keys[1:], self.tent_src) + 1
            slot[self.tent_src == t] = 0
            src_poses = self.values.poses[self._pose_rows(self.tent_src)]
            self.tent_pts = range_bearing_inverse(src_poses, self.tent_z)
            gp, gz = range_bearing_inverse_jacobians(src_poses, self.tent_z)
            src_rows = 3 * slot[:, None] + np.arange(3)  # (n_t, 3)
            cross = np.einsum("iab,ibk->iak", gp, m[src_rows][:, :, base]).reshape(2 * n_t, base.size)
            ss = m[src_rows[:, :, None, None], src_rows[None, None, :, :]]  # (n_t, 3, n_t, 3)
            tt = np.einsum("iab,ibjc,jdc->iajd", gp, ss, gp)
            tt[np.arange(n_t), :, np.arange(n_t), :] += gz @ cfg.sensor.covariance @ np.swapaxes(gz, 1, 2)
            cov[base.size:, :base.size] = cross
            cov[:base.size, base.size:] = cross.T
            cov[base.size:, base.size:] = tt.reshape(2 * n_t, 2 * n_t)
        self.belief.set(np.concatenate([near_keys, self.tent_keys]), cov)
        if n_l:
            self.point_covs[self._point_rows(near_keys)] = self.belief.point_covs(near_keys)

    def _pose_rows(self, keys: NDArray[np.int64]) -> NDArray[np.int64]:
        """Rows of these pose keys in ``values`` (pose keys are added in increasing order)."""
        return np.searchsorted(self.values.pose_keys, keys).astype(np.int64)

    def _point_rows(self, keys: Any) -> NDArray[np.int64]:
        """Rows of these point keys in ``values`` (all must exist)."""
        pk = self.values.point_keys
        if self._point_order.size != pk.size:
            self._point_order = np.argsort(pk, kind="stable")
        k = np.asarray(keys, dtype=np.int64).reshape(-1)
        return self._point_order[np.searchsorted(pk[self._point_order], k)].astype(np.int64)

    def _reachable(self, t: int, pose: Array, reach: float) -> NDArray[np.bool_]:
        """Points within ``reach`` (m) of ``pose`` (and, with loop closure off, seen within revisit_gap_steps)."""
        cfg = self.config
        near = np.hypot(*(self.values.points - pose[:2]).T) <= reach
        if not cfg.loop_closure:
            near &= t - self.point_seen <= cfg.revisit_gap_steps
        return near

    def _add_points(self, keys: Any, points: Array, covs: Array, t: int) -> None:
        self.values.add_points(keys, points)
        self.point_covs = np.concatenate([self.point_covs, np.asarray(covs).reshape(-1, 2, 2)])
        self.point_seen = np.concatenate([self.point_seen, np.full(len(keys), t, dtype=np.int64)])

    def _mark_seen(self, keys: NDArray[np.int64], t: int) -> None:
        if keys.size:
            self.point_seen[self._point_rows(keys)] = t
        for k in keys:
            self.last_seen[int(k)] = t

    def _new_key(self) -> int:
        while np.any(self.values.point_keys == self.next_key) or np.any(self.tent_keys == self.next_key):
            self.next_key += 1
        k = self.next_key
        self.next_key += 1
        return k

    def _add_landmark_factors(self, t: int, pose: Array, obs: Any) -> None:
        """Known association: the source's ids (re-keyed after a long gap when loop closure is off)."""
        cfg = self.config
        R = cfg.sensor.covariance
        z = obs.z
        keys = np.asarray(self.values.point_keys, dtype=np.int64)
        assign = np.full(len(obs), CLUTTER, dtype=np.int64)
        for i, sid in enumerate(obs.landmark_id):
            sid = int(sid)
            if sid < 0:
                continue
            key: int | None = self.alias.get(sid, sid)
            if key is not None and key in self.last_seen and not cfg.loop_closure \
                    and t - self.last_seen[key] > cfg.revisit_gap_steps:
                key = None  # not recognised: it will start a new landmark
            if key is None:
                key = self._new_key() + 1_000_000
                self.alias[sid] = key
            else:
                self.alias.setdefault(sid, key)
            assign[i] = key
        use = assign >= 0
        if not np.any(use):
            self.last_assignment = assign
            return
        idx = np.flatnonzero(use)
        # a new landmark is initialised from its first sighting (inverse sensor model)
        fresh_keys, first = np.unique(assign[idx], return_index=True)
        is_new = ~np.isin(fresh_keys, keys)
        j = idx[first[is_new]]
        order = np.argsort(j)
        j, fresh_keys = j[order], fresh_keys[is_new][order]
        if j.size:
            gp, gz = range_bearing_inverse_jacobians(pose, z[j])
            covs = gp @ self.pose_cov @ np.swapaxes(gp, 1, 2) + gz @ R @ np.swapaxes(gz, 1, 2)
            self._add_points(fresh_keys, range_bearing_inverse(pose, z[j]), covs, t)
        info = np.broadcast_to(np.linalg.inv(R), (idx.size, 2, 2))
        self.graph.add_range_bearing(np.full(idx.size, t), assign[idx], z[idx], info)
        self._mark_seen(assign[idx], t)
        self.last_assignment = assign

    def _tentative_points(self) -> Array:
        """Positions of the tentative landmarks, (T, 2)."""
        return self.tent_pts.copy()

    def association_candidates(self) -> Candidates:
        """The candidates the next observations at the newest pose are associated against: confirmed landmarks (and
        tentative ones) predicted within max_range_m + candidate_margin_m, with S and S_joint from the joint belief.

        Optimises first (refreshing the belief) when a candidate lies outside the belief's block.
        """
        return self._candidates()[0]

    def _candidates(self) -> tuple[Candidates, Array]:
        """:meth:`association_candidates` and the candidates' positions (C, 2)."""
        cfg = self.config
        reach = cfg.sensor.max_range_m + cfg.candidate_margin_m
        for attempt in range(2):
            t = int(self.values.pose_keys[-1])
            pose = self.values.poses[-1]
            near = self._reachable(t, pose, reach)
            near_t = np.hypot(*(self.tent_pts - pose[:2]).T) <= reach
            keys = np.concatenate([self.values.point_keys[near], self.tent_keys[near_t]])
            pts = np.concatenate([self.values.points[near], self.tent_pts[near_t]])
            if attempt == 0 and np.any(self.belief.rows(keys) < 0):
                self._optimize(cfg.iterations, local=True)  # moved beyond the block since the last optimisation
                continue
            break
        return candidates_from_belief(pose, pts, keys, self.belief.select(keys), cfg.sensor.covariance), pts

    def _count_tentative_misses(self) -> NDArray[np.bool_]:
        """One more miss for each tentative landmark predicted well in view and not sighted at this step (the
        tracks know which were); returns which are to be discarded (over the miss limit, or dynamic)."""
        cfg = self.config
        if self.tent_keys.size == 0:
            return np.zeros(0, dtype=bool)
        zp = range_bearing(self.values.poses[-1], self.tent_pts)
        view = in_view(zp, cfg.sensor.max_range_m, cfg.sensor.fov_rad, cfg.view_margin_m)
        self.tent_tracks.miss(view[None], self.index)
        return self.tent_tracks.prune_mask()[0]

    def _sightings(self, pose: Array, z: Array) -> tuple[Array | None, Array | None]:
        """World points of observations z (k,2) from ``pose`` and their covariances G_z R G_z^T (pose taken as exact)
        for the tracks' persistence rule; (None, None) when the rule is off."""
        if not self.config.dynamic_test:
            return None, None
        _, gz = range_bearing_inverse_jacobians(pose, z)
        return range_bearing_inverse(pose, z), gz @ self.config.sensor.covariance @ np.swapaxes(gz, 1, 2)

    def _retire_tentatives(self, promote: NDArray[np.bool_], drop: NDArray[np.bool_]) -> None:
        """Forget the tentative landmarks that were confirmed (already in the graph) or discarded (also removed from
        the belief), with their held sightings."""
        if np.any(drop):
            self.belief.remove(self.tent_keys[drop])
            self.tentative_dropped += int(drop.sum())
        gone = promote | drop
        if not np.any(gone):
            return
        h = np.isin(self.held_key, self.tent_keys[gone])
        self.held_pose, self.held_key, self.held_z = self.held_pose[~h], self.held_key[~h], self.held_z[~h]
        keep = ~gone
        self.tent_keys, self.tent_src, self.tent_z = self.tent_keys[keep], self.tent_src[keep], self.tent_z[keep]
        self.tent_pts = self.tent_pts[keep]
        self.tent_tracks.keep(keep)

    def _observe_unknown(self, t: int, obs: Any) -> None:
        """Unknown association against the joint belief; tentative landmarks are held aside until confirmed.

        Order (as in EKF-SLAM): associate; update the belief with the matches whose factors enter the graph now
        (confirmed landmarks, and tentative ones confirmed by this sighting) and move the newest pose and the
        block's landmarks by the correction; then start the NEW observations as tentative landmarks from the
        corrected pose; confirm and discard tentative landmarks; add the factors.
        """
        cfg = self.config
        R = cfg.sensor.covariance
        z = np.asarray(obs.z, dtype=np.float64)
        cands, cand_pts = self._candidates()
        assign = self._associate(obs, cands)
        is_tent = np.isin(assign, self.tent_keys) & (assign >= 0)
        conf = (assign >= 0) & ~is_tent
        # one sighting per tentative landmark and step (its first matching observation)
        slot_of = np.argsort(self.tent_keys)
        obs_t = np.flatnonzero(is_tent)
        cols, first = np.unique(slot_of[np.searchsorted(self.tent_keys, assign[obs_t], sorter=slot_of)],
                                return_index=True)
        self.tent_tracks.sight(cols, t, *self._sightings(self.values.poses[-1], z[obs_t[first]]))
        promote = self.tent_tracks.confirmed[0]
        upd = conf | np.isin(assign, self.tent_keys[promote])
        if np.any(upd):
            self._local_update(assign[upd], z[upd], cands, cand_pts)
        pose = self.values.poses[-1]
        new = np.flatnonzero(assign == NEW)
        if new.size:
            new_keys = np.array([self._new_key() for _ in range(new.size)], dtype=np.int64)
            assign[new] = new_keys
            gp, gz = range_bearing_inverse_jacobians(pose, z[new])
            self.belief.augment(new_keys, gp, gz, R)
            self.tent_keys = np.concatenate([self.tent_keys, new_keys])
            self.tent_src = np.concatenate([self.tent_src, np.full(new.size, t, dtype=np.int64)])
            self.tent_z = np.concatenate([self.tent_z, z[new]])
            self.tent_pts = np.concatenate([self.tent_pts, range_bearing_inverse(pose, z[new])])
            self.tent_tracks.append(new.size, t, *self._sightings(pose, z[new]))
            promote = self.tent_tracks.confirmed[0]
            is_tent[new] = True
        # sightings of tentative landmarks are held aside until they are confirmed
        hold = np.flatnonzero(is_tent)
        self.held_pose = np.concatenate([self.held_pose, np.full(hold.size, t, dtype=np.int64)])
        self.held_key = np.concatenate([self.held_key, assign[hold]])
        self.held_z = np.concatenate([self.held_z, z[hold]])
        drop = self._count_tentative_misses() & ~promote
        # confirmed: the point and every held sighting join the graph
        f_pose, f_key, f_z = [np.full(int(conf.sum()), t, dtype=np.int64)], [assign[conf]], [z[conf]]
        if np.any(promote):
            pk = self.tent_keys[promote]
            self._add_points(pk, self.tent_pts[promote], self.belief.point_covs(pk), t)
            h = np.isin(self.held_key, pk)
            f_pose.append(self.held_pose[h])
            f_key.append(self.held_key[h])
            f_z.append(self.held_z[h])
        self._retire_tentatives(promote, drop)
        fp, fk, fz = np.concatenate(f_pose), np.concatenate(f_key), np.concatenate(f_z)
        if fk.size:
            info = np.broadcast_to(np.linalg.inv(R), (fk.size, 2, 2))
            self.graph.add_range_bearing(fp, fk, fz, info)
            self._mark_seen(np.unique(fk), t)
        self.last_assignment = assign

    def _local_update(self, keys: NDArray[np.int64], z: Array, cands: Candidates, cand_pts: Array) -> None:
        """EKF update of the belief with these matches, and the same correction applied to the newest pose and to
        the block's landmarks (graph values and tentative means); see :mod:`slam2d.graph.local_belief`."""
        pose = self.values.poses[-1]
        order = np.argsort(cands.ids)
        ci = order[np.searchsorted(cands.ids, keys, sorter=order)]
        zp = cands.z_pred[ci]
        nu = np.column_stack([z[:, 0] - zp[:, 0], angle_diff(z[:, 1], zp[:, 1])])
        hp, hl = range_bearing_jacobians(np.broadcast_to(pose, (keys.size, 3)), cand_pts[ci])
        dx = self.belief.update(keys, hp, hl, nu, self.config.sensor.covariance)
        self.values.poses[-1] = se2.retract(pose, dx[:3])
        d = dx[3:].reshape(-1, 2)
        bk = self.belief.keys
        in_graph = np.isin(bk, self.values.point_keys)
        if np.any(in_graph):
            self.values.points[self._point_rows(bk[in_graph])] += d[in_graph]
        if np.any(~in_graph):
            tr = np.searchsorted(self.tent_keys, bk[~in_graph], sorter=np.argsort(self.tent_keys))
            self.tent_pts[np.argsort(self.tent_keys)[tr]] += d[~in_graph]

    def _associate(self, obs: Any, cands: Candidates) -> NDArray[np.int64]:
        """Run the configured association method (every observation is NEW when there is no candidate)."""
        if cands.ids.size == 0:
            return np.full(len(obs), NEW, dtype=np.int64)
        return np.asarray(association.associate(obs, cands, self._assoc, rng=self.rng).assignment, dtype=np.int64)

    def _remember_keyframe(self, t: int, z: Array) -> None:
        self.loops.add_keyframe(t, *observation_points(z, self.config.sensor.covariance))

    def _detect_loop(self, t: int, z: Array, add_keyframe: bool = True) -> bool:
        """Try to close a loop at pose ``t``; an accepted one enters the graph as a robust between factor."""
        cfg = self.config
        pts, covs = observation_points(z, cfg.sensor.covariance)
        return self._add_loops(
            self.loops.try_close(t, pts, covs, self._pose_of, self._loop_joint_cov, add_keyframe=add_keyframe))

    def _add_loops(self, found: list[LoopCandidate]) -> bool:
        """Record the gate's decisions; an accepted loop enters the graph as a robust between factor a -> b."""
        cfg = self.config
        for c in found:
            self.new_loops.append(c.event)
            self.loops_accepted += c.accepted
            self.loops_rejected += not c.accepted
            if c.accepted:
                info = np.linalg.inv(c.cov) * cfg.loop_info_scale
                kernel = None if cfg.loop_robust_kernel == "none" else cfg.loop_robust_kernel
                self.graph.add_between([c.a], [c.b], c.T_a_b[None], info[None], robust=kernel)
        return any(c.accepted for c in found)

    def _loop_joint_cov(self, a: int, b: int) -> Array:
        """Joint marginal of poses a, b for the loop gate. Window mode (bounded work): the two poses' own marginals
        as independent (a's from when it was the newest), which widens the gate; verification and the robust
        kernel on loop factors guard it."""
        if not self._windowed:
            return self._marginals([a, b])
        cov = np.zeros((6, 6))
        cov[:3, :3] = self._pose_covs[self._pose_rows(np.array([a]))[0]]
        cov[3:, 3:] = self._pose_covs[self._pose_rows(np.array([b]))[0]] if b != self.index else self.belief.pose_cov
        return cov

    def _pose_of(self, key: int) -> Array:
        return self.values.poses[np.searchsorted(self.values.pose_keys, key)]
