"""The "break-it" experiments: damage one ingredient of SLAM and watch what fails.

Each damage is a transformation of the recorded :class:`Log` (what the estimator is given) or of the estimator's
config, so every back end is broken in exactly the same way:

* ``no-loop-closure``: the estimator's ``loop_closure`` switch off (only back ends that have one);
* ``wrong-association``: half of the landmark ids reported with the observations are replaced by a wrong landmark's
  id (run with ``known`` association, the estimator trusts them: this is what a bad association layer does);
* ``few-landmarks``: only one landmark in five ever reports observations.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from slam2d.log import Log


def corrupt_association(log: Log, fraction: float, rng: np.random.Generator) -> Log:
    """A copy of ``log`` where ``fraction`` of the landmark observations carry a wrong (but valid) landmark id."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1] (got {fraction})")
    ids = log.obs_id.copy()
    real = np.flatnonzero(ids >= 0)
    known = np.unique(ids[real])
    if len(known) < 2 or len(real) == 0:
        return log
    pick = real[rng.random(len(real)) < fraction]
    # shift each picked id to a different landmark id (never the true one)
    offset = rng.integers(1, len(known), size=len(pick))
    pos = np.searchsorted(known, ids[pick])
    ids[pick] = known[(pos + offset) % len(known)]
    return dataclasses.replace(log, obs_id=ids, metadata={**log.metadata, "breakit": f"wrong-association:{fraction}"})


def thin_landmarks(log: Log, keep_fraction: float, rng: np.random.Generator) -> Log:
    """A copy of ``log`` in which only a random ``keep_fraction`` of the landmarks are ever observed."""
    if not 0.0 < keep_fraction <= 1.0:
        raise ValueError(f"keep_fraction must be in (0, 1] (got {keep_fraction})")
    ids = np.unique(log.obs_id[log.obs_id >= 0])
    n_keep = max(1, round(keep_fraction * len(ids)))
    kept = rng.choice(ids, size=n_keep, replace=False) if len(ids) else ids
    mask = np.isin(log.obs_id, kept) | (log.obs_id < 0)
    return dataclasses.replace(
        log,
        obs_step=log.obs_step[mask],
        obs_range_m=log.obs_range_m[mask],
        obs_bearing_rad=log.obs_bearing_rad[mask],
        obs_id=log.obs_id[mask],
        obs_descriptor=None if log.obs_descriptor is None else log.obs_descriptor[mask],
        metadata={**log.metadata, "breakit": f"few-landmarks:{keep_fraction}"},
    )
