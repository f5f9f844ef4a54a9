"""Association quality against the data source's true ids (simulator oracle ids or barcodes).

Definitions (per observation; counts are summed over any number of batches before the ratios are taken, i.e. the
ratios are pooled, not averages of per-batch ratios):

* a *match* is an observation assigned to a landmark id (assignment >= 0);
* a match is *correct* when the assigned id equals the observation's true id;
* an observation is *matchable* when its true id is a landmark (>= 0) that was among the candidates offered, i.e.
  a correct match was possible;
* ``precision = correct / matches``: the fraction of matches that are right. Matches of clutter, of moving objects
  and of landmarks not among the candidates are all wrong matches (nan when there are no matches);
* ``recall = correct / matchable``: the fraction of possible correct matches made (nan when nothing is matchable);
* ``false_new_rate = (matchable observations assigned NEW) / matchable``: how often a known landmark would be
  duplicated as a new one (nan when nothing is matchable);
* ``missed_new_rate = (unmatchable landmark observations assigned to a landmark) / unmatchable landmark
  observations``: how often a not-yet-mapped landmark is folded into an existing one (nan when there are none).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from slam2d.association.base import NEW


@dataclass(frozen=True)
class AssociationCounts:
    """Counts behind the association metrics; add two with ``+`` to pool batches."""

    observations: int = 0
    matchable: int = 0
    matches: int = 0
    correct: int = 0
    false_new: int = 0
    unmatchable_landmark: int = 0
    wrongly_merged: int = 0

    def __add__(self, other: AssociationCounts) -> AssociationCounts:
        return AssociationCounts(**{k: getattr(self, k) + getattr(other, k) for k in self.__dataclass_fields__})

    @staticmethod
    def _ratio(num: int, den: int) -> float:
        return num / den if den else float("nan")

    @property
    def precision(self) -> float:
        """correct / matches."""
        return self._ratio(self.correct, self.matches)

    @property
    def recall(self) -> float:
        """correct / matchable."""
        return self._ratio(self.correct, self.matchable)

    @property
    def false_new_rate(self) -> float:
        """matchable observations assigned NEW / matchable."""
        return self._ratio(self.false_new, self.matchable)

    @property
    def missed_new_rate(self) -> float:
        """unmatchable landmark observations assigned to a landmark / unmatchable landmark observations."""
        return self._ratio(self.wrongly_merged, self.unmatchable_landmark)

    def as_dict(self) -> dict[str, float | int]:
        """Counts and ratios in one flat record (for JSON)."""
        out: dict[str, float | int] = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out.update(precision=self.precision, recall=self.recall, false_new_rate=self.false_new_rate,
                   missed_new_rate=self.missed_new_rate)
        return out


def association_counts(true_ids: ArrayLike, assignment: ArrayLike, candidate_ids: ArrayLike) -> AssociationCounts:
    """Score one batch. Shapes: true_ids (K,) (>= 0 landmark, negative: clutter / moving), assignment (K,),
    candidate_ids (L,) the landmark ids that were offered as candidates."""
    t = np.asarray(true_ids, dtype=np.int64).reshape(-1)
    a = np.asarray(assignment, dtype=np.int64).reshape(-1)
    if t.shape != a.shape:
        raise ValueError(f"true_ids and assignment must have the same length, got {t.shape} and {a.shape}")
    offered = np.isin(t, np.asarray(candidate_ids, dtype=np.int64).reshape(-1)) & (t >= 0)
    matched = a >= 0
    unmatchable_lm = (t >= 0) & ~offered
    return AssociationCounts(
        observations=int(t.size),
        matchable=int(offered.sum()),
        matches=int(matched.sum()),
        correct=int((matched & (a == t)).sum()),
        false_new=int((offered & (a == NEW)).sum()),
        unmatchable_landmark=int(unmatchable_lm.sum()),
        wrongly_merged=int((unmatchable_lm & matched).sum()),
    )


def run_association_scores(assignments: Sequence[ArrayLike], true_ids: Sequence[ArrayLike]) -> dict[str, float]:
    """Precision and recall of a whole run whose landmark ids are the estimator's own (not the source's).

    Each estimator landmark is mapped to the true id most often observed when it was matched; then a match is
    correct when its landmark maps to the observation's true id. An observation is matchable when its true landmark
    had been observed in an earlier step (so a correct match was possible). Steps are given in order: one array of
    assignments (>= 0 estimator id, NEW, CLUTTER) and one of true ids per step.
    """
    if len(assignments) != len(true_ids):
        raise ValueError(f"assignments and true_ids must have one array per step, got {len(assignments)} and "
                         f"{len(true_ids)} steps")
    for i, (x, y) in enumerate(zip(assignments, true_ids, strict=True)):
        if np.size(x) != np.size(y):
            raise ValueError(f"step {i}: {np.size(x)} assignments for {np.size(y)} true ids")
    if not assignments:
        return {"assoc_precision": float("nan"), "assoc_recall": float("nan")}
    a = np.concatenate([np.asarray(x, dtype=np.int64).reshape(-1) for x in assignments])
    t = np.concatenate([np.asarray(x, dtype=np.int64).reshape(-1) for x in true_ids])
    step = np.concatenate([np.full(np.size(x), i) for i, x in enumerate(assignments)])
    matched = a >= 0
    mapping: dict[int, int] = {}
    if np.any(matched):
        pairs, counts = np.unique(np.stack([a[matched], t[matched]], axis=1), axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))  # per estimator id, most frequent true id first
        for est_id, true_id in pairs[order]:
            mapping.setdefault(int(est_id), int(true_id))
    mapped = np.array([mapping.get(int(x), -10) for x in a], dtype=np.int64)
    correct = matched & (mapped == t) & (t >= 0)
    # first sighting step of every true landmark: observations after it are matchable
    first_seen: dict[int, int] = {}
    for s_i, tid in zip(step, t, strict=True):
        if tid >= 0 and int(tid) not in first_seen:
            first_seen[int(tid)] = int(s_i)
    matchable = np.array([tid >= 0 and first_seen[int(tid)] < s_i for s_i, tid in zip(step, t, strict=True)],
                         dtype=bool)
    n_match, n_matchable = int(matched.sum()), int(matchable.sum())
    return {
        "assoc_precision": float(correct.sum() / n_match) if n_match else float("nan"),
        "assoc_recall": float((correct & matchable).sum() / n_matchable) if n_matchable else float("nan"),
    }
