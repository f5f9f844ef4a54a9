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
