"""The one estimator contract every back end implements, and the typed snapshot it returns.

    est = SomeEstimator(SomeConfig(...))   # configuration only
    est.reset(initial_pose, rng=rng)       # fresh state
    for step in log:                       # odometry + observations (+ scan, gps) of one step; never ground truth
        est.step(step)
        snap = est.estimate()              # immutable, typed snapshot
    est.finalize()                         # once, after the last step (smoothers optimise to convergence)

History is the runner's job (``slam2d.lab.runner``): an estimator keeps only what its next step needs, so its
snapshot carries the *current* belief plus what happened in the last step (its association, the loops it
accepted or rejected). Optional abilities are small protocols (``SupportsLoopClosure``, ``SupportsGraphView``,
``SupportsSaveMap``) tested with ``isinstance``; ``require(est, Ability)`` names the estimator and the ability when
one is missing. ``EstimatorLifecycle`` gives every back end the same order checks (``EstimatorStateError``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from slam2d.log import Step

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _no_points() -> Array:
    return np.zeros((0, 2))


def _no_ids() -> IntArray:
    return np.zeros(0, dtype=np.int64)


class EstimatorStateError(RuntimeError):
    """An estimator was used out of order: ``estimate()``/``step()`` before ``reset()``, ``step()`` after
    ``finalize()``."""


class CapabilityError(TypeError):
    """An estimator lacks an ability a caller asked for (e.g. closing a loop on demand)."""


@dataclass(frozen=True)
class LoopEvent:
    """One loop-closure decision: pose indices ``a`` < ``b``, the measured ``T_a_b`` (3,) and whether it entered
    the graph."""

    a: int
    b: int
    accepted: bool
    T_a_b: Array


@dataclass(frozen=True)
class ParticleView:
    """A particle filter's cloud after the step: poses (M,3), normalised weights (M,), the effective sample size
    before resampling, and whether the step resampled."""

    poses: Array
    weights: Array
    n_eff: float
    resampled: bool


@dataclass(frozen=True)
class GraphView:
    """Nodes and typed edges of a factor graph, for drawing: pose/point positions with their keys, and per factor
    kind the key pairs (E,2) of its edges (a unary factor's second key repeats the first)."""

    poses: Array
    pose_keys: IntArray
    points: Array
    point_keys: IntArray
    edges: dict[str, IntArray]


@dataclass(frozen=True)
class Diagnostics:
    """Named counters a back end reports (cumulative since ``reset``); zero where they do not apply."""

    dropped_observations: int = 0
    covariance_repairs: int = 0
    landmarks_removed: int = 0
    tentative_dropped: int = 0
    weight_resets: int = 0
    range_outliers: int = 0
    optimizations: int = 0
    loops_accepted: int = 0
    loops_rejected: int = 0


@dataclass(frozen=True)
class Estimate:
    """A snapshot of an estimator's belief after a step.

    Shapes: pose (3,), pose_cov (3,3) or None, landmarks (L,2) confirmed landmarks, landmark_covs (L,2,2) or None,
    landmark_ids (L,) int (the estimator's own ids; with ``known`` association they equal the source's ids).
    Optional views are None when a back end has nothing to say:

    - ``trajectory`` (T+1,3): every pose so far, when the back end re-estimates past poses (smoothers);
    - ``association`` (K,): the landmark id, ``NEW`` or ``CLUTTER`` given to each observation of the last step;
    - ``tentative_landmarks`` (K,2) / ``tentative_ids`` (K,): landmarks seen but not yet confirmed;
    - ``new_loops``: the loop-closure decisions taken in the last step (the runner collects them);
    - ``particles``, ``graph``: a particle cloud, or the factor graph's nodes and edges;
    - ``full_cov`` (D,D): the whole state covariance, when asked for (EKF ``snapshot_full_cov``).
    """

    pose: Array
    pose_cov: Array | None = None
    landmarks: Array = field(default_factory=_no_points)
    landmark_covs: Array | None = None
    landmark_ids: IntArray = field(default_factory=_no_ids)
    state_dim: int = 3
    trajectory: Array | None = None
    association: IntArray | None = None
    tentative_landmarks: Array = field(default_factory=_no_points)
    tentative_ids: IntArray = field(default_factory=_no_ids)
    new_loops: tuple[LoopEvent, ...] = ()
    particles: ParticleView | None = None
    graph: GraphView | None = None
    full_cov: Array | None = None
    diagnostics: Diagnostics = field(default_factory=Diagnostics)


@runtime_checkable
class Estimator(Protocol):
    """What the runner, the lab and the web page need from a back end."""

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        """Start afresh at ``initial_pose`` (3,), using ``rng`` for any randomness."""

    def step(self, step: Step) -> None:
        """Consume one step's odometry and measurements."""

    def estimate(self) -> Estimate:
        """The current belief as an immutable snapshot."""

    def finalize(self) -> None:
        """Called once after the last step; a filter does nothing, a smoother optimises to convergence."""


@runtime_checkable
class SupportsLoopClosure(Protocol):
    """Can try to close a loop on demand from the newest pose's observations (the lab's "close loop now")."""

    def close_loop_now(self, z: Array) -> bool: ...


@runtime_checkable
class SupportsGraphView(Protocol):
    """Exposes its factor graph for drawing."""

    def graph_view(self) -> GraphView: ...


@runtime_checkable
class SupportsSaveMap(Protocol):
    """Can write its map to a store and start from one (saved maps)."""

    def save_map(self, path: str) -> None: ...


A = TypeVar("A")


def require(estimator: object, ability: type[A]) -> A:
    """``estimator`` as ``ability`` or a ``CapabilityError`` naming both (the caller's check, in one place)."""
    if not isinstance(estimator, ability):
        raise CapabilityError(f"estimator {type(estimator).__name__} does not support {ability.__name__}")
    return estimator


class EstimatorLifecycle:
    """The order rules every estimator shares: reset first, no steps after finalize.

    Back ends call ``_lifecycle_reset()`` in ``reset``, ``_check_step()`` at the top of ``step``,
    ``_check_ready()`` in ``estimate`` and ``_lifecycle_finalize()`` in ``finalize``.
    """

    _ready: bool = False
    _finalized: bool = False

    def _lifecycle_reset(self) -> None:
        self._ready = True
        self._finalized = False

    def _check_ready(self) -> None:
        if not self._ready:
            raise EstimatorStateError(f"{type(self).__name__}: call reset(initial_pose, rng=...) first")

    def _check_step(self) -> None:
        self._check_ready()
        if self._finalized:
            raise EstimatorStateError(f"{type(self).__name__}: step() after finalize(); call reset() to start again")

    def _lifecycle_finalize(self) -> bool:
        """Mark finalized; True the first time (so a smoother optimises only once)."""
        self._check_ready()
        first = not self._finalized
        self._finalized = True
        return first
