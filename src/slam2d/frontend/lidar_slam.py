"""2D lidar SLAM on raw scan logs: scan-to-local-map ICP odometry, ICP loop closures, a pose graph, an occupancy map.

Pipeline (:func:`run_lidar_slam`):

1. keyframes: a scan becomes a keyframe when the logged odometry moved ``keyframe_distance_m`` or
   ``keyframe_angle_rad`` since the last keyframe (with ``track_scans`` every scan in between is matched too, so
   the keyframe's initial guess comes from tracking rather than from several scans of odometry);
2. odometry: each keyframe is matched by point-to-line ICP against the points of the previous ``local_map_keyframes``
   keyframes (placed at their current estimates), starting from the previous estimate composed with the odometry
   increment; the result becomes a relative-pose edge with the ICP covariance (floored, see the config);
3. loop closures: every ``loop_every`` keyframes, old keyframes whose estimate lies within ``loop_radius_m`` are
   matched against the new one (ICP against a small local map around the old keyframe); a match with enough
   overlap and a small residual adds an edge;
4. after new loop edges the pose graph is re-solved (:func:`solve_pose_graph`, first pose fixed);
5. non-keyframe scans get the pose of their keyframe composed with the odometry increment since it, or, with
   ``refine_scans``, are each matched by ICP to the local map around their keyframe (fixed at its optimised pose).

The pose graph is solved by the graph back end (:mod:`slam2d.graph`, Gauss-Newton with a Cauchy kernel on the loop
edges).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.config import check_positive
from slam2d.frontend.icp import ICPConfig, icp
from slam2d.geometry import se2

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True, kw_only=True)
class LidarSlamConfig:
    """Settings of the lidar SLAM pipeline."""

    keyframe_distance_m: float = 0.3
    """odometry translation that starts a new keyframe (m)."""
    keyframe_angle_rad: float = 0.25
    """odometry rotation that starts a new keyframe (rad)."""
    local_map_keyframes: int = 6
    """previous keyframes whose points form the matching target."""
    max_range_m: float = 25.0
    """beams longer than this are not used for matching (far points are sparse and noisy) (m)."""
    icp: ICPConfig = field(default_factory=lambda: ICPConfig(max_correspondence_m=0.5, trim_fraction=0.85,
                                                                           tolerance=1e-4))
    """scan-matching settings for odometry."""
    min_sigma_xy_m: float = 0.02
    """floor on the standard deviation of a scan-matching edge in x and y (ICP Hessians are over-confident) (m)."""
    min_sigma_theta_rad: float = 0.005
    """floor on the standard deviation of a scan-matching edge in heading (rad)."""
    loop_closure: bool = True
    """search for loop closures and solve the pose graph (False: scan-matching odometry only)."""
    loop_every: int = 5
    """search loops every this many keyframes."""
    loop_radius_m: float = 4.0
    """old keyframes whose estimate is within this distance are loop candidates (m)."""
    loop_min_separation: int = 30
    """keyframes closer than this in sequence are not loop candidates."""
    loop_candidates: int = 3
    """at most this many candidates are verified per search (the nearest ones)."""
    loop_min_fitness: float = 0.6
    """a loop needs at least this fraction of the scan's points matched."""
    loop_max_rmse_m: float = 0.08
    """a loop's point-to-line residual RMS must be below this (m)."""
    loop_max_correction_m: float = 2.0
    """a loop may move the new keyframe relative to its guess by at most this much (m)."""
    cauchy_scale: float = 3.0
    """Cauchy kernel scale on loop edges, in standard deviations (0: plain least squares)."""
    solver_iterations: int = 10
    """Gauss-Newton iterations per pose-graph solve."""
    track_scans: bool = True
    """match every scan (not only keyframes) against the local map as it arrives: the next keyframe starts from the
    tracked pose instead of a multi-scan odometry guess, and scans between keyframes keep their matched pose
    relative to their keyframe (needed when odometry is poor or out of step with the laser, e.g. fr079; False:
    keyframes only, about 3x faster)."""
    refine_scans: bool = False
    """after the graph solve, match every non-keyframe scan to the local map around its keyframe (slower: one ICP
    per scan) instead of placing it by odometry from its keyframe."""

    def __post_init__(self) -> None:
        check_positive(self, "keyframe_distance_m", "keyframe_angle_rad", "max_range_m", "min_sigma_xy_m",
                       "min_sigma_theta_rad", "loop_radius_m", "loop_min_fitness", "loop_max_rmse_m",
                       "loop_max_correction_m")
        for n in ("local_map_keyframes", "loop_every", "loop_candidates", "solver_iterations"):
            if getattr(self, n) < 1:
                raise ValueError(f"LidarSlamConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.loop_min_separation < 1:
            raise ValueError(f"LidarSlamConfig.loop_min_separation must be >= 1 (got {self.loop_min_separation})")
        if self.cauchy_scale < 0:
            raise ValueError(f"LidarSlamConfig.cauchy_scale must be >= 0 (got {self.cauchy_scale})")


@dataclass(frozen=True)
class PoseGraphEdges:
    """Relative-pose constraints ``between(x_i, x_j) ~ z``. Shapes: i (E,), j (E,), z (E,3), info (E,3,3), loop (E,)."""

    i: IntArray
    j: IntArray
    z: Array
    info: Array
    loop: NDArray[np.bool_]


def solve_pose_graph(poses: ArrayLike, edges: PoseGraphEdges, iterations: int = 10, cauchy_scale: float = 0.0,
                     tol: float = 1e-6) -> tuple[Array, float]:
    """Optimise the keyframe poses with the graph back end (:mod:`slam2d.graph`); pose 0 is held fixed.

    Sequential edges are plain least squares; loop edges carry a Cauchy kernel with scale ``cauchy_scale`` (in
    standard deviations, sqrt(chi2)) when it is > 0. Gauss-Newton, at most ``iterations`` iterations.
    Returns the optimised poses (N,3) and the final cost. Shapes: poses (N,3).
    """
    from slam2d.graph import FactorGraph, OptimizerConfig, Values, optimize

    x = np.asarray(poses, dtype=np.float64).copy()
    n = len(x)
    if len(edges.i) == 0 or n < 2:
        return x, 0.0
    g = FactorGraph()
    seq, loop = ~edges.loop, edges.loop
    if seq.any():
        g.add_between(edges.i[seq], edges.j[seq], edges.z[seq], edges.info[seq])
    if loop.any():
        g.add_between(edges.i[loop], edges.j[loop], edges.z[loop], edges.info[loop],
                      robust="cauchy" if cauchy_scale > 0 else None, robust_param=cauchy_scale or 1.0)
    values = Values()
    values.add_poses(np.arange(n), x)
    # Gauss-Newton: the warm start is good (previous solution + new keyframes), and LM's rejected steps would eat
    # the small iteration budget (measured on aces: LM with 10 iterations left the map visibly bent)
    cfg = OptimizerConfig(method="gn", max_iterations=max(iterations, 1), step_tol=tol)
    out, summary = optimize(g, values, cfg, fixed_pose_keys=[0])
    order = np.argsort(out.pose_keys)
    return np.asarray(out.poses[order], dtype=np.float64), float(summary.cost_final)


@dataclass(frozen=True)
class LidarSlamResult:
    """Output of :func:`run_lidar_slam`. Shapes: poses (S,3) one per scan; keyframes (K,) scan indices;
    keyframe_poses (K,3); odometry_poses (S,3) scan-matching odometry before loop closure, per scan."""

    poses: Array
    keyframes: IntArray
    keyframe_poses: Array
    odometry_poses: Array
    edges: PoseGraphEdges
    loops_accepted: int
    loops_tried: int
    icp_failures: int


def _scan_points(ranges: Array, angles: Array, max_range: float) -> Array:
    ok = np.isfinite(ranges) & (ranges > 0.05) & (ranges < max_range)
    return np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])], axis=-1)


def _floor_cov(cov: Array, cfg: LidarSlamConfig) -> Array:
    if not np.all(np.isfinite(cov)):
        cov = np.diag([0.2, 0.2, 0.05]) ** 2  # ICP failed: the odometry guess with a loose covariance
    return cov + np.diag([cfg.min_sigma_xy_m**2, cfg.min_sigma_xy_m**2, cfg.min_sigma_theta_rad**2])


def run_lidar_slam(odom_poses: ArrayLike, ranges: ArrayLike, angles: ArrayLike, max_range: float,
                   config: LidarSlamConfig | None = None) -> LidarSlamResult:
    """Run the pipeline on a scan log. Shapes: odom_poses (S,3) logged odometry pose per scan, ranges (S,B),
    angles (B,). Returns poses in the frame of the first scan's pose (first pose = odom_poses[0])."""
    cfg = config or LidarSlamConfig()
    odom = np.asarray(odom_poses, dtype=np.float64)
    rng_all = np.asarray(ranges, dtype=np.float64)
    ang = np.asarray(angles, dtype=np.float64)
    s = len(odom)
    if s == 0:
        raise ValueError("run_lidar_slam: the log has no scans")
    lim = min(max_range, cfg.max_range_m)

    # 1. keyframes from odometry motion (a short loop over scans: a scalar test per scan)
    kf = [0]
    for t in range(1, s):
        d = se2.between(odom[kf[-1]], odom[t])
        if np.hypot(d[0], d[1]) >= cfg.keyframe_distance_m or abs(d[2]) >= cfg.keyframe_angle_rad:
            kf.append(t)
    kfa = np.asarray(kf, dtype=np.int64)
    pts = [_scan_points(rng_all[t], ang, lim) for t in kfa]
    est = np.zeros((len(kfa), 3))
    est[0] = odom[0]
    ei: list[int] = []
    ej: list[int] = []
    ez: list[Array] = []
    einfo: list[Array] = []
    eloop: list[bool] = []
    failures = 0
    loops_ok = 0
    loops_tried = 0
    loop_cfg = ICPConfig(method="point-to-line", max_correspondence_m=0.6, trim_fraction=0.8, max_iterations=50,
                         tolerance=1e-4)

    def local_map(center: int, lo: int, hi: int, frame: Array) -> Array:
        idx = range(max(lo, 0), min(hi, center + 1))
        world = [se2.transform_points(est[k], pts[k]) for k in idx]
        return se2.inverse_transform_points(frame, np.vstack(world)) if world else np.zeros((0, 2))

    def add_edge(i: int, j: int, z: Array, cov: Array, loop: bool) -> None:
        ei.append(i)
        ej.append(j)
        ez.append(z)
        einfo.append(np.asarray(np.linalg.inv(_floor_cov(cov, cfg)), dtype=np.float64))
        eloop.append(loop)

    odo_only = np.zeros_like(est)
    odo_only[0] = est[0]
    rel = np.zeros((s, 3))  # with track_scans: each scan's pose relative to its keyframe
    for k in range(1, len(kfa)):
        guess = se2.compose(est[k - 1], se2.between(odom[kfa[k - 1]], odom[kfa[k]]))
        target = local_map(k - 1, k - cfg.local_map_keyframes, k, est[k - 1])
        if cfg.track_scans:
            cur = np.zeros(3)  # tracked pose relative to keyframe k-1, one small odometry step at a time
            for m in range(kfa[k - 1] + 1, kfa[k]):
                g = se2.compose(cur, se2.between(odom[m - 1], odom[m]))
                r_m = icp(_scan_points(rng_all[m], ang, lim), target, initial=g, config=cfg.icp)
                cur = r_m.transform if r_m.converged and r_m.fitness > 0.5 else g
                rel[m] = cur
            guess = se2.compose(est[k - 1], se2.compose(cur, se2.between(odom[kfa[k] - 1], odom[kfa[k]])))
        res = icp(pts[k], target, initial=se2.between(est[k - 1], guess), config=cfg.icp)
        if res.converged and res.fitness > 0.5:
            z, cov = res.transform, res.covariance
        else:
            failures += 1
            z, cov = se2.between(est[k - 1], guess), np.full((3, 3), np.inf)
        est[k] = se2.compose(est[k - 1], z)
        odo_only[k] = se2.compose(odo_only[k - 1], z)
        add_edge(k - 1, k, z, cov, False)

        if not cfg.loop_closure or k % cfg.loop_every:
            continue
        old = k - cfg.loop_min_separation
        if old <= 0:
            continue
        dist = np.hypot(*(est[:old, :2] - est[k, :2]).T)
        cand = np.flatnonzero(dist < cfg.loop_radius_m)
        cand = cand[np.argsort(dist[cand])][: cfg.loop_candidates]
        added = False
        for c in cand:
            loops_tried += 1
            target = local_map(int(c) + 2, int(c) - 2, int(c) + 3, est[c])
            guess_rel = se2.between(est[c], est[k])
            res = icp(pts[k], target, initial=guess_rel, config=loop_cfg)
            corr = se2.local(guess_rel, res.transform)
            if (res.converged and res.fitness >= cfg.loop_min_fitness and res.rmse_m <= cfg.loop_max_rmse_m
                    and np.hypot(corr[0], corr[1]) <= cfg.loop_max_correction_m):
                add_edge(int(c), k, res.transform, res.covariance, True)
                loops_ok += 1
                added = True
        if added:
            edges = _edges(ei, ej, ez, einfo, eloop)
            sol, _ = solve_pose_graph(est[: k + 1], edges, cfg.solver_iterations, cfg.cauchy_scale)
            est[: k + 1] = sol

    edges = _edges(ei, ej, ez, einfo, eloop)
    if cfg.loop_closure and loops_ok:
        est, _ = solve_pose_graph(est, edges, cfg.solver_iterations, cfg.cauchy_scale)
    poses = interpolate_poses(odom, kfa, est)
    if cfg.track_scans:
        owner = np.searchsorted(kfa, np.arange(s), side="right") - 1
        inside = (np.arange(s) != kfa[owner]) & (owner < len(kfa) - 1)  # scans after the last keyframe: odometry
        poses[inside] = se2.compose(est[owner[inside]], rel[inside])
    if cfg.refine_scans:
        owner = np.searchsorted(kfa, np.arange(s), side="right") - 1
        for k in range(len(kfa)):  # one local map per keyframe, one ICP per scan it owns
            members = np.flatnonzero((owner == k) & (np.arange(s) != kfa[k]))
            if len(members) == 0:
                continue
            target = local_map(min(k + 2, len(kfa) - 1), k - 2, k + 3, est[k])
            for mi in members.tolist():
                res = icp(_scan_points(rng_all[mi], ang, lim), target, initial=se2.between(est[k], poses[mi]),
                          config=cfg.icp)
                if res.converged and res.fitness > 0.5:
                    poses[mi] = se2.compose(est[k], res.transform)
    odo_poses = interpolate_poses(odom, kfa, odo_only)
    return LidarSlamResult(poses, kfa, est, odo_poses, edges, loops_ok, loops_tried, failures)


def _edges(ei: list[int], ej: list[int], ez: list[Array], einfo: list[Array], eloop: list[bool]) -> PoseGraphEdges:
    return PoseGraphEdges(np.asarray(ei, dtype=np.int64), np.asarray(ej, dtype=np.int64),
                          np.asarray(ez, dtype=np.float64).reshape(-1, 3),
                          np.asarray(einfo, dtype=np.float64).reshape(-1, 3, 3), np.asarray(eloop, dtype=bool))


def interpolate_poses(odom: Array, keyframes: IntArray, kf_poses: Array) -> Array:
    """Pose of every scan: its latest keyframe's estimate composed with the odometry increment since that keyframe.

    Shapes: odom (S,3), keyframes (K,) sorted scan indices starting at 0, kf_poses (K,3) -> (S,3).
    """
    owner = np.searchsorted(keyframes, np.arange(len(odom)), side="right") - 1
    return se2.compose(kf_poses[owner], se2.between(odom[keyframes[owner]], odom))
