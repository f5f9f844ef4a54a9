"""Loop closing for any back end that keeps poses: keyframes, place recognition, verification and a gate.

:class:`LoopCloser` owns the keyframe database (descriptor per keyframe plus its observation points) and decides,
for a new observation set at pose key ``b``, whether it closes a loop with an earlier keyframe ``a``:

1. **propose**: the keyframes whose descriptor is close (:class:`~slam2d.frontend.place_recognition.
   KeyframeDatabase`, at most ``top_k``, at least ``min_separation`` keys back);
2. **verify**: RANSAC + weighted least squares between the two point sets gives ``T_a_b`` and its covariance
   (:func:`~slam2d.frontend.place_recognition.verify_loop`);
3. **gate**: the measured ``T_a_b`` must agree with the back end's current estimate of the same relative pose at a
   chi-square probability, with the covariance of that estimate taken from the JOINT marginal of ``[x_a, x_b]``
   (:func:`~slam2d.frontend.place_recognition.loop_gate`). A place that merely looks the same fails here.

Candidates are tried best descriptor first; the first one that passes the gate is the closure (the others are not
tried). The back end supplies its estimate through two callables, so nothing here knows how it stores poses:
``pose_of(key) -> (3,)`` and ``joint_cov(a, b) -> (6, 6)`` (called only for a verified candidate: a marginal can be
expensive).

Bounded work per step (``queue`` + ``verify_queued``): instead of verifying every candidate of a keyframe at once
(each verification costs a few milliseconds), a back end may queue them and verify a fixed number per step; the
candidates of one keyframe keep their order and the first accepted one still ends them. At most ``MAX_QUEUED``
candidates wait (the oldest are dropped: a stale candidate's keyframe has left the back end's local window).

State: the keyframes are map state (one entry per keyframe with enough points, kept for the whole run, as the
landmarks are); the queue holds at most ``MAX_QUEUED`` key pairs.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import LoopEvent
from slam2d.frontend.place_recognition import (
    KeyframeDatabase,
    LoopHypothesis,
    PlaceRecognitionConfig,
    loop_gate,
    verify_loop,
)
from slam2d.geometry import se2

Array = NDArray[np.float64]

#: candidates waiting for verification at most (``LoopCloser.queue``)
MAX_QUEUED = 6


@dataclass(frozen=True)
class LoopCandidate:
    """A verified candidate and the gate's verdict: keyframe ``a`` < pose ``b``, measured ``T_a_b`` (3,) with
    covariance ``cov`` (3,3), the gate's squared Mahalanobis distance ``d2`` and whether it passed."""

    a: int
    b: int
    T_a_b: Array
    cov: Array
    d2: float
    accepted: bool

    @property
    def event(self) -> LoopEvent:
        return LoopEvent(self.a, self.b, self.accepted, self.T_a_b)


class LoopCloser:
    """Keyframe database plus verification and gating (see module doc)."""

    def __init__(self, place: PlaceRecognitionConfig, gate_probability: float, rng: np.random.Generator) -> None:
        if not 0 < gate_probability < 1:
            raise ValueError(f"LoopCloser: gate_probability must be in (0, 1) (got {gate_probability})")
        self.place = place
        self.gate_probability = gate_probability
        self.rng = rng
        self.db = KeyframeDatabase(place)
        self.keyframes: dict[int, tuple[Array, Array]] = {}  # key -> points (K,2), covariances (K,2,2)
        self.queued: deque[tuple[int, int]] = deque(maxlen=MAX_QUEUED)  # (a, b) pairs, oldest first

    def add_keyframe(self, key: int, points: Array, covs: Array) -> bool:
        """Store a keyframe (points in its own frame with their covariances); False when too few points."""
        if not self.db.add(key, points):
            return False
        self.keyframes[int(key)] = (np.asarray(points, dtype=np.float64), np.asarray(covs, dtype=np.float64))
        return True

    def propose(self, key: int, points: Array) -> list[int]:
        """Keys of stored keyframes that look like ``points``, best first."""
        return [a for a, _ in self.db.query(points, key) if a in self.keyframes]

    def verify(self, a: int, points: Array, covs: Array) -> LoopHypothesis | None:
        """Geometric verification of keyframe ``a`` against these points (None: not the same place)."""
        pa, ca = self.keyframes[a]
        return verify_loop(pa, ca, points, covs, self.place, self.rng)

    def gate(self, a: int, b: int, hyp: LoopHypothesis, pose_a: Array, pose_b: Array, joint_ab: Array) -> LoopCandidate:
        """Check ``hyp`` against the estimate: poses (3,) of a and b and their joint marginal (6,6)."""
        t_pred = se2.between(pose_a, pose_b)
        ja, jb = se2.between_jacobians(pose_a, pose_b)
        j = np.hstack([ja, jb])
        ok, d2 = loop_gate(hyp.T_a_b, hyp.cov, t_pred, j @ joint_ab @ j.T, self.gate_probability)
        return LoopCandidate(a, b, hyp.T_a_b, hyp.cov, d2, ok)

    def try_close(self, key: int, points: Array, covs: Array, pose_of: Callable[[int], Array],
                  joint_cov: Callable[[int, int], Array], *, add_keyframe: bool = True) -> list[LoopCandidate]:
        """Propose, verify and gate loops for the observations at pose ``key``; returns every gated candidate in
        order (at most the last one accepted). The observations become a keyframe afterwards if ``add_keyframe``."""
        out: list[LoopCandidate] = []
        for a in self.propose(key, points):
            cand = self._check(a, key, points, covs, pose_of, joint_cov)
            if cand is None:
                continue
            out.append(cand)
            if cand.accepted:
                break
        if add_keyframe:
            self.add_keyframe(key, points, covs)
        return out

    def _check(self, a: int, b: int, points: Array, covs: Array, pose_of: Callable[[int], Array],
               joint_cov: Callable[[int, int], Array]) -> LoopCandidate | None:
        """Verify keyframe ``a`` against the observations at ``b`` and gate the result (None: not verified)."""
        hyp = self.verify(a, points, covs)
        return None if hyp is None else self.gate(a, b, hyp, pose_of(a), pose_of(b), joint_cov(a, b))

    def queue(self, key: int, points: Array, covs: Array) -> int:
        """Store the observations at pose ``key`` as a keyframe and queue its candidates (best first) for
        :meth:`verify_queued`; returns how many were queued."""
        cands = self.propose(key, points)
        if not self.add_keyframe(key, points, covs):
            return 0
        self.queued.extend((a, int(key)) for a in cands)
        return len(cands)

    def verify_queued(self, pose_of: Callable[[int], Array], joint_cov: Callable[[int, int], Array],
                      budget: int = 1) -> list[LoopCandidate]:
        """Verify and gate at most ``budget`` queued candidates, oldest first: the same decisions as
        :meth:`try_close` for the keyframe, spread over calls. An accepted one drops the rest of its keyframe's."""
        out: list[LoopCandidate] = []
        for _ in range(min(budget, len(self.queued))):
            a, b = self.queued.popleft()
            cand = self._check(a, b, *self.keyframes[b], pose_of, joint_cov)
            if cand is None:
                continue
            out.append(cand)
            if cand.accepted:
                self.queued = deque((p for p in self.queued if p[1] != b), maxlen=MAX_QUEUED)
        return out
