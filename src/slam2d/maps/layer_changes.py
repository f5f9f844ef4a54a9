"""Changes to a loaded map (:class:`~slam2d.maps.layers.MapLayers` started from a saved static layer).

On a session that starts from a saved map, something that appears where the loaded map had observed free ground
is a *change to the map* (a pallet put down, a trolley parked), not new structure. Such a cell keeps a *changed
since* time (the first hit after the load, or after it was last seen free) and stays out of the static layer until
the change has lasted ``LayersConfig.changed_persist_s`` (30 min by default: longer than a flight, far shorter
than a shift, so a pallet parked for a day does join). Until then it is labelled dynamic and, while its log-odds
says occupied, it is part of the dynamic layer (:meth:`MapLayers.dynamic_occupancy` = 1: a *semi-static* change,
it does not decay). A changed cell that is seen free again (log-odds at or below ``free_logodds``) forgets its
clock; a pallet put there later starts a new one. The age of every open change is saved with the map
(``static_changed_age_s``, -1: none), so the clock runs on across flights (a change seen on two 5-minute flights
has lasted 10 minutes). Removals are not delayed: a saved static cell that is seen through leaves the layer as on
a cold start. Cold starts (no loaded map) never create these arrays and behave exactly as before.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from slam2d.maps.layers import MapLayers

__all__ = ["CHANGE_FILL", "SAVED_AGE", "changed_mask", "load_changes", "saved_ages", "track_changes"]

CHANGE_FILL: dict[str, tuple[float | bool, type, tuple[int, ...]]] = {
    "changed_since": (-np.inf, np.float32, ()), "prior_free": (False, bool, ())}
"""per-cell arrays of a loaded map: when the current change began (-inf: none), and whether the loaded map had the
cell observed free (a hit there is a change)."""

SAVED_AGE = "static_changed_age_s"


def load_changes(lay: MapLayers, arrays: Mapping[str, NDArray[Any]]) -> None:
    """Start tracking changes on ``lay``, just loaded from ``arrays`` (a saved map; its optional change ages)."""
    lay.prior_map = True
    lay._fill.update(CHANGE_FILL)
    lay.prior_free = lay.logodds <= lay.config.free_logodds
    lay.changed_since = np.full(lay.shape, -np.inf, dtype=np.float32)
    age = arrays.get(SAVED_AGE)
    lay.pending_ages = None
    if age is not None:
        age = np.asarray(age, dtype=np.float32)
        if age.shape != lay.shape:
            raise ValueError(f"MapLayers.from_saved: {SAVED_AGE} has shape {age.shape}, the layer {lay.shape}")
        lay.prior_free |= age >= 0  # a change still open when the map was saved
        lay.pending_ages = age  # turned into times at the first scan (the session's clock is not known before)


def track_changes(lay: MapLayers, t: np.float32, miss: NDArray[np.int64], hit: NDArray[np.int64]) -> None:
    """One scan's bookkeeping: ``miss`` cells were seen through (their log-odds already lowered), ``hit`` cells hit
    at time ``t`` (before their log-odds rise). Nothing on a cold start."""
    if not lay.prior_map:
        return
    since = lay.changed_since.ravel()
    if lay.pending_ages is not None:
        since[:] = np.where(lay.pending_ages.ravel() >= 0, t - lay.pending_ages.ravel(), -np.inf)
        lay.pending_ages = None
    lo = lay.logodds.ravel()
    since[miss[lo[miss] <= lay.config.free_logodds]] = -np.inf  # seen free again: the change is over
    start = hit[lay.prior_free.ravel()[hit] & ~np.isfinite(since[hit])]
    since[start] = t
    lay.last_time_s = float(t)


def changed_mask(lay: MapLayers) -> NDArray[np.bool_]:
    """Cells holding a change to the loaded map (occupied, not yet static): the semi-static part of the dynamic
    layer. All False on a cold start."""
    if not lay.prior_map:
        return np.zeros(lay.shape, dtype=bool)
    return np.isfinite(lay.changed_since) & ~lay.static & (lay.logodds >= lay.config.occupied_logodds)


def saved_ages(lay: MapLayers) -> dict[str, NDArray[Any]]:
    """The ages (s) of the open changes for a saved map (-1: none); nothing on a cold start."""
    if not lay.prior_map:
        return {}
    if lay.pending_ages is not None:  # no scan since the load: the saved ages are still the ages
        return {SAVED_AGE: lay.pending_ages.copy()}
    open_ = np.isfinite(lay.changed_since) & ~lay.static
    age = np.where(open_, np.float32(lay.last_time_s) - lay.changed_since, -1.0)
    return {SAVED_AGE: age.astype(np.float32)}
