"""Settings of online graph SLAM (:mod:`slam2d.graph.online`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam2d.association import AssociationConfig
from slam2d.association.tracks import TrackConfig
from slam2d.config import check_nonnegative, check_positive
from slam2d.frontend.place_recognition import PlaceRecognitionConfig
from slam2d.models.motion import MotionNoise
from slam2d.models.sensors import SensorConfig


@dataclass(frozen=True, slots=True, kw_only=True)
class GraphSLAMConfig:
    """Online graph SLAM settings."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    """odometry noise (filled from the log's metadata)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """range-bearing sensor noise and range (filled from the log's metadata)."""
    association: AssociationConfig = field(default_factory=lambda: AssociationConfig(method="auto"))
    """how observations are matched to landmarks. Default ``auto``: the source's ids when the data carry them, else
    ``association.AUTO_WITHOUT_IDS`` (:func:`slam2d.association.resolve_method`)."""
    optimize_every: int = 10
    """re-optimise the whole graph every this many steps (and after every accepted loop closure)."""
    iterations: int = 5
    """Levenberg-Marquardt iterations per online optimisation (warm-started from the current estimate)."""
    final_iterations: int = 50
    """iterations of the optimisation run when the estimate is read after the last step (``finalize``)."""
    loop_closure: bool = True
    """detect loops by place recognition; when off, landmarks unseen for ``revisit_gap_steps`` are forgotten."""
    revisit_gap_steps: int = 60
    """with loop closure off: a landmark re-seen after this many steps counts as a new one."""
    keyframe_every: int = 5
    """steps between keyframes used for place recognition."""
    place: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    """place recognition and verification."""
    loop_gate_probability: float = 0.999
    """a verified loop must agree with the current estimate at this chi-square probability (3 dof)."""
    loop_robust_kernel: str = "cauchy"
    """robust kernel on loop-closure factors: none, huber, cauchy or dcs."""
    odometry_info_scale: float = 1.0
    """multiply odometry information (> 1: overconfident odometry, the "2 m offset" puzzle)."""
    loop_info_scale: float = 1.0
    """multiply loop-closure information (< 1: a weak loop constraint)."""
    confirm_after: int = 2
    """unknown association: a new landmark is tentative (its sightings held aside, nothing in the graph) until it has
    been associated this many times, counting its first sighting (1: every NEW observation is a landmark at once)."""
    tentative_max_misses: int = 3
    """a tentative landmark predicted well inside the sensor's view this many steps without a match is discarded with
    its sightings (0: never). Divided by the sensor's ``detection_prob``, as in EKF-SLAM."""
    view_margin_m: float = 0.5
    """"well inside the view" means predicted range <= max_range_m - view_margin_m (and inside the field of view)."""
    dynamic_test: bool = False
    """the tracks' persistence rule: a tentative landmark whose sightings drift (a moving object) is discarded."""
    candidate_margin_m: float = 3.0
    """landmarks predicted within max_range_m + this (m) of the newest pose are association candidates."""
    window: int = 0
    """0: every optimisation is over the whole graph. N > 0: bounded work per step -- the periodic optimisations
    solve only the newest N poses and the landmarks they saw, the rest held fixed (:mod:`slam2d.graph.
    sliding_window`); the whole graph is optimised after an accepted loop closure (at most once per ``full_every``
    steps), on ``close_loop_now`` and in ``finalize`` (so the final estimate is the same optimum). Known association
    only: with unknown association every optimisation stays whole-graph (its gates need the joint belief)."""
    window_iterations: int = 2
    """with ``window`` > 0: Levenberg-Marquardt iterations per window solve (warm-started; solves come often)."""
    window_sightings: int = 5
    """with ``window`` > 0: sightings from before the window kept per landmark in a window solve (the newest)."""
    full_every: int = 200
    """with ``window`` > 0: fewest steps between two whole-graph optimisations triggered by loop closures."""
    belief_margin_m: float = 10.0
    """the joint [pose, landmarks] block used for association holds the landmarks within max_range_m +
    candidate_margin_m + this (m) of the newest pose at the last optimisation; when the robot has moved so far that a
    candidate is outside it, the graph is optimised early (which refreshes the block)."""

    def __post_init__(self) -> None:
        for n in ("optimize_every", "iterations", "final_iterations", "revisit_gap_steps", "keyframe_every",
                  "full_every", "window_sightings", "window_iterations"):
            if getattr(self, n) < 1:
                raise ValueError(f"GraphSLAMConfig.{n} must be >= 1 (got {getattr(self, n)})")
        try:
            self.tracks()
        except ValueError as e:
            raise ValueError(f"GraphSLAMConfig.{e}") from None
        check_positive(self, "odometry_info_scale", "loop_info_scale")
        check_nonnegative(self, "view_margin_m", "candidate_margin_m", "belief_margin_m", "window")
        if not 0 < self.loop_gate_probability < 1:
            raise ValueError(f"GraphSLAMConfig.loop_gate_probability must be in (0, 1) (got "
                             f"{self.loop_gate_probability})")
        if self.loop_robust_kernel not in ("none", "huber", "cauchy", "dcs"):
            raise ValueError(f"GraphSLAMConfig.loop_robust_kernel must be none, huber, cauchy or dcs "
                             f"(got {self.loop_robust_kernel!r})")

    def tracks(self) -> TrackConfig:
        """The track rules of the tentative landmarks (a confirmed one leaves the tracks for the graph)."""
        return TrackConfig(confirm_after=self.confirm_after, tentative_max_misses=self.tentative_max_misses,
                           confirmed_max_misses=0, view_margin_m=self.view_margin_m,
                           misses_per_sighting=self.sensor.misses_per_sighting, dynamic_test=self.dynamic_test)
