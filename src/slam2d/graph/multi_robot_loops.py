"""Each robot's own loop closures in the joint graph: keyframes, place recognition, verification, a deferred gate.

The single-robot online graph closes loops by place recognition over landmark constellations
(:class:`~slam2d.frontend.loop_closure.LoopCloser`): a keyframe's observations, matched as a rigid point set against
an earlier keyframe's, give ``T_a_b`` however the individual landmarks were associated. Without ids that is what
keeps a robot's drift in check where the landmarks stand in tight clusters (MRCLAM: 15 landmarks in 6 clusters,
0.18-0.25 m apart, range noise 0.12-0.21 m) and single sightings are easily given to the wrong member. The joint
graph runs one :class:`LoopCloser` per robot (its own keyframes only: every robot keeps its own frame until merged,
so a loop is always within one frame).

Proposal and verification happen when the keyframe is taken (a few ms each); the GATE (``T_a_b`` against the
current estimate with the joint marginal of ``[x_a, x_b]``) waits for the next optimisation, when the graph holds
every factor and one factorisation serves every pending candidate. As in :meth:`LoopCloser.try_close`, a keyframe's
candidates are gated best first and the first accepted one is its closure; accepted loops enter the graph as
between factors with a robust kernel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam2d.frontend.loop_closure import LoopCandidate, LoopCloser
from slam2d.frontend.place_recognition import LoopHypothesis, PlaceRecognitionConfig, observation_points

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PendingLoop:
    """A verified candidate waiting for the gate: robot ``robot``'s keyframe ``a`` against its pose ``b``."""

    robot: int
    a: int
    b: int
    hypothesis: LoopHypothesis


class RobotLoops:
    """One :class:`LoopCloser` per robot and the verified candidates waiting for the gate (module doc)."""

    def __init__(self, robots: int, place: PlaceRecognitionConfig, gate_probability: float, keyframe_every: int,
                 rng: np.random.Generator) -> None:
        self.closers = [LoopCloser(place, gate_probability, rng) for _ in range(robots)]
        self.keyframe_every = keyframe_every
        self.last_keyframe = np.full(robots, -keyframe_every, dtype=np.int64)
        self.pending: list[PendingLoop] = []
        self.accepted = 0
        self.rejected = 0

    def observe(self, r: int, t: int, key: int, z: Array, R: Array) -> None:
        """Robot r measured ``z`` (K,2) at step t (pose ``key``): a keyframe when ``keyframe_every`` steps have
        passed since its last one; its verified candidates wait for :meth:`gate`."""
        if t - self.last_keyframe[r] < self.keyframe_every:
            return
        self.last_keyframe[r] = t
        closer = self.closers[r]
        pts, covs = observation_points(z, R)
        for a in closer.propose(key, pts):
            hyp = closer.verify(a, pts, covs)
            if hyp is not None:
                self.pending.append(PendingLoop(r, a, key, hyp))
        closer.add_keyframe(key, pts, covs)

    def keys(self) -> NDArray[np.int64]:
        """Pose keys the pending candidates need in the joint marginal."""
        return np.unique(np.array([k for p in self.pending for k in (p.a, p.b)], dtype=np.int64))

    def gate(self, pose_of: Callable[[int], Array], joint_cov: Callable[[int, int], Array]) -> list[LoopCandidate]:
        """Gate every pending candidate (the first accepted one per keyframe ends its others); returns the
        accepted ones and empties the queue."""
        out: list[LoopCandidate] = []
        closed: set[int] = set()
        for p in self.pending:
            if p.b in closed:
                continue
            c = self.closers[p.robot].gate(p.a, p.b, p.hypothesis, pose_of(p.a), pose_of(p.b), joint_cov(p.a, p.b))
            if c.accepted:
                closed.add(p.b)
                out.append(c)
                self.accepted += 1
            else:
                self.rejected += 1
        self.pending = []
        return out
