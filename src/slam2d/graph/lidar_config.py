"""Settings of the lidar back end (:mod:`slam2d.graph.lidar`): :class:`LidarSLAMConfig` and its lifelong variant."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam2d.config import check_nonnegative, check_positive
from slam2d.frontend.correlative import CorrelativeConfig
from slam2d.frontend.icp import ICPConfig
from slam2d.graph.incremental import IncrementalConfig
from slam2d.graph.lidar_markers import MarkerSettings
from slam2d.maps.layers import LayersConfig

__all__ = ["LidarSLAMConfig", "LifelongLidarConfig"]


def _tracking_icp() -> ICPConfig:
    return ICPConfig(max_correspondence_m=0.5, median_gate=4.0, tolerance=1e-4)


def _loop_icp() -> ICPConfig:
    return ICPConfig(max_correspondence_m=0.3, trim_fraction=0.8, max_iterations=50, tolerance=1e-4)


def _track_correlative() -> CorrelativeConfig:
    return CorrelativeConfig(window_xy_m=0.5, window_theta_rad=0.5)


@dataclass(frozen=True, slots=True, kw_only=True)
class LidarSLAMConfig:
    """Settings of the lidar SLAM estimator. The figures in these docstrings were measured with tracking's earlier
    fixed trim, on the VM of the time, unless they say otherwise (``docs/lidar_history.md``)."""

    keyframe_distance_m: float = 0.3
    """tracked translation since the last keyframe that makes a new keyframe (m)."""
    keyframe_angle_rad: float = 0.25
    """tracked rotation since the last keyframe that makes a new keyframe (rad)."""
    local_map_keyframes: int = 6
    """newest keyframes whose points form the tracking target. With the wide loop retry (``loop_retry_window_m``),
    4 gives aces 0.0365 m (6: 0.038-0.039, measured with earlier versions of the retry); but on a 150-step
    warehouse drive with floor markers (tests/unit/test_lidar_markers.py) 4 drifts 0.65 m along an aisle, 6 0.26 m
    (5: 0.78 m), so 6 stays: not changed on the strength of aces alone."""
    max_range_m: float = 25.0
    """beams longer than this are not matched (far points are sparse and noisy) (m)."""
    min_range_m: float = 0.05
    """beams shorter than this are not matched (the robot itself) (m)."""
    icp: ICPConfig = field(default_factory=_tracking_icp)
    """tracking scan matcher. It keeps the matches within 4 times their median distance (``median_gate``), not a
    fixed 85 % of them: a fixed trim drops the same share of a clean scan, whose matches all hold, as of one with a
    moved forklift. Chosen on intel and the simulated room and aisle (gate 3 / 4: intel 0.0150 / 0.0142 m on one CPU,
    0.0153 / 0.0150 m on another, the room 0.014 / 0.013 m, the aisle 0.240 / 0.203 m), then reported on aces, fr079
    and mit-csail (README, "Lidar SLAM")."""
    min_fitness: float = 0.5
    """a tracking match needs this fraction of the scan's points matched, else the odometry guess is kept."""
    track_rematch_rmse_m: float = 0.05
    """a tracking match whose residual RMS is above this (or that matched too few points, or failed) is redone from
    a correlative search (:mod:`slam2d.graph.lidar_tracking`); 0.05 m is above the 99.9th percentile of the
    tracking residual on ACES and intel (0.03 m), where the wrong minima of an in-place spin had 0.14-0.16 m (m)."""
    track_correlative: CorrelativeConfig = field(default_factory=_track_correlative)
    """the window of that re-match: it must cover the guess error of a poor odometry step."""
    track_rematch_points: int = 180
    """points of the scan (evenly spread) in that correlative search (0: no re-match)."""
    track_prior_xy: float = 0.0
    """weight of the odometry guess in tracking's first ICP fit, per metre of x and y: a row ``w (T - guess)`` beside
    one row per match whose point-to-line residual weighs 1 per metre (0 with ``track_prior_theta`` 0: off). A
    corridor's axis, which the walls leave loose, then follows odometry. Off by default: at 1.0 / 2.0 the warehouse's
    mean ATE over 15 seeds falls from 1.40 to 1.00 m and intel, fr079 and aces improve, but mit-csail, whose
    odometry stalls and then jumps, goes from 0.0284 to 0.144 m (README, "Lidar SLAM")."""
    track_prior_theta: float = 0.0
    """the same for heading, per radian."""
    min_sigma_xy_m: float = 0.02
    """floor on the standard deviation of a keyframe edge in x and y (ICP Hessians are over-confident) (m)."""
    min_sigma_theta_rad: float = 0.005
    """floor on the standard deviation of a keyframe edge in heading (rad)."""
    loop_closure: bool = True
    """search for loop closures (False: scan-matching odometry only)."""
    loop_every: int = 2
    """search loops every this many keyframes."""
    loop_radius_m: float = 4.0
    """old keyframes whose estimate lies within this distance of the new one are candidates (m)."""
    loop_min_separation: int = 30
    """keyframes closer than this in sequence are not candidates."""
    loop_candidates: int = 4
    """at most this many candidates (the nearest) are verified per search."""
    loop_map_keyframes: int = 2
    """a candidate's local map: its keyframe and this many on each side."""
    loop_static_radius_m: float = 0.1
    """a loop in a self-similar place is verified again on static structure only
    (:func:`slam2d.graph.lidar_loops.confirmed_mask`): the points of the scan and of the old local map that no other
    keyframe contradicts -- one that looked within ``loop_static_seen_m`` must have seen a surface with the same
    normal within this distance (m; 0: no re-verification). A moving object is seen at a different place by each
    keyframe and drops out: the warehouse's false loops all slid along the middle aisle with a forklift."""
    loop_static_ambiguity: float = 0.8
    """... where self-similar means a correlative ambiguity above this (0: every loop is re-verified; the
    warehouse's false loops had 0.81-0.88, its right ones 0.65-0.83). Re-verifying every loop cost intel 0.023 ->
    0.035 m (measured before queued verification and the loop kernel)."""
    loop_static_normal_rad: float = 1.0
    """... and whose normal is within this angle of that point's: the end face of an object that slid along its
    own side is not confirmed by the side (rad)."""
    loop_static_seen_m: float = 0.5
    """... among the points near which another keyframe saw something within this distance (m): a surface only
    one keyframe saw is kept (see :func:`slam2d.graph.lidar_loops.confirmed_mask`)."""
    correlative: CorrelativeConfig = field(default_factory=CorrelativeConfig)
    """the correlative search of a loop candidate."""
    loop_min_score: float = 0.5
    """a loop's correlative score (mean likelihood of its points) must reach this."""
    loop_max_ambiguity: float = 0.9
    """a loop is rejected when a competing alignment outside the ambiguity radius scores this fraction of the
    best (identical aisles, a corridor's axis)."""
    loop_retry_window_m: float = 2.5
    """a candidate whose correlative search matched nothing (score gate), its best try lying at the window's edge
    (the scores still rising there), is searched again over +- this window, counting only rivals that are peaks of
    their own (:func:`slam2d.graph.lidar_loops.wide_correlative`), as a candidate of its own (due ``loop_queue``
    scans after the first search's decision, in ``loop_retry_stages`` stages); every later gate and the pair
    confirmation still apply, and such a loop is always re-verified on static structure (m; 0: off).
    ACES's return to its start (guess 1.7 m off): closed at 2.5 m, not reliably at 2.0 (a best alignment near the
    window's edge is rejected); aces 0.0475 -> 0.0384 m, intel, fr079, mit-csail and the simulated room and
    warehouse seeds unchanged (``benchmarks/lidar_backend.py``). Retrying ambiguity failures too let a warehouse
    seed accept loops slid 2.3 m along an aisle; retrying every score failure, not only those at the edge,
    searched mit-csail 364 times instead of 202 (``LidarSLAM.loops_retried``) for the same loops. It was off by
    default while verification ran one stage per scan: candidates still unverified at their due scan are finished
    at once (``loop_queue``), and the retries crowded into those scans (mit-csail CPU p99 65 ms); stages that fill
    each scan's ``loop_budget_ms`` left 9 such scans in 1900 (p99 32 ms). Never finishing a candidate at once
    failed both ways: letting it enter late (``loop_queue``) saturated verification (128 waiting on fr079 and
    mit-csail, intel's real-time factor down by 28 %); giving up an overdue retry lost aces's return (0.0462 m)."""
    loop_retry_after_m: float = 40.0
    """the wide retry is only for the candidates of a keyframe reached after this much driving since the newest loop
    entered the graph (along the keyframe edges): sooner, the drift cannot have outgrown the first window (1 m
    at 2.5 % of the distance driven). Chosen on aces and intel: of 640 retries on intel none passed and 4 came
    after 40 m; aces's return comes after 97 m (m; 0: every candidate at the window's edge)."""
    loop_retry_step_cells: int = 4
    """coarse translation step of that wider search, in ``correlative.resolution_m`` cells."""
    loop_retry_stride: int = 3
    """that wider search matches every this many points of the scan (its ICP refinement all of them)."""
    loop_retry_stages: int = 6
    """that wider search runs as this many verification stages (its coarse scores split by rotation), so that it
    costs a scan no more than the first search does (6 with ``loop_search_stages``, see there)."""
    loop_wide_window_m: float = 0.0
    """a loop that passed every gate is searched again over +- this window (coarse only) and rejected when another
    alignment there scores ``loop_wide_max_ambiguity`` of the best: identical aisles farther apart than the
    verification window (m; 0: off). Off by default: measured at 4 m, threshold 0.9, it removed the false warehouse
    loops (seeds 2, 3) but also most ACES corridor loops (0.048 -> 0.337 m); at 0.97 ACES 0.052 m and seed 2 still
    had 2 false loops."""
    loop_wide_max_ambiguity: float = 0.97
    """the wide search's ambiguity threshold (its coarse scores are blurrier than the verification's)."""
    loop_wide_step_cells: int = 6
    """coarse translation step of that wide search, in ``correlative.resolution_m`` cells."""
    loop_icp: ICPConfig = field(default_factory=_loop_icp)
    """refinement of a loop's correlative match."""
    loop_min_fitness: float = 0.6
    """a loop's ICP refinement must match this fraction of the scan's points (at most ``loop_icp.trim_fraction``)."""
    loop_max_rmse_m: float = 0.08
    """a loop's point-to-line residual RMS must be below this (m)."""
    loop_max_sigma_m: float = 0.05
    """a loop's ICP covariance must constrain every direction: its largest translational standard deviation must
    be below this (m). A corridor or aisle leaves the axis unconstrained, and a loop there would be a guess."""
    loop_chi2: float = 16.27
    """chi-square gate (3 dof, p = 0.001) on the ICP covariance between the correlative and the ICP result."""
    loop_confirmations: int = 1
    """a verified loop enters the graph only once another verified loop (from the same or a later keyframe within
    ``loop_pair_keyframes``) agrees with it (0: each verified loop enters at once)."""
    loop_pair_keyframes: int = 25
    """how long (in keyframes) a verified loop waits for a partner."""
    loop_pair_xy_m: float = 0.15
    """two loops agree when their implied poses of the new keyframe differ by less than this (m) ..."""
    loop_pair_theta_rad: float = 0.05
    """... and this (rad)."""
    loop_full_iterations: int = 5
    """Gauss-Newton iterations on the whole keyframe graph after a loop entered, one per scan over the next scans
    (0: the incremental graph's local solve only)."""
    loop_verify_per_scan: int = 1
    """verification stages every scan runs: candidates are queued when a keyframe is made and verified over the
    following scans, a stage at a time, which bounds the work of every scan. A first search is a stage for its local
    map's likelihood grid, ``loop_search_stages`` stages of correlative scores, then one for the ICP target's normals
    and one for ICP and the later gates; a self-similar place's static re-check is two mask stages, then its own
    search (:meth:`slam2d.graph.lidar.LidarSLAM._check_stages`)."""
    loop_budget_ms: float = 27.0
    """after its ``loop_verify_per_scan`` stages, a scan runs another while its own CPU time (the thread's, from the
    start of ``step``, including the graph update of the loops whose decisions are due in it, which enter before its
    stages) plus the predicted cost of that stage stays under this (ms; 0: never more). The prediction is
    the longest of the last 4 stages of the same kind (grid, scores, normals, icp, mask): a 1 ms slice of scores
    still fits where a 10 ms mask would not. Results do not depend on it (decisions enter the graph at fixed scans,
    a candidate not verified by then is finished at once); latency does: stages fill the scans whose tracking left
    time, so fewer candidates are left to be finished at once at their due scan, the spikes. Before the prediction
    a stage began while the scan was under 20 ms and ran past it by its own length (up to 16 ms on mit-csail):
    25 ms gave p99 34-35 ms, 20 gave 30-32 ms, and mit-csail still had scans of 80-110 ms. With it, runs alternated
    with the old rule at 20 (``benchmarks/lidar_backend.py``, CPU p99 / max per scan, ms): mit-csail 30.6 / 38 and
    29.2 / 37 at 27 against 32.6 / 101 and 26.8 / 40; fr079 32.5 / 125 and 32.5 / 138 against 33.6 / 147 and
    31.1 / 139 (its spikes are bursts of candidates beyond what any budget under 33 ms verifies in time). 24 left
    mit-csail's spikes (80-108 ms), 30 raised its p99 (31-32 ms). Later, on a VM a quarter slower, mit-csail at 27
    against the old rule at 20: p99 34.4 / 32.7 / 35.7 against 41.9 / 41.1 / 57.5 ms, but spikes of 105-117 ms
    against 84-146 ms on both: there the bursts outgrow the budget too. An earlier prediction from the longest of the
    last 16 stages of any kind, with no stage forced, ran too few: more candidates were finished at once (p99 71
    ms)."""
    loop_search_stages: int = 6
    """a first search's correlative scores run as this many verification stages (split by rotation), after the
    stage that builds the likelihood grid. Results do not depend on it, latency does (see ``loop_budget_ms``). At 3
    (4-6 ms a stage on mit-csail on 2026-12-02's VM) mit-csail's CPU p99 was 29 ms that day, 44-60 ms on the slower
    VM of 2026-12-03; 6 here and in ``loop_retry_stages`` gave 31-37 ms there, fr079 unchanged (34-37 ms against
    34-35 ms, runs alternated; ``benchmarks/lidar_backend.py``)."""
    loop_queue: int = 16
    """the delay, in scans, from queueing a candidate to its decision entering the graph: fixed, so that results
    do not depend on when within that delay the candidate was verified. Also at most this many candidates are in
    flight (queued in the last ``loop_queue`` scans); more are refused unverified (counted), a rule that does not
    depend on how fast they are verified either. (Letting a candidate unverified at its due scan enter late
    instead, with at most one stage per scan, lost mit-csail: 0.0309 -> 0.277 m with the wide retry off.)"""
    graph: IncrementalConfig = field(default_factory=lambda: IncrementalConfig(
        window=30, loop_neighbourhood=3, iterations=3, full_every=200, loop_kernel="cauchy"))
    """incremental pose-graph settings (in keyframes). Loop edges carry a Cauchy kernel (3 sigma): with plain least
    squares the relation error moved with harmless changes (intel 0.023 -> 0.054 m for ``loop_candidates`` 4 -> 5:
    a few verified-but-slightly-wrong loops pulled the map), with the kernel it stays at 0.015 m for both
    (chosen on intel; fr079, aces and mit-csail are reported with it)."""
    markers: MarkerSettings = field(default_factory=MarkerSettings)
    """floor markers (used when steps carry readings): marker nodes and re-sighting solves."""
    map_resolution_m: float = 0.05
    """cell size of the occupancy map (m)."""
    layers: LayersConfig | None = None
    """lifelong mode (None: off): track against the static layer of :mod:`slam2d.maps.layers` instead of the
    newest keyframes, keep dynamic points out of matching and out of that layer, and add a keyframe only where
    none lies within ``coverage_m`` (memory follows the mapped area, not the time). Needs ``loop_closure=False``."""
    coverage_m: float = 2.0
    """lifelong mode: a scan becomes a keyframe only when no keyframe lies within this distance (m)."""
    match_points: int = 200
    """lifelong mode: at most this many points of a scan (evenly spread over its beams) are matched."""
    min_inliers: int = 40
    """lifelong mode: a match needs this many points within ``layers.inlier_m`` of the static layer, else the
    odometry guess is kept (counted as a tracking failure)."""
    surveyed_markers: tuple[tuple[int, float, float], ...] = ()
    """lifelong mode: floor markers whose map-frame positions were surveyed, (id, x, y); each reading of one
    corrects the matched pose (:mod:`slam2d.graph.lidar_lifelong`). Empty: markers are not used in this mode."""
    map_unsurveyed_markers: bool = False
    """lifelong mode: map markers missing from the survey on their first sighting (the mean of that sighting's
    readings) and let later readings correct the pose; such a marker carries the drift of the pass that mapped it."""
    survey_sigma_m: float = 0.01
    """lifelong mode: standard deviation of a surveyed marker position per axis (m)."""
    marker_match_sigma_xy_m: float = 0.05
    """lifelong mode: floor on the standard deviation of the static-layer match, in x and y, when a marker reading
    corrects it (the match's own covariance ignores the layer's shared error) (m)."""
    marker_match_sigma_theta_rad: float = 0.005
    """lifelong mode: the same floor in heading (rad)."""

    def __post_init__(self) -> None:
        check_positive(self, "keyframe_distance_m", "keyframe_angle_rad", "max_range_m", "min_sigma_xy_m",
                       "min_sigma_theta_rad", "loop_radius_m", "loop_min_fitness", "loop_max_rmse_m", "loop_chi2",
                       "loop_max_sigma_m", "map_resolution_m", "loop_pair_xy_m", "loop_pair_theta_rad",
                       "loop_static_normal_rad", "loop_static_seen_m", "min_fitness", "loop_min_score",
                       "loop_max_ambiguity", "loop_wide_max_ambiguity")
        check_nonnegative(self, "min_range_m")
        if not self.min_range_m < self.max_range_m:  # else no beam is ever matched: odometry under lidar's name
            raise ValueError(f"LidarSLAMConfig.min_range_m must be < max_range_m (got {self.min_range_m} >= "
                             f"{self.max_range_m})")
        if self.loop_confirmations not in (0, 1):
            raise ValueError(f"LidarSLAMConfig.loop_confirmations must be 0 or 1 (got {self.loop_confirmations})")
        for n in ("local_map_keyframes", "loop_every", "loop_candidates", "loop_min_separation",
                  "loop_pair_keyframes", "loop_verify_per_scan", "loop_queue", "loop_retry_step_cells",
                  "loop_retry_stride", "loop_retry_stages", "loop_search_stages"):
            if getattr(self, n) < 1:
                raise ValueError(f"LidarSLAMConfig.{n} must be >= 1 (got {getattr(self, n)})")
        if self.layers is not None and self.loop_closure:
            raise ValueError("LidarSLAMConfig.layers needs loop_closure=False: a loop would move keyframes under a "
                             "static layer that was built at the tracked poses")
        check_positive(self, "coverage_m", "match_points", "min_inliers", "survey_sigma_m", "marker_match_sigma_xy_m",
                       "marker_match_sigma_theta_rad")
        if (self.surveyed_markers or self.map_unsurveyed_markers) and self.layers is None:
            raise ValueError("LidarSLAMConfig.surveyed_markers and map_unsurveyed_markers are used by the lifelong "
                             "mode only (set layers)")
        check_nonnegative(self, "loop_static_radius_m", "track_rematch_points", "loop_retry_window_m", "loop_budget_ms",
                          "loop_retry_after_m", "track_prior_xy", "track_prior_theta")
        if (self.track_prior_xy or self.track_prior_theta) and self.icp.method != "point-to-line":
            raise ValueError("LidarSLAMConfig.track_prior_xy / track_prior_theta need icp.method='point-to-line'")
        check_positive(self, "track_rematch_rmse_m")
        if self.loop_map_keyframes < 0:
            raise ValueError(f"LidarSLAMConfig.loop_map_keyframes must be >= 0 (got {self.loop_map_keyframes})")


@dataclass(frozen=True, slots=True, kw_only=True)
class LifelongLidarConfig(LidarSLAMConfig):
    """:class:`LidarSLAMConfig` with the lifelong mode on (``--estimator lidar-lifelong``)."""

    layers: LayersConfig | None = field(default_factory=LayersConfig)
    loop_closure: bool = False
