"""The server's joint pose graph over every drone's keyframes, its inter-robot loop closures and map tiles.

Frames: every drone starts at a surveyed dock whose pose in the warehouse frame it announces in ``hello`` and runs
its own front end in that frame, so all drones share one frame up to their drift ("known starts"). The first
keyframe of each drone gets a prior at the pose the drone reported for it; everything else is relative: the drones'
own edges (odometry chain, own loops) and the inter-robot loops found here.

Inter-robot loops: a new keyframe is compared with the keyframes of OTHER drones within ``loop_radius_m`` in the
merged frame (heading within ``loop_max_turn_rad``; nearest first, range-histogram descriptor distance as a
pre-filter). A candidate is verified on the compact point sets alone: correlative matching against the candidate's
local map (it and ``loop_map_keyframes`` neighbours on each side) with the score and ambiguity gates of the lidar
estimator, then point-to-line ICP with its fitness, residual and covariance gates and the chi-square agreement gate
(defaults taken from :class:`~slam2d.graph.lidar.LidarSLAMConfig`, not tuned here).

Floor markers: a keyframe's marker sightings (ids read from the tags, so association is certain) are ``point``
factors to one shared node per marker id. A marker read by two drones ties them with no search and no ambiguity, along
an aisle as well as across it; one read again by the same drone ``marker_resight_keyframes`` later closes its loop.
Either counts as a loop for the solve schedule.

Optimisation: Gauss-Newton on the whole joint graph from the current estimate, after every update that brought a
loop (inter-robot or a drone's own) and every ``solve_every`` keyframes otherwise; both gaps grow with the graph
(``solve_growth``) so that the whole-graph work per keyframe stays bounded as the fleet's map grows. Between
solves a new keyframe is placed by chaining its drone's edge, which the drone fused with its odometry. Loop edges
(a drone's own and inter-robot) carry a Cauchy kernel; the keyframe chains and marker readings are plain least
squares. Surveyed markers (``surveyed_markers``, from ``slam2d map-server --marker-survey``) get priors at their
surveyed positions and tie every drone that reads one to the warehouse frame.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.fleet.journal import LoopRow
from slam2d.fleet.protocol import Edge, Keyframe, info_matrix, unpack_descriptor, unpack_markers, unpack_points
from slam2d.frontend.correlative import CorrelativeConfig, correlative_match
from slam2d.frontend.icp import icp
from slam2d.geometry import se2
from slam2d.geometry.angles import wrap_angle
from slam2d.graph.graph import FactorGraph, Values
from slam2d.graph.lidar import LidarSLAMConfig
from slam2d.graph.linear import SolverError
from slam2d.graph.optimizer import OptimizerConfig, optimize

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: a solve whose result holds a value beyond this (m, rad) diverged and is not taken (drones send at most 1e6)
MAX_SOLVED = 1e12


@dataclass(frozen=True, slots=True, kw_only=True)
class JointConfig:
    """Settings of the server's joint graph."""

    prior_sigma_xy_m: float = 0.01
    """standard deviation of each drone's first keyframe about its reported (dock) pose (m)."""
    prior_sigma_theta_rad: float = 0.002
    """... and in heading (rad)."""
    loop_radius_m: float = 3.0
    """other drones' keyframes within this distance (merged frame) are loop candidates (m)."""
    loop_max_turn_rad: float = 1.0
    """... whose heading differs by less than this (the lidar sees a half circle ahead) (rad)."""
    loop_max_descriptor_l1: float = 0.6
    """... and whose range histograms differ by less than this (L1 of the beam fractions)."""
    loop_every: int = 3
    """search inter-robot loops for every this many keyframes of a drone."""
    loop_candidates: int = 2
    """at most this many candidates are verified per search."""
    loop_map_keyframes: int = 3
    """a candidate's local map: its keyframe and this many on each side (same drone)."""
    correlative: CorrelativeConfig = field(default_factory=lambda: CorrelativeConfig(window_xy_m=0.6,
                                                                                     window_theta_rad=0.2))
    """the correlative search around the current relative estimate."""
    sliding_loops: bool = True
    """accept loops whose alignment slides along one axis, with no information along it (see ``_verify``)."""
    sliding_sigma_m: float = 5.0
    """standard deviation a sliding loop keeps along its free axis (m): ICP's own covariance there is far too
    confident (measured: 4 cm for a 25 cm error)."""
    solve_every: int = 50
    """keyframes between whole-graph solves when no loop arrived."""
    loop_solve_gap: int = 10
    """a loop waits until this many keyframes arrived since the last solve (bounds the solves per second when
    drones run faster than real time)."""
    loop_kernel: str | None = "cauchy"
    """robust kernel on every loop edge (a drone's own and inter-robot; the keyframe chains stay plain least
    squares): measured at 10 simulated minutes, 5 drones, about 1 % of the loops are off by more than 20 cm."""
    loop_kernel_scale: float = 3.0
    """scale of ``loop_kernel`` in standard deviations (the lidar back end's own default)."""
    solve_growth: float = 0.02
    """the gaps above are at least this fraction of the graph's keyframes (a whole-graph solve costs time in
    proportion to the graph; 5 drones for 30 minutes make ~9000 keyframes, a solve every 180 at the end)."""
    solve_iterations: int = 3
    """Gauss-Newton iterations per solve (warm-started from the current estimate)."""
    marker_resight_keyframes: int = 10
    """a drone reading a marker again this many of its keyframes after its last reading of it closes a loop."""
    surveyed_markers: tuple[tuple[int, float, float], ...] = ()
    """floor markers whose warehouse positions were surveyed, (id, x, y): each gets a prior of ``survey_sigma_m``
    (empty: markers are landmarks placed by the drones alone, which fixes consistency but not drift)."""
    survey_sigma_m: float = 0.01
    """standard deviation of a surveyed marker position (m)."""
    tile_m: float = 10.0
    """side of a map tile (m)."""
    tile_resolution_m: float = 0.2
    """cell of a tile's hit-count raster (m)."""
    raster_place_m: float = 1.0
    """a tile's raster draws the newest keyframe in each cell of this size and heading octant (m)."""


def free_axis(info: Array, sigma_m: float) -> Array:
    """``info`` with its weakest translation direction (the slide axis) replaced by a standard deviation of
    ``sigma_m``: the information along that axis, and its coupling to the others, removed."""
    w, v = np.linalg.eigh(info[:2, :2])
    axis = np.array([v[0, 0], v[1, 0], 0.0])
    p = np.eye(3) - np.outer(axis, axis)
    return np.asarray(p @ info @ p + np.outer(axis, axis) / sigma_m**2, dtype=np.float64)


@dataclass(frozen=True)
class SolveRecord:
    nodes: int
    edges: int
    seconds: float


class JointGraph:
    """Every committed keyframe as a node (key = arrival order), every edge and accepted loop as a factor."""

    def __init__(self, config: JointConfig | None = None) -> None:
        self.config = config or JointConfig()
        self.lidar = LidarSLAMConfig()
        self.poses = np.zeros((0, 3))
        self.reported = np.zeros((0, 3))
        self.node_drone = np.zeros(0, np.int64)
        self.node_kf = np.zeros(0, np.int64)
        self.desc = np.zeros((0, 17))
        self.points: list[Array] = []
        self.keys: dict[int, list[int]] = {}  # drone -> node keys in keyframe order
        self.docks: dict[int, Array] = {}
        self._ei: list[int] = []
        self._ej: list[int] = []
        self._z: list[Array] = []
        self._info: list[Array] = []
        self._is_loop: list[bool] = []
        self.loops: list[LoopRow] = []
        self._since_solve = 0
        self._loops_pending = False
        self._last_search: dict[int, int] = {}
        self.solves: list[SolveRecord] = []
        self.failed_solves = 0  # solves that left the estimate unchanged (see solve)
        self.tile_version: dict[tuple[int, int], int] = {}
        self._rasters: dict[tuple[int, int], tuple[int, bytes]] = {}
        self._version = 0
        self.marker_ids: list[int] = []
        self._marker_slot: dict[int, int] = {}
        self.markers = np.zeros((0, 2))
        self._mk_key: list[int] = []  # per sighting: node key, marker slot, z (2,), sigma (m)
        self._mk_slot: list[int] = []
        self._mk_z: list[Array] = []
        self._mk_sigma: list[float] = []
        self.marker_last: dict[tuple[int, int], int] = {}  # (marker slot, drone) -> its newest reading keyframe
        self.marker_links = 0  # sightings of a marker another drone had read
        self.marker_resightings = 0  # a drone reading a marker again after marker_resight_keyframes
        self._survey = {int(i): np.array([x, y], np.float64) for i, x, y in self.config.surveyed_markers}

    # ------------------------------------------------------------------ building
    def add_drone(self, drone: int, dock: Array) -> None:
        self.keys.setdefault(drone, [])
        self.docks[drone] = np.asarray(dock, np.float64)

    def key(self, drone: int, kf: int) -> int:
        return self.keys[drone][kf]

    def add_keyframes(self, drone: int, kfs: tuple[Keyframe, ...] | list[Keyframe], edges: tuple[Edge, ...] |
                      list[Edge]) -> list[int]:
        """Add a drone's keyframes (placed by its own pose change since its newest node) and edges; new keys."""
        own = self.keys[drone]
        if not kfs:
            new: list[int] = []
        else:
            reported = np.asarray([k.pose for k in kfs], np.float64).reshape(-1, 3)
            if own:  # keep the drone's own shape, moved the way the server has moved its newest node
                last = own[-1]
                corr = se2.compose(self.poses[last], se2.inverse(self.reported[last]))
                guess = se2.compose(np.broadcast_to(corr, reported.shape), reported)
            else:
                guess = reported.copy()
            # better: chain the drone's edge to the previous keyframe (its front end's own pose drifts along the
            # aisles; the edge fuses odometry, see fleet.drone.keyframe_edge), so a node is placed well before
            # its first solve
            step = {e.b: e for e in edges if e.b == e.a + 1}
            first_id = kfs[0].id
            for i, k in enumerate(kfs):
                e = step.get(k.id)
                if e is None or k.id == 0:
                    continue
                prev = guess[i - 1] if k.id - 1 >= first_id else self.poses[own[k.id - 1]]
                guess[i] = se2.compose(prev, np.asarray(e.z, np.float64))
            first = len(self.poses)
            new = list(range(first, first + len(kfs)))
            self.poses = np.vstack([self.poses, guess])
            self.reported = np.vstack([self.reported, reported])
            self.node_drone = np.concatenate([self.node_drone, np.full(len(kfs), drone, np.int64)])
            self.node_kf = np.concatenate([self.node_kf, np.asarray([k.id for k in kfs], np.int64)])
            self.desc = np.vstack([self.desc, [unpack_descriptor(k.desc) for k in kfs]])
            self.points.extend(unpack_points(k.pts) for k in kfs)
            own.extend(new)
            for key in new:
                self._touch(key)
            for key, k in zip(new, kfs, strict=True):
                if k.mk:
                    self._add_markers(drone, key, k)
        for e in edges:
            self._add_factor(own[e.a], own[e.b], e.z, info_matrix(e.info), loop=abs(e.b - e.a) > 1)
            self._loops_pending |= abs(e.b - e.a) > 1
        self._since_solve += len(kfs)
        return new

    def _add_markers(self, drone: int, key: int, kf: Keyframe) -> None:
        """The marker sightings of node ``key``: factors to shared marker nodes (a new one starts at the node's
        estimate composed with the sighting)."""
        ids, xy, sigma = unpack_markers(kf.mk)
        for mid, z, sg in zip(ids.tolist(), xy, sigma.tolist(), strict=True):
            s = self._marker_slot.get(mid)
            if s is None:
                s = self._marker_slot[mid] = len(self.marker_ids)
                self.marker_ids.append(mid)
                start = self._survey.get(mid)
                if start is None:
                    start = se2.transform_points(self.poses[key], z[None])[0]
                self.markers = np.vstack([self.markers, start[None]])
            others = any(d != drone for (m, d) in self.marker_last if m == s)
            last = self.marker_last.get((s, drone))
            if others:
                self.marker_links += 1
            resight = last is not None and kf.id - last >= self.config.marker_resight_keyframes
            self.marker_resightings += resight
            if others or resight or mid in self._survey:  # a surveyed marker is an absolute fix
                self._loops_pending = True
            self.marker_last[(s, drone)] = kf.id
            self._mk_key.append(key)
            self._mk_slot.append(s)
            self._mk_z.append(z)
            self._mk_sigma.append(sg)

    def marker_drones(self) -> dict[int, list[int]]:
        """Marker id -> the drones that read it."""
        out: dict[int, list[int]] = {}
        for s, d in sorted(self.marker_last):
            out.setdefault(self.marker_ids[s], []).append(d)
        return out

    def _add_factor(self, i: int, j: int, z: Array, info: Array, *, loop: bool) -> None:
        self._is_loop.append(loop)
        self._ei.append(i)
        self._ej.append(j)
        self._z.append(np.asarray(z, np.float64))
        self._info.append(np.asarray(info, np.float64))

    def add_loop(self, lp: LoopRow) -> None:
        self.loops.append(lp)
        self._loops_pending = True
        self._add_factor(self.key(lp.drone_a, lp.a), self.key(lp.drone_b, lp.b), lp.z, lp.info, loop=True)

    # ------------------------------------------------------------------ loops
    def search_loops(self, keys: list[int], stamp: float) -> list[LoopRow]:
        """Inter-robot loops of the new nodes ``keys`` (verified, not yet added)."""
        cfg = self.config
        out: list[LoopRow] = []
        others_exist = len(self.keys) > 1
        for n in keys if others_exist else []:
            d = int(self.node_drone[n])
            kf = int(self.node_kf[n])
            if kf - self._last_search.get(d, -cfg.loop_every) < cfg.loop_every or len(self.points[n]) < 20:
                continue
            self._last_search[d] = kf
            diff = self.poses[:, :2] - self.poses[n, :2]
            dist = np.hypot(diff[:, 0], diff[:, 1])
            turn = np.abs(wrap_angle(self.poses[:, 2] - self.poses[n, 2]))
            l1 = np.abs(self.desc - self.desc[n]).sum(axis=1)
            ok = ((self.node_drone != d) & (dist < cfg.loop_radius_m) & (turn < cfg.loop_max_turn_rad)
                  & (l1 < cfg.loop_max_descriptor_l1))
            cand = np.flatnonzero(ok)
            taken: set[int] = set()
            for c in cand[np.argsort(dist[cand], kind="stable")].tolist():
                if int(self.node_drone[c]) in taken:
                    continue  # one candidate per other drone
                taken.add(int(self.node_drone[c]))
                lp = self._verify(c, n, stamp)
                if lp is not None:
                    out.append(lp)
                if len(taken) == cfg.loop_candidates:
                    break
        return out

    def _local_map(self, c: int) -> Array:
        """Points of node ``c`` and its drone neighbours, in ``c``'s frame (merged estimates)."""
        d, kf = int(self.node_drone[c]), int(self.node_kf[c])
        own = self.keys[d]
        m = self.config.loop_map_keyframes
        parts = [se2.transform_points(self.poses[own[i]], self.points[own[i]])
                 for i in range(max(0, kf - m), min(len(own), kf + m + 1))]
        return se2.inverse_transform_points(self.poses[c], np.vstack(parts))

    def _verify(self, c: int, n: int, stamp: float) -> LoopRow | None:
        """A verified loop T_c_n with its information, or None.

        Two kinds pass. A unique match: the correlative search finds one clearly best alignment and ICP refines it
        (every gate of the lidar estimator). A sliding match: the place scores as well but slides along an axis (an
        aisle's length, which the lidar cannot see the end of); ICP from the current estimate then fixes what the
        scans do fix (across the aisle, the heading) and its covariance leaves the axis free, so the loop carries
        no information along it instead of a guess."""
        lc = self.lidar
        pts, target = self.points[n], self._local_map(c)
        guess = se2.between(self.poses[c], self.poses[n])
        cm = correlative_match(pts, target, guess, self.config.correlative)
        if cm.score < lc.loop_min_score:
            return None
        unique = cm.ambiguity <= lc.loop_max_ambiguity
        if not unique and not self.config.sliding_loops:
            return None
        res = icp(pts, target, initial=cm.transform if unique else guess, config=lc.loop_icp)
        if not (res.converged and res.fitness >= lc.loop_min_fitness and res.rmse_m <= lc.loop_max_rmse_m
                and np.all(np.isfinite(res.covariance))):
            return None
        floor = np.diag([lc.min_sigma_xy_m**2, lc.min_sigma_xy_m**2, lc.min_sigma_theta_rad**2])
        info = np.asarray(np.linalg.inv(res.covariance + floor), dtype=np.float64)
        if unique:
            e = se2.local(res.transform, cm.transform)
            if float(e @ info @ e) > lc.loop_chi2:
                return None
        else:
            info = free_axis(info, self.config.sliding_sigma_m)
        # ICP's covariance is over x, y in c's frame; the between factor's error is in n's: turn it
        return LoopRow(int(self.node_drone[c]), int(self.node_kf[c]), int(self.node_drone[n]), int(self.node_kf[n]),
                       res.transform, se2.covariance_in_frame(info, res.transform[2]), stamp)

    # ------------------------------------------------------------------ optimisation
    def needs_solve(self) -> bool:
        c = self.config
        grow = int(c.solve_growth * len(self.poses))  # a solve costs O(nodes): amortised O(1 / solve_growth)
        return ((self._loops_pending and self._since_solve >= max(c.loop_solve_gap, grow))
                or self._since_solve >= max(c.solve_every, grow))

    def settle(self, iterations: int = 10) -> SolveRecord | None:
        """Solve once more if anything arrived since the last solve (a drone landed: its newest keyframes would
        otherwise keep their first placement until another drone's update brings a solve)."""
        if self._since_solve == 0 and not self._loops_pending:
            return None
        return self.solve(iterations)

    def solve(self, iterations: int | None = None) -> SolveRecord:
        """Gauss-Newton on the whole joint graph from the current estimate; marks moved tiles."""
        cfg = self.config
        t0 = time.perf_counter()
        g = FactorGraph()
        if self._ei:
            ei, ej, z, info = (np.asarray(a) for a in (self._ei, self._ej, self._z, self._info))
            loop = np.asarray(self._is_loop, bool)
            for sel, kernel in ((~loop, None), (loop, cfg.loop_kernel)):
                if sel.any():
                    g.add_between(ei[sel], ej[sel], z[sel], info[sel], robust=kernel,
                                  robust_param=cfg.loop_kernel_scale)
        firsts = [own[0] for own in self.keys.values() if own]
        prior_info = np.diag([cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_xy_m**-2, cfg.prior_sigma_theta_rad**-2])
        g.add_prior(np.asarray(firsts), self.reported[firsts], np.repeat(prior_info[None], len(firsts), axis=0))
        if self._mk_key:
            sig = np.asarray(self._mk_sigma)
            g.add_point(np.asarray(self._mk_key), np.asarray(self._mk_slot), np.asarray(self._mk_z),
                        np.eye(2)[None] / sig[:, None, None] ** 2)
        known = [(s, self._survey[m]) for s, m in enumerate(self.marker_ids) if m in self._survey]
        if known:
            g.add_point_prior(np.asarray([s for s, _ in known]), np.asarray([xy for _, xy in known]),
                              np.repeat(np.eye(2)[None] / cfg.survey_sigma_m**2, len(known), axis=0))
        before = self.poses.copy()
        start = Values(np.arange(len(self.poses)), self.poses, np.arange(len(self.markers)), self.markers)
        out = None
        # Gauss-Newton; if it cannot factor the system (numerically singular: drones' values that pass every
        # per-message check can still combine badly), Levenberg-Marquardt from the same start, and if that fails
        # too, or leaves non-finite or absurd values, the estimate stays as it was: the server must not die on a
        # solve (nor on tile indices of poses beyond 64-bit integers)
        for method in ("gn", "lm"):
            try:
                out, _ = optimize(g, start, OptimizerConfig(method=method, gauge="none",
                                                            max_iterations=iterations or cfg.solve_iterations))
            except SolverError:
                continue
            if all(np.all(np.abs(a) <= MAX_SOLVED) for a in (out.poses, out.points)):  # also False for nan
                break
            out = None
        if out is None:
            self.failed_solves += 1
        else:
            self.poses = np.asarray(out.poses, np.float64).copy()
            if len(self.markers):
                self.markers[out.point_keys] = out.points
        moved = np.flatnonzero(np.hypot(*(self.poses[:, :2] - before[:, :2]).T) > 0.02)
        for k in moved.tolist():
            self._touch(k)
        self._since_solve = 0
        self._loops_pending = False
        rec = SolveRecord(len(self.poses), len(self._ei) + len(firsts) + len(self._mk_key), time.perf_counter() - t0)
        self.solves.append(rec)
        return rec

    # ------------------------------------------------------------------ tiles
    def _tile_of(self, xy: Array) -> tuple[int, int]:
        t = self.config.tile_m
        return int(np.floor(xy[0] / t)), int(np.floor(xy[1] / t))

    def _touch(self, key: int) -> None:
        self._version += 1
        self.tile_version[self._tile_of(self.poses[key, :2])] = self._version

    def tiles_near(self, xy: Array, radius_m: float) -> list[tuple[int, int]]:
        t = self.config.tile_m
        return [k for k in self.tile_version if np.hypot((k[0] + 0.5) * t - xy[0], (k[1] + 0.5) * t - xy[1])
                <= radius_m + t]

    def tile_raster(self, tile: tuple[int, int], reach_m: float = 12.0) -> bytes:
        """Hit counts (uint8, saturating) of the keyframe points in ``tile`` (the newest keyframe per place, see
        :meth:`_newest_per_place`), zlib-compressed, row-major (y, x); computed once per tile version."""
        version = self.tile_version.get(tile, -1)
        hit = self._rasters.get(tile)
        if hit is not None and hit[0] == version:
            return hit[1]
        out = self._raster(tile, reach_m)
        self._rasters[tile] = (version, out)
        return out

    def _raster(self, tile: tuple[int, int], reach_m: float) -> bytes:
        cfg = self.config
        n = round(cfg.tile_m / cfg.tile_resolution_m)
        lo = np.array(tile, np.float64) * cfg.tile_m
        centre = lo + cfg.tile_m / 2
        near = np.flatnonzero(np.hypot(*(self.poses[:, :2] - centre).T) <= reach_m + cfg.tile_m)
        near = self._newest_per_place(near)
        counts = np.zeros(n * n, np.int64)
        if near.size:
            world = np.vstack([se2.transform_points(self.poses[k], self.points[k]) for k in near.tolist()])
            ij = np.floor((world - lo) / cfg.tile_resolution_m).astype(np.int64)
            inside = np.all((ij >= 0) & (ij < n), axis=1)
            counts = np.bincount(ij[inside, 1] * n + ij[inside, 0], minlength=n * n)
        return zlib.compress(np.minimum(counts, 255).astype(np.uint8).tobytes(), 6)

    def _newest_per_place(self, keys: IntArray) -> IntArray:
        """Of nodes ``keys``, the newest in each ``raster_place_m`` cell and heading octant: a place flown over
        again and again adds the same walls, so the raster's work follows the mapped area, not the flight time."""
        if not keys.size:
            return keys
        p = self.poses[keys]
        cell = np.floor(p[:, :2] / self.config.raster_place_m).astype(np.int64)
        octant = np.floor((p[:, 2] + np.pi) / (np.pi / 4)).astype(np.int64) % 8
        place = (cell[:, 0] * 100003 + cell[:, 1]) * 8 + octant
        _, last = np.unique(place[::-1], return_index=True)  # first of the reversed order = newest
        return np.sort(keys[::-1][last])

    def drone_poses(self, drone: int) -> Array:
        return self.poses[self.keys.get(drone, [])]
