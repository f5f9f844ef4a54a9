"""The one interface every data-association method implements, and the dispatcher back ends call.

A back end predicts a measurement for each candidate landmark (mean ``z_pred`` and innovation covariance
``S = H P H^T + R``); the association decides, for each observation, which candidate it is (by the candidate's id),
or that it starts a new landmark (``NEW``), or that it is clutter to ignore (``CLUTTER``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from slam2d.config import check_nonnegative, check_positive, check_probability
from slam2d.log import Observations

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: assignment value: the observation starts a tentative landmark
NEW = -1
#: assignment value: the observation is ignored (clutter, a moving object, or too ambiguous to use)
CLUTTER = -2

#: the concrete methods (``AssociationConfig.method`` also accepts ``auto``, which back ends resolve to one of these)
METHODS = ("known", "nn", "mahalanobis", "jcbb", "ransac")

#: what ``auto`` becomes on data without landmark ids (measured on MRCLAM robots 1-3 with the ids withheld)
AUTO_WITHOUT_IDS: Literal["mahalanobis"] = "mahalanobis"


@dataclass(frozen=True, slots=True, kw_only=True)
class AssociationConfig:
    """How observations are matched to landmarks."""

    method: Literal["auto", "known", "nn", "mahalanobis", "jcbb", "ransac"] = "mahalanobis"
    """auto (``known`` when the data carry landmark ids, else ``AUTO_WITHOUT_IDS``; see :func:`resolve_method`),
    known (oracle ids), nn (Euclidean in measurement space), mahalanobis (individual compatibility with
    mutual exclusion), jcbb (joint compatibility branch and bound), ransac (consensus over minimal sets)."""
    gate_probability: float = 0.99
    """a correct match passes the chi-square gate with this probability."""
    new_landmark_probability: float = 0.9999
    """an observation outside this (wider) gate of every candidate starts a new landmark; between the two gates it
    is treated as ambiguous clutter, so that a slightly-off sighting never duplicates a landmark."""
    nn_max_distance: float = 1.0
    """nn only: largest Euclidean distance in measurement space ([m, rad] stacked) accepted as a match."""
    descriptor_max_distance: float = 0.0
    """when > 0 and descriptors exist on both sides, pairs farther apart than this (Euclidean) are not matched."""
    known_outlier_gate: bool = True
    """known only: a source id whose measurement falls outside the wide gate (``new_landmark_probability``) of
    that landmark is treated as clutter -- real sources misread ids (MRCLAM barcodes)."""
    ransac_iterations: int = 100
    """ransac only: number of minimal-set hypotheses."""
    ransac_min_pairs: int = 2
    """ransac only: pairs per minimal set (2 pairs = 4 scalar measurements fix the 3-dof pose correction)."""
    jcbb_max_nodes: int = 1_000_000
    """jcbb only: stop the search after visiting this many nodes and return the best hypothesis found so far
    (``AssociationResult.truncated`` is then True, so the caller knows the answer may not be optimal)."""
    jcbb_time_budget_s: float | None = None
    """jcbb only: stop the search after this much wall time (s) and return the best hypothesis found so far
    (``truncated`` True); None: no time limit, the answer depends only on the inputs."""

    def __post_init__(self) -> None:
        from slam2d.config import _coerce  # local: avoid a cycle at import time

        _coerce(self.method, Literal["auto", "known", "nn", "mahalanobis", "jcbb", "ransac"],
                "AssociationConfig.method")
        check_probability(self, "gate_probability", "new_landmark_probability", open_low=True)
        for name in ("gate_probability", "new_landmark_probability"):
            if getattr(self, name) >= 1.0:
                raise ValueError(f"AssociationConfig.{name} must be < 1 (got {getattr(self, name)})")
        if self.new_landmark_probability < self.gate_probability:
            raise ValueError("AssociationConfig.new_landmark_probability must be >= gate_probability")
        check_positive(self, "nn_max_distance")
        check_nonnegative(self, "descriptor_max_distance")
        if self.ransac_iterations < 1:
            raise ValueError(f"AssociationConfig.ransac_iterations must be >= 1 (got {self.ransac_iterations})")
        if self.ransac_min_pairs < 1:
            raise ValueError(f"AssociationConfig.ransac_min_pairs must be >= 1 (got {self.ransac_min_pairs})")
        if self.jcbb_max_nodes < 1:
            raise ValueError(f"AssociationConfig.jcbb_max_nodes must be >= 1 (got {self.jcbb_max_nodes})")
        if self.jcbb_time_budget_s is not None and not self.jcbb_time_budget_s >= 0.0:
            raise ValueError("AssociationConfig.jcbb_time_budget_s must be >= 0 or None "
                             f"(got {self.jcbb_time_budget_s})")


def resolve_method(config: AssociationConfig, has_ids: bool) -> AssociationConfig:
    """``config`` with ``auto`` replaced by the method it means: ``known`` when the data carry landmark ids (some
    observation has an id >= 0), else ``AUTO_WITHOUT_IDS``. Any other method is returned unchanged.

    Who decides ``has_ids``: the runner looks at the whole log (``Log.obs_id``) before building the estimator; a back
    end that still holds ``auto`` (built without a log, e.g. from Python) resolves it at its first step that has
    observations, from that step's ids.
    """
    if config.method != "auto":
        return config
    return replace(config, method="known") if has_ids else replace(config, method=AUTO_WITHOUT_IDS)


@dataclass(frozen=True)
class Candidates:
    """Predicted measurements of the landmarks an observation may belong to.

    Shapes: ids (L,) int, z_pred (L,2) [range, bearing], S (L,2,2) innovation covariances,
    S_joint (2L,2L) joint innovation covariance of all candidates (landmark-landmark correlations through the pose;
    needed by ``jcbb`` and ``ransac``; None means "block diagonal of S"), descriptors (L,D) or None.
    """

    ids: IntArray
    z_pred: Array
    S: Array
    S_joint: Array | None = None
    descriptors: Array | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @staticmethod
    def empty() -> Candidates:
        return Candidates(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)))


@dataclass(frozen=True)
class AssociationResult:
    """Per observation: the candidate id it belongs to, or NEW / CLUTTER; with the statistics of the decision.

    Shapes: assignment (K,) int, d2 (K,) squared Mahalanobis distance to the assigned candidate (nan when none),
    joint_nis = sum of d2 over matched observations evaluated jointly (with S_joint when given); nan when one
    candidate is claimed by two observations (only ``nn`` and ``known`` can do that) since no joint Gaussian exists.
    ``nodes``: search effort (jcbb: interpretation-tree nodes visited; ransac: hypotheses scored; else 0).
    ``truncated``: jcbb stopped at ``jcbb_max_nodes`` or ``jcbb_time_budget_s`` and the answer may not be the
    optimum.
    """

    assignment: IntArray
    d2: Array
    joint_nis: float = 0.0
    nodes: int = 0
    truncated: bool = False

    @property
    def matched(self) -> NDArray[np.bool_]:
        """(K,) True where the observation was assigned to a candidate."""
        return self.assignment >= 0


def associate_known(observations: Observations, candidates: Candidates) -> AssociationResult:
    """Oracle association: the source's ids (simulator truth or barcodes). Unseen ids are NEW; negative ids clutter."""
    ids = observations.landmark_id
    known = np.isin(ids, candidates.ids)
    assignment = np.where(known, ids, np.where(ids >= 0, NEW, CLUTTER)).astype(np.int64)
    return AssociationResult(assignment, np.full(len(ids), np.nan), 0.0)
