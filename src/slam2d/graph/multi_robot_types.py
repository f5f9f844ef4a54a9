"""Configuration and result types of multi-robot graph SLAM (:mod:`slam2d.graph.multi_robot`), and the composed
odometry covariance it uses between pose nodes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam2d.association import AssociationConfig
from slam2d.frontend.place_recognition import PlaceRecognitionConfig
from slam2d.geometry import se2
from slam2d.graph.map_merge import MergeHypothesis
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig
from slam2d.multi_log import MultiRobotLog

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True, kw_only=True)
class MultiGraphConfig:
    """Multi-robot graph SLAM settings. Per-robot noise comes from each robot's log (:func:`config_from_log`)."""

    motion: tuple[MotionNoise, ...] = ()
    """odometry noise of each robot (in the order of the log's robots)."""
    sensor: tuple[SensorConfig, ...] = ()
    """landmark sensor of each robot."""
    sighting_range_std_m: float = 0.15
    """robot-robot sighting range noise (m) (from the log's fitted ``sighting_noise`` when present)."""
    sighting_bearing_std_rad: float = 0.02
    """robot-robot sighting bearing noise (rad)."""
    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(method="known"))
    """how landmark observations are matched (robot identities are always known from their barcodes)."""
    unknown_starts: bool = False
    """each robot starts in its own frame; frames are merged from common evidence (module docstring)."""
    node_every: int = 10
    """steps between pose nodes of a robot that measures nothing."""
    optimize_every: int = 100
    """re-optimise the joint graph every this many steps (MRCLAM's shared grid: ~0.055 s per step)."""
    iterations: int = 5
    """Levenberg-Marquardt iterations per online optimisation."""
    final_iterations: int = 50
    """iterations of the final optimisation (``finalize``)."""
    start_std_m: float = 0.01
    """known starts: standard deviation of each robot's anchor prior (m; the same number in rad for heading)."""
    confirm_after: int = 2
    """unknown association: a new landmark joins the graph after this many sightings (held aside until then)."""
    candidate_margin_m: float = 1.0
    """landmarks predicted within max_range_m + this of a robot are association candidates."""
    loop_closure: bool = True
    """each robot closes loops on its own keyframes by place recognition (:mod:`slam2d.graph.multi_robot_loops`)."""
    keyframe_every: int = 5
    """fewest steps between two keyframes of a robot (taken at steps where it measures landmarks)."""
    place: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    """place recognition and verification (the single-robot graph's defaults)."""
    loop_gate_probability: float = 0.999
    """a verified loop must agree with the estimate at this chi-square probability (3 dof)."""
    loop_robust_kernel: str = "cauchy"
    """robust kernel on loop-closure factors: none, huber, cauchy or dcs."""
    landmark_robust_kernel: str = "cauchy"
    """unknown association: robust kernel on landmark factors (none, huber, cauchy or dcs), its scale the association
    gate (sqrt of the chi-square(2) quantile at ``association.gate_probability``, in sigmas): a sighting given to the
    wrong landmark pulls less. Known ids: never."""
    merge_probability: float = 0.99
    """a merge hypothesis passes the chi-square test at this probability."""
    merge_min_pairs: int = 3
    """a merge needs at least this many consistent correspondences."""
    merge_min_spread_m: float = 1.0
    """... spread over at least this distance."""
    merge_ransac_iterations: int = 200
    """RANSAC hypotheses per merge attempt."""

    def __post_init__(self) -> None:
        for n in ("node_every", "optimize_every", "iterations", "final_iterations", "confirm_after", "keyframe_every",
                  "merge_min_pairs", "merge_ransac_iterations"):
            if getattr(self, n) < 1:
                raise ValueError(f"MultiGraphConfig.{n} must be >= 1 (got {getattr(self, n)})")
        for n in ("sighting_range_std_m", "sighting_bearing_std_rad", "start_std_m"):
            if not getattr(self, n) > 0:
                raise ValueError(f"MultiGraphConfig.{n} must be > 0 (got {getattr(self, n)})")
        if len(self.motion) != len(self.sensor):
            raise ValueError("MultiGraphConfig: one motion and one sensor model per robot")
        if not 0 < self.loop_gate_probability < 1:
            raise ValueError(f"MultiGraphConfig.loop_gate_probability must be in (0, 1) (got "
                             f"{self.loop_gate_probability})")
        for n in ("loop_robust_kernel", "landmark_robust_kernel"):
            if getattr(self, n) not in ("none", "huber", "cauchy", "dcs"):
                raise ValueError(f"MultiGraphConfig.{n} must be none, huber, cauchy or dcs (got {getattr(self, n)!r})")
        if not 0 < self.merge_probability < 1:
            raise ValueError(f"MultiGraphConfig.merge_probability must be in (0, 1) (got {self.merge_probability})")


def config_from_log(log: MultiRobotLog, **fields: object) -> MultiGraphConfig:
    """A :class:`MultiGraphConfig` with each robot's fitted motion and sensor noise and the fitted sighting noise
    from ``log``'s metadata; ``fields`` override the rest."""
    motion = tuple(MotionNoise(**{k: v for k, v in lg.metadata.get("motion", {}).items()
                                  if k in MotionNoise.__dataclass_fields__}) for lg in log.logs)
    sensor = tuple(SensorConfig(**{k: v for k, v in lg.metadata.get("sensor", {}).items()
                                   if k in SensorConfig.__dataclass_fields__}) for lg in log.logs)
    sn = log.metadata.get("sighting_noise", {})
    extra: dict[str, object] = {}
    if sn:
        extra = {"sighting_range_std_m": sn["range_std_m"], "sighting_bearing_std_rad": sn["bearing_std_rad"]}
    return MultiGraphConfig(motion=motion, sensor=sensor, **{**extra, **fields})  # type: ignore[arg-type]


@dataclass(frozen=True)
class MergeEvent:
    """A merge decision: group ``robots_b`` tested against group ``robots_a`` at ``step``; ``hypothesis`` holds
    T_a_b, the inliers and the chi-square verdict; ``landmark_pairs`` / ``sighting_pairs`` count the inliers by kind.
    """

    step: int
    robots_a: tuple[int, ...]
    robots_b: tuple[int, ...]
    hypothesis: MergeHypothesis
    landmark_pairs: int
    sighting_pairs: int


@dataclass(frozen=True)
class MultiEstimate:
    """The joint estimate. Shapes: poses (R,3) newest pose of each robot; trajectories: one (T+1,3) per robot (every
    step; between nodes composed from odometry); starts (R,3) each robot's first pose; landmarks (L,2) confirmed
    landmarks with ids (L,) (the source ids with known association) and the group (robot index) owning each;
    groups (R,) the group (lowest robot index of its frame) of each robot. Without ``unknown_starts`` (or once all
    are merged) every group is 0 and every pose is in one frame."""

    robots: tuple[int, ...]
    poses: Array
    trajectories: tuple[Array, ...]
    starts: Array
    landmarks: Array
    landmark_ids: IntArray
    landmark_groups: IntArray
    groups: IntArray
    merges: tuple[MergeEvent, ...]
    counters: dict[str, int]


def compose_with_covariance(u: Array, q: Array) -> tuple[Array, Array]:
    """``U = u_1 (+) ... (+) u_n`` and its covariance ``sum_k J_k Q_k J_k^T`` (independent increments; additive
    perturbations as everywhere in the library), vectorised: with ``P_k`` the chain up to k, ``dU/du_k`` is the
    rotation by P_{k-1}'s heading on x, y and ``[-(U - P_k)_y, (U - P_k)_x, 1]`` on the heading.
    Shapes: (n,3),(n,3,3) -> (3,),(3,3); n = 0 gives the identity with zero covariance."""
    p = se2.compose_chain(np.zeros(3), u)
    big_u = p[-1]
    c, s = np.cos(p[:-1, 2]), np.sin(p[:-1, 2])
    j = np.zeros((u.shape[0], 3, 3))
    j[:, 0, 0], j[:, 0, 1], j[:, 1, 0], j[:, 1, 1] = c, -s, s, c
    j[:, 0, 2] = -(big_u[1] - p[1:, 1])
    j[:, 1, 2] = big_u[0] - p[1:, 0]
    j[:, 2, 2] = 1.0
    return big_u, np.einsum("nij,njk,nlk->il", j, q, j)
