"""Multi-robot graph SLAM: one factor graph over every robot's poses and the shared landmarks.

The robots' data arrive on one clock (:class:`~slam2d.multi_log.MultiStep`). Each robot gets a pose node whenever
it measures something, is sighted, or every ``node_every`` steps; the odometry between two nodes is composed into
one between-factor with the propagated covariance (exactly what marginalising the intermediate poses of a chain
gives), so the full trajectory is recovered afterwards by composing the odometry from the node before each step.
Landmark sightings are range-bearing factors (association through :func:`slam2d.association.associate` against
the robot's joint map, as in the single-robot online graph); robot-robot sightings are ``pose_range_bearing``
factors between the two robots' nodes at that instant, gated first against the current estimate. Every
``optimize_every`` steps the whole graph is re-optimised (sparse Levenberg-Marquardt, warm start) and the marginal
covariances of the newest poses and of the landmarks are recovered for the next association gates. Without ids
the landmark factors carry a robust kernel scaled to the association gate (a sighting given to the wrong landmark of
a cluster pulls less: MRCLAM's 15 landmarks stand in clusters 0.18-0.25 m apart), and each robot closes loops on
its own keyframes (:mod:`slam2d.graph.multi_robot_loops`).

Starting poses: known (``unknown_starts=False``): each robot is anchored by a prior at its start pose. Unknown:
each robot starts at the origin of its own frame and is a separate group (own map, own gauge: the optimiser holds
the first pose of every connected component). After each optimisation every pair of groups is tested for a merge
(:func:`slam2d.graph.map_merge.find_merge`: common landmarks -- same id, or candidate pairs with unknown
association -- and robot-robot sightings between them); only a VERIFIED hypothesis merges the frames: group B's
poses and landmarks are moved into A's frame, duplicated landmarks become one variable, and the stored sightings
between them become factors. Sightings between groups not merged yet are kept as merge evidence only.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

import slam2d.association as association
from slam2d.association import CLUTTER, NEW, candidates_from_belief
from slam2d.estimator import EstimatorLifecycle
from slam2d.geometry import se2
from slam2d.geometry.angles import angle_diff
from slam2d.geometry.gaussian import chi2_gate
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.map_merge import find_merge
from slam2d.graph.marginals import marginal_covariances
from slam2d.graph.multi_robot_loops import RobotLoops
from slam2d.graph.multi_robot_types import (
    MergeEvent,
    MultiEstimate,
    MultiGraphConfig,
    compose_with_covariance,
    config_from_log,
)
from slam2d.graph.optimizer import Optimizer, OptimizerConfig
from slam2d.log import Observations
from slam2d.models.motion import odometry_covariance
from slam2d.models.sensors import (
    range_bearing,
    range_bearing_inverse,
    range_bearing_inverse_jacobians,
    range_bearing_jacobians,
)
from slam2d.multi_log import MultiStep

__all__ = ["KEY_STRIDE", "MergeEvent", "MultiEstimate", "MultiGraphConfig", "MultiGraphSLAM",
           "compose_with_covariance", "config_from_log"]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: added to every per-step odometry covariance (as in the single-robot online graph): 0.1 mm / 0.1 mrad
ODOMETRY_FLOOR_COV = np.diag([1e-8, 1e-8, 1e-8])
#: pose key of robot r (its index) at step t is r * KEY_STRIDE + t
KEY_STRIDE = 10_000_000



class MultiGraphSLAM(EstimatorLifecycle):
    """Multi-robot graph SLAM over a :class:`MultiRobotLog` (own runner: see :mod:`slam2d.lab.multi_robot`)."""

    def __init__(self, config: MultiGraphConfig) -> None:
        self.config = config

    # ------------------------------------------------------------------ protocol
    def reset(self, initial_poses: Array | None, *, rng: np.random.Generator) -> None:
        """Fresh state for ``len(config.motion)`` robots. ``initial_poses`` (R,3): the known starts (ignored, and
        may be None, with ``unknown_starts``: every robot then starts at the origin of its own frame)."""
        cfg = self.config
        n = len(cfg.motion)
        if n == 0:
            raise ValueError("MultiGraphConfig has no robots (use config_from_log)")
        if cfg.unknown_starts or initial_poses is None:
            if not cfg.unknown_starts:
                raise ValueError("known starts need initial_poses (R,3)")
            starts = np.zeros((n, 3))
        else:
            starts = np.asarray(initial_poses, dtype=np.float64).reshape(n, 3)
        self.rng = rng
        self.n = n
        self.index = 0
        self.group = np.zeros(n, dtype=np.int64) if not cfg.unknown_starts else np.arange(n, dtype=np.int64)
        # pose nodes (growing buffers): key, value, robot
        self._pk: list[int] = []
        self._pv: list[Array] = []
        self._row: dict[int, int] = {}
        self.node_steps: list[list[int]] = [[0] for _ in range(n)]
        self.last_row = np.zeros(n, dtype=np.int64)
        for r in range(n):
            self.last_row[r] = len(self._pk)
            self._row[r * KEY_STRIDE] = len(self._pk)
            self._pk.append(r * KEY_STRIDE)
            self._pv.append(starts[r].copy())
        self.cur = starts.copy()  # pose of each robot's newest node
        std = cfg.start_std_m
        self.cur_cov = np.broadcast_to(np.diag([std**2, std**2, std**2]), (n, 3, 3)).copy()
        if cfg.unknown_starts:
            self.cur_cov[:] = np.diag([1e-12, 1e-12, 1e-12])
        self.node_cov = self.cur_cov.copy()  # marginal of the newest node at the last optimisation
        self.odometry: list[list[Array]] = [[] for _ in range(n)]
        # factors: lists of stacked arrays, concatenated on each optimisation
        self.f_between: list[tuple[Any, ...]] = []  # (i keys, j keys, z, information), stacked
        self.f_rb: list[tuple[Any, ...]] = []
        self.f_prr: list[tuple[Any, ...]] = []
        self.f_loop: list[tuple[Any, ...]] = []  # accepted loop closures (robust between factors)
        self.loops = RobotLoops(n, cfg.place, cfg.loop_gate_probability, cfg.keyframe_every, rng)
        self._solved: tuple[FactorGraph, Values, Any] | None = None  # graph, values, analysis of the last solve
        self._fg: FactorGraph | None = None  # the graph so far (factors appended on each optimisation)
        self._in_graph: dict[str, int] = {}
        self.prior_keys = np.zeros(0, dtype=np.int64)
        self.prior_z = np.zeros((0, 3))
        if not cfg.unknown_starts:
            self.prior_keys = np.arange(n, dtype=np.int64) * KEY_STRIDE
            self.prior_z = starts.copy()
        # landmarks: key -> position, covariance, group, source id (known association), confirmed
        self.lm_pos: dict[int, Array] = {}
        self.lm_cov: dict[int, Array] = {}
        self.lm_group: dict[int, int] = {}
        self.lm_src: dict[int, int] = {}
        self.key_of: dict[tuple[int, int], int] = {}  # (group, source id) -> key (known association)
        self.tentative: dict[int, int] = {}  # key -> hits (unknown association, not yet in the graph)
        self.held: list[tuple[Any, ...]] = []  # (pose key, landmark key, z, info) of tentatives
        self.next_key = 0
        self.pending: list[tuple[int, int, int, Array]] = []  # sightings between unmerged groups: (t, o, b, z)
        self.merges: list[MergeEvent] = []
        self.counters = {"optimizations": 0, "sightings_used": 0, "sightings_gated": 0, "landmarks_gated": 0,
                         "merge_attempts": 0, "merges": 0, "loops_accepted": 0, "loops_rejected": 0,
                         "landmarks_fused": 0}
        self.sighting_R = np.diag([cfg.sighting_range_std_m**2, cfg.sighting_bearing_std_rad**2])
        self._lifecycle_reset()

    def step(self, ms: MultiStep) -> None:
        self._check_step()
        cfg = self.config
        t = ms.index
        self.index = t
        if len(ms.steps) != self.n:
            raise ValueError(f"step {t}: {len(ms.steps)} robot steps for {self.n} robots")
        robots_now = set()
        if len(ms.sightings):
            robots_now = {int(r) for r in np.concatenate([ms.sightings.observer, ms.sightings.observed])}
        for r, st in enumerate(ms.steps):
            self.odometry[r].append(st.odometry)
            if t % cfg.node_every == 0 or len(st.observations) or (r + 1) in robots_now:
                self._add_node(r, t)
        for r, st in enumerate(ms.steps):
            if len(st.observations):
                self._observe(r, t, st.observations)
                if cfg.loop_closure:
                    self.loops.observe(r, t, r * KEY_STRIDE + t, st.observations.z, cfg.sensor[r].covariance)
        if len(ms.sightings):
            self._sightings(t, ms)
        if t % cfg.optimize_every == 0:
            self._optimize(cfg.iterations)
            if self.loops.pending and self._close_loops():
                self._optimize(cfg.iterations * 4)
            if cfg.unknown_starts:
                self._try_merges(t)
            if cfg.association.method != "known":
                self._fuse_duplicates()

    def finalize(self) -> None:
        if self._lifecycle_finalize():
            for r in range(self.n):
                if self.node_steps[r][-1] != self.index:
                    self._add_node(r, self.index)
            self._optimize(self.config.final_iterations, marginals=False)

    def estimate(self) -> MultiEstimate:
        self._check_ready()
        vals = np.asarray(self._pv)
        trajs = []
        for r in range(self.n):
            steps = np.asarray(self.node_steps[r], dtype=np.int64)
            nodes = vals[self._rows(r * KEY_STRIDE + steps)]
            u = np.asarray(self.odometry[r]).reshape(-1, 3)
            dr = se2.compose_chain(np.zeros(3), u)  # (t+1, 3)
            t_all = np.arange(dr.shape[0])
            last = np.searchsorted(steps, t_all, side="right") - 1
            trajs.append(se2.compose(nodes[last], se2.between(dr[steps[last]], dr)))
        lk = np.array(sorted(k for k in self.lm_pos if k not in self.tentative), dtype=np.int64)
        ids = np.array([self.lm_src.get(int(k), int(k)) for k in lk], dtype=np.int64)
        return MultiEstimate(
            robots=tuple(range(1, self.n + 1)),
            poses=np.array([tr[-1] for tr in trajs]),
            trajectories=tuple(trajs),
            starts=vals[self._rows(np.arange(self.n) * KEY_STRIDE)].copy(),
            landmarks=np.array([self.lm_pos[int(k)] for k in lk]).reshape(-1, 2),
            landmark_ids=ids, landmark_groups=np.array([self.lm_group[int(k)] for k in lk], dtype=np.int64),
            groups=self.group.copy(), merges=tuple(self.merges), counters=dict(self.counters))

    # ------------------------------------------------------------------ nodes and odometry
    def _rows(self, keys: IntArray) -> IntArray:
        """Rows of these pose keys in the node buffers (rows never move: nodes are only appended)."""
        return np.array([self._row[int(k)] for k in np.asarray(keys).reshape(-1)], dtype=np.int64)

    def _add_node(self, r: int, t: int) -> None:
        """A pose node for robot r at step t and the composed odometry factor from its previous node."""
        s_prev = self.node_steps[r][-1]
        prev_key = r * KEY_STRIDE + s_prev
        key = r * KEY_STRIDE + t
        u = np.asarray(self.odometry[r][s_prev:t]).reshape(-1, 3)
        z, cov = compose_with_covariance(u, odometry_covariance(u, self.config.motion[r]) + ODOMETRY_FLOOR_COV)
        # the between factor's error is rotated into the end of the motion (g2o): cov_e = Rz^T cov Rz
        cz, sz = np.cos(z[2]), np.sin(z[2])
        rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
        info = np.linalg.inv(rz.T @ cov @ rz)
        self.f_between.append((np.array([prev_key]), np.array([key]), z[None], 0.5 * (info + info.T)[None]))
        c, s = np.cos(self.cur[r, 2]), np.sin(self.cur[r, 2])
        j1 = np.array([[1.0, 0.0, -s * z[0] - c * z[1]], [0.0, 1.0, c * z[0] - s * z[1]], [0.0, 0.0, 1.0]])
        j2 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # se2.compose_jacobians, written out
        self.cur_cov[r] = j1 @ self.cur_cov[r] @ j1.T + j2 @ cov @ j2.T
        self.cur[r] = se2.compose(self.cur[r], z)
        self.last_row[r] = len(self._pk)
        self._row[key] = len(self._pk)
        self._pk.append(key)
        self._pv.append(self.cur[r].copy())
        self.node_steps[r].append(t)

    # ------------------------------------------------------------------ landmarks
    def _new_key(self) -> int:
        k = self.next_key
        self.next_key += 1
        return k

    def _observe(self, r: int, t: int, obs: Observations) -> None:
        cfg = self.config
        sensor = cfg.sensor[r]
        R = sensor.covariance
        pose, P = self.cur[r], self.cur_cov[r]
        g = int(self.group[r])
        known = cfg.association.method == "known"
        reach = sensor.max_range_m + cfg.candidate_margin_m
        if known:  # the landmarks the source names (wherever they are: a far one is gated, not duplicated)
            named = set(obs.landmark_id.tolist())
            keys = np.array([k for k, gg in self.lm_group.items() if gg == g and self.lm_src[k] in named],
                            dtype=np.int64)
        else:
            keys = np.array([k for k, gg in self.lm_group.items() if gg == g
                             and np.hypot(*(self.lm_pos[k] - pose[:2])) <= reach], dtype=np.int64)
        if keys.size:
            pts = np.array([self.lm_pos[int(k)] for k in keys])
            cov = np.zeros((3 + 2 * keys.size, 3 + 2 * keys.size))
            cov[:3, :3] = P
            for i, k in enumerate(keys):
                cov[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] = self.lm_cov[int(k)]
            ids = np.array([self.lm_src[int(k)] for k in keys]) if known else keys
            cands = candidates_from_belief(pose, pts, ids, cov, R)
            res = association.associate(obs, cands, cfg.association, rng=self.rng)
            assign = np.asarray(res.assignment, dtype=np.int64)
        else:
            assign = np.where(obs.landmark_id >= 0, NEW, CLUTTER) if known else np.full(len(obs), NEW)
        self.counters["landmarks_gated"] += int(np.sum((assign == CLUTTER) & (obs.landmark_id >= 0)))
        pkey = r * KEY_STRIDE + t
        info = np.linalg.inv(R)
        z = obs.z
        for i in range(len(obs)):
            a = int(assign[i])
            if a == CLUTTER:
                continue
            if known:
                src = int(obs.landmark_id[i])
                if a == NEW:
                    self._create_landmark(g, r, z[i], src)
                key = self.key_of[(g, src)]
                self.f_rb.append((np.array([pkey]), np.array([key]), z[i][None], info[None]))
                continue
            if a == NEW:
                key = self._create_landmark(g, r, z[i], -1)
                self.tentative[key] = 0
            else:
                key = a
            if key in self.tentative:
                self.tentative[key] += 1
                self.held.append((pkey, key, z[i], info))
                if self.tentative[key] >= cfg.confirm_after:
                    del self.tentative[key]
                    mine = [h for h in self.held if h[1] == key]
                    self.held = [h for h in self.held if h[1] != key]
                    for h in mine:
                        self.f_rb.append((np.array([h[0]]), np.array([h[1]]), h[2][None], h[3][None]))
            else:
                self.f_rb.append((np.array([pkey]), np.array([key]), z[i][None], info[None]))

    def _create_landmark(self, g: int, r: int, z: Array, src: int) -> int:
        key = self._new_key()
        gp, gz = range_bearing_inverse_jacobians(self.cur[r], z[None])
        R = self.config.sensor[r].covariance
        self.lm_pos[key] = range_bearing_inverse(self.cur[r], z[None])[0]
        self.lm_cov[key] = gp[0] @ self.cur_cov[r] @ gp[0].T + gz[0] @ R @ gz[0].T
        self.lm_group[key] = g
        self.lm_src[key] = src if src >= 0 else key
        if src >= 0:
            self.key_of[(g, src)] = key
        return key

    # ------------------------------------------------------------------ robot-robot sightings
    def _sightings(self, t: int, ms: MultiStep) -> None:
        s = ms.sightings
        for k in range(len(s)):
            o, b = int(s.observer[k]) - 1, int(s.observed[k]) - 1
            z = np.array([s.range_m[k], s.bearing_rad[k]])
            if not (0 <= o < self.n and 0 <= b < self.n):
                raise ValueError(f"step {t}: sighting names robot {o + 1} -> {b + 1}, not one of 1..{self.n}")
            if self.group[o] == self.group[b]:
                self._add_sighting(t, o, b, z)
            else:
                self.pending.append((t, o, b, z))

    def _add_sighting(self, t: int, o: int, b: int, z: Array, pose_o: Array | None = None,
                      pose_b: Array | None = None) -> None:
        """Gate a sighting against the current estimate (both poses' covariances) and add it as a factor."""
        xo = self.cur[o] if pose_o is None else pose_o
        xb = self.cur[b] if pose_b is None else pose_b
        hp, hl = range_bearing_jacobians(xo, xb[:2])
        S = hp @ self.cur_cov[o] @ hp.T + hl @ self.cur_cov[b][:2, :2] @ hl.T + self.sighting_R
        zp = range_bearing(xo, xb[:2])
        nu = np.array([z[0] - zp[0], angle_diff(z[1], zp[1])])
        if float(nu @ np.linalg.solve(S, nu)) > chi2_gate(self.config.association.new_landmark_probability, 2):
            self.counters["sightings_gated"] += 1
            return
        self.counters["sightings_used"] += 1
        self.f_prr.append((np.array([o * KEY_STRIDE + t]), np.array([b * KEY_STRIDE + t]), z[None],
                           np.linalg.inv(self.sighting_R)[None]))

    # ------------------------------------------------------------------ optimisation
    def _graph(self) -> FactorGraph:
        """The factor graph with every factor so far: the factors added since the last call are appended to the
        cached graph (validated once); a landmark re-keying (merge, fusion) rebuilds it."""
        if self._fg is None:
            self._fg = FactorGraph()
            self._in_graph = {"between": 0, "rb": 0, "prr": 0, "loop": 0}
            if self.prior_keys.size:
                std = self.config.start_std_m
                self._fg.add_prior(self.prior_keys, self.prior_z, np.diag([std**-2, std**-2, std**-2]))
        g = self._fg
        for name, parts in (("between", self.f_between), ("rb", self.f_rb), ("prr", self.f_prr),
                            ("loop", self.f_loop)):
            if not parts:
                continue
            i, j, z, info = (np.concatenate([p[c] for p in parts]) for c in range(4))
            parts[:] = [(i, j, z, info)]
            n0 = self._in_graph[name]
            self._in_graph[name] = i.size
            if n0 == i.size:
                continue
            i, j, z, info = i[n0:], j[n0:], z[n0:], info[n0:]
            if name == "between":
                g.add_between(i, j, z, info)
            elif name == "loop":
                kernel = self.config.loop_robust_kernel
                g.add_between(i, j, z, info, robust=None if kernel == "none" else kernel)
            elif name == "rb":
                kernel = "none" if self.config.association.method == "known" else self.config.landmark_robust_kernel
                g.add_range_bearing(i, j, z, info, robust=None if kernel == "none" else kernel,
                                    robust_param=np.sqrt(chi2_gate(self.config.association.gate_probability, 2)))
            else:
                g.add_pose_range_bearing(i, j, z, info)
        return g

    def _optimize(self, iterations: int, *, marginals: bool = True) -> None:
        graph = self._graph()
        used = graph.point_keys_used()
        pk = np.asarray(self._pk, dtype=np.int64)
        values = Values(pk, np.asarray(self._pv), used, np.array([self.lm_pos[int(k)] for k in used]).reshape(-1, 2))
        opt = Optimizer(graph, OptimizerConfig(method="lm", max_iterations=iterations))
        out, _ = opt.optimize(values)
        self.counters["optimizations"] += 1
        self._pv = list(out.poses)
        for k, p in zip(out.point_keys.tolist(), out.points, strict=True):
            self.lm_pos[k] = p.copy()
        self.cur = out.poses[self.last_row].copy()
        self._solved = (graph, out, opt.analysis)
        if not marginals:
            return
        m = marginal_covariances(graph, out, pk[self.last_row], used, analysis=opt.analysis, solver=opt.solver)
        for r in range(self.n):
            pc = m.block("pose", int(pk[self.last_row[r]]))
            self.node_cov[r] = pc
            self.cur_cov[r] = pc
        for k in used.tolist():
            self.lm_cov[k] = m.block("point", k)

    def _close_loops(self) -> bool:
        """Gate the pending loop candidates against the estimate just solved (one joint marginal over their poses);
        the accepted ones become robust between factors. True when any was accepted."""
        assert self._solved is not None
        graph, values, analysis = self._solved
        keys = self.loops.keys()
        m = marginal_covariances(graph, values, keys, analysis=analysis)
        at = {int(k): 3 * i for i, k in enumerate(keys)}

        def joint_cov(a: int, b: int) -> Array:
            idx = np.r_[at[a]:at[a] + 3, at[b]:at[b] + 3]
            return m.joint[np.ix_(idx, idx)]

        found = self.loops.gate(lambda k: self._pv[self._row[k]], joint_cov)
        self.counters["loops_accepted"] = self.loops.accepted
        self.counters["loops_rejected"] = self.loops.rejected
        for c in found:
            info = np.linalg.inv(c.cov)
            self.f_loop.append((np.array([c.a]), np.array([c.b]), c.T_a_b[None], 0.5 * (info + info.T)[None]))
        return bool(found)

    # ------------------------------------------------------------------ map merging
    def _try_merges(self, t: int) -> None:
        merged = True
        while merged:
            merged = False
            roots = sorted(set(self.group.tolist()))
            for ia, ga in enumerate(roots):
                for gb in roots[ia + 1:]:
                    if self._try_merge(t, ga, gb):
                        merged = True
                        break
                if merged:
                    break

    def _evidence(self, ga: int, gb: int) -> tuple[Array, Array, Array, Array, NDArray[np.bool_], IntArray,
                                                    IntArray, list[tuple[int, int]], list[int]]:
        """Correspondences between groups a and b: landmark pairs and robot-robot sightings (module docstring)."""
        known = self.config.association.method == "known"
        conf = [k for k in self.lm_pos if k not in self.tentative]
        la = [k for k in conf if self.lm_group[k] == ga]
        lb = [k for k in conf if self.lm_group[k] == gb]
        if known:
            src_b = {self.lm_src[k]: k for k in lb}
            lm_pairs = [(ka, src_b[self.lm_src[ka]]) for ka in la if self.lm_src[ka] in src_b]
        else:
            lm_pairs = [(ka, kb) for ka in la for kb in lb]
        pa, ca, pb, cb = [], [], [], []
        for ka, kb in lm_pairs:
            pa.append(self.lm_pos[ka])
            ca.append(self.lm_cov[ka])
            pb.append(self.lm_pos[kb])
            cb.append(self.lm_cov[kb])
        sight: list[int] = []
        for n_, (st, o, b, z) in enumerate(self.pending):
            go, gbb = int(self.group[o]), int(self.group[b])
            if {go, gbb} != {ga, gb}:
                continue
            xo = self._pv[int(self._rows(np.array([o * KEY_STRIDE + st]))[0])]
            xb = self._pv[int(self._rows(np.array([b * KEY_STRIDE + st]))[0])]
            gp, gz = range_bearing_inverse_jacobians(xo, z[None])
            seen = range_bearing_inverse(xo, z[None])[0]
            c_seen = gp[0] @ self.node_cov[o] @ gp[0].T + gz[0] @ self.sighting_R @ gz[0].T
            c_b = self.node_cov[b][:2, :2]
            if go == ga:
                pa_, ca_, pb_, cb_ = seen, c_seen, xb[:2], c_b
            else:
                pa_, ca_, pb_, cb_ = xb[:2], c_b, seen, c_seen
            pa.append(pa_)
            ca.append(ca_)
            pb.append(pb_)
            cb.append(cb_)
            sight.append(n_)
        n_l = len(lm_pairs)
        amb = np.zeros(len(pa), dtype=bool)
        amb[:n_l] = not known
        ida = np.arange(len(pa), dtype=np.int64) + 10**9
        idb = ida.copy()
        if n_l:
            ida[:n_l] = [p[0] for p in lm_pairs]
            idb[:n_l] = [p[1] for p in lm_pairs]
        return (np.array(pa).reshape(-1, 2), np.array(ca).reshape(-1, 2, 2), np.array(pb).reshape(-1, 2),
                np.array(cb).reshape(-1, 2, 2), amb, ida, idb, lm_pairs, sight)

    def _try_merge(self, t: int, ga: int, gb: int) -> bool:
        cfg = self.config
        pa, ca, pb, cb, amb, ida, idb, lm_pairs, sight = self._evidence(ga, gb)
        if pa.shape[0] < cfg.merge_min_pairs:
            return False
        self.counters["merge_attempts"] += 1
        hyp = find_merge(pa, ca, pb, cb, rng=self.rng, ambiguous=amb, ids_a=ida, ids_b=idb,
                         probability=cfg.merge_probability, min_pairs=cfg.merge_min_pairs,
                         min_spread_m=cfg.merge_min_spread_m, iterations=cfg.merge_ransac_iterations)
        n_l = len(lm_pairs)
        inl = hyp.inliers
        robots_a = tuple(int(r) + 1 for r in np.flatnonzero(self.group == ga))
        robots_b = tuple(int(r) + 1 for r in np.flatnonzero(self.group == gb))
        ev = MergeEvent(t, robots_a, robots_b, hyp, int(np.sum(inl < n_l)), int(np.sum(inl >= n_l)))
        if not hyp.accepted:
            if not self.merges or self.merges[-1].hypothesis.reason != hyp.reason:
                self.merges.append(ev)  # rejected: recorded when the reason changes (not every attempt)
            return False
        self.merges.append(ev)
        self.counters["merges"] += 1
        self._apply_merge(ga, gb, hyp.T_a_b, [lm_pairs[i] for i in inl if i < n_l],
                          [sight[i - n_l] for i in inl if i >= n_l])
        self._optimize(cfg.iterations * 4)
        return True

    def _apply_merge(self, ga: int, gb: int, T: Array, lm_pairs: list[tuple[int, int]], sight: list[int]) -> None:
        """Move group b into a's frame, fuse its duplicated landmarks, turn the inlier sightings into factors."""
        rot = np.eye(3)
        rot[:2, :2] = se2.rotation_matrix(T[2])
        robots_b = np.flatnonzero(self.group == gb)
        pk = np.asarray(self._pk, dtype=np.int64)
        moving = np.isin(pk // KEY_STRIDE, robots_b)
        pv = np.asarray(self._pv)
        pv[moving] = se2.compose(T, pv[moving])
        self._pv = list(pv)
        for r in robots_b:
            self.cur[r] = se2.compose(T, self.cur[r])
            self.cur_cov[r] = rot @ self.cur_cov[r] @ rot.T
            self.node_cov[r] = rot @ self.node_cov[r] @ rot.T
        for k in [k for k, g in self.lm_group.items() if g == gb]:
            self.lm_pos[k] = se2.transform_points(T, self.lm_pos[k][None])[0]
            self.lm_cov[k] = rot[:2, :2] @ self.lm_cov[k] @ rot[:2, :2].T
            self.lm_group[k] = ga
        remap = {kb: ka for ka, kb in lm_pairs}
        if self.config.association.method == "known":  # every common id is one landmark, inlier or not
            src_a = {self.lm_src[k]: k for k, g in self.lm_group.items() if g == ga and k not in remap}
            for (g, src), kb in list(self.key_of.items()):
                if g == gb:
                    del self.key_of[(g, src)]
                    if src in src_a and src_a[src] != kb:
                        remap[kb] = src_a[src]
                    else:
                        self.key_of[(ga, src)] = kb
        self._remap_landmarks(remap)
        self.group[robots_b] = ga
        keep = []
        for n_, (st, o, b, z) in enumerate(self.pending):
            if self.group[o] != self.group[b]:
                keep.append((st, o, b, z))
            elif n_ in sight:
                self.counters["sightings_used"] += 1
                self.f_prr.append((np.array([o * KEY_STRIDE + st]), np.array([b * KEY_STRIDE + st]), z[None],
                                   np.linalg.inv(self.sighting_R)[None]))
            else:
                self.counters["sightings_gated"] += 1
        self.pending = keep

    def _remap_landmarks(self, remap: dict[int, int]) -> None:
        """Landmark ``kb`` becomes ``remap[kb]``: its factors are re-keyed and its variable is dropped."""
        if not remap:
            return
        for kb in remap:  # chains (c -> b, b -> a) end at the landmark that stays
            while remap[kb] in remap:
                remap[kb] = remap[remap[kb]]
        self._fg = None  # re-keyed factors: rebuild the graph
        if self.f_rb:
            i, j, z, info = (np.concatenate([p[c] for p in self.f_rb]) for c in range(4))
            j = np.array([remap.get(int(k), int(k)) for k in j], dtype=np.int64)
            self.f_rb[:] = [(i, j, z, info)]
        for kb in remap:
            for d in (self.lm_pos, self.lm_cov, self.lm_group, self.lm_src):
                d.pop(kb, None)
            self.tentative.pop(kb, None)
        self.held = [(h[0], remap.get(h[1], h[1]), h[2], h[3]) for h in self.held]

    def _fuse_duplicates(self) -> None:
        """Unknown association: two confirmed landmarks of one frame whose estimates agree (squared Mahalanobis
        distance of their difference, marginal covariances summed, within the association gate) and that no single
        pose has observed together are one landmark seen twice: fuse them (greedily, closest pair first)."""
        keys = np.array([k for k in self.lm_pos if k not in self.tentative], dtype=np.int64)
        if keys.size < 2 or not self.f_rb:
            return
        pos = np.array([self.lm_pos[int(k)] for k in keys])
        cov = np.array([self.lm_cov[int(k)] for k in keys])
        grp = np.array([self.lm_group[int(k)] for k in keys])
        d = pos[:, None, :] - pos[None, :, :]
        S = cov[:, None] + cov[None, :]
        S[np.arange(keys.size), np.arange(keys.size)] = np.eye(2)
        d2 = np.einsum("abi,abij,abj->ab", d, np.linalg.inv(S), d)
        gate = chi2_gate(self.config.association.gate_probability, 2)
        cand = (d2 <= gate) & (grp[:, None] == grp[None, :]) & np.triu(np.ones_like(d2, dtype=bool), 1)
        if not np.any(cand):
            return
        i, j, _, _ = (np.concatenate([p[c] for p in self.f_rb]) for c in range(4))
        seen_by = {int(k): set(i[j == k].tolist()) for k in keys}
        remap: dict[int, int] = {}
        for a, b in sorted(zip(*np.nonzero(cand), strict=True), key=lambda ab: d2[ab[0], ab[1]]):
            ka, kb = int(keys[a]), int(keys[b])
            if ka in remap or kb in remap or (ka in remap.values() and kb in remap.values()):
                continue
            if seen_by[ka] & seen_by[kb]:
                continue  # seen together from one pose: two landmarks
            remap[kb] = ka
            seen_by[ka] |= seen_by[kb]
        self.counters["landmarks_fused"] += len(remap)
        self._remap_landmarks(remap)

