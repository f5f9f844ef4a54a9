"""Changes to a loaded map (:class:`~slam2d.maps.layers.MapLayers` started from a saved static layer).

On a session that starts from a saved map, something that appears where the loaded map had observed free ground
is a *change to the map* (a pallet put down, a trolley parked), not new structure. Such a cell keeps a *changed
since* time (the first hit after the load, or after it was last seen free) and stays out of the static layer until
the change has lasted ``LayersConfig.changed_persist_s`` (8 h by default, a shift: pallets are moved daily, so a
change that outlasts a shift is structure; 30 min, the first choice, is shorter than a full-scale flight, 44 min,
and let moved pallets join within one). Until then it is labelled dynamic and, while its log-odds
says occupied, it is part of the dynamic layer (:meth:`MapLayers.dynamic_occupancy` = 1: a *semi-static* change,
it does not decay). A changed cell that is seen free again (log-odds at or below ``free_logodds``) forgets its
clock; a pallet put there later starts a new one.

Removals wait the same way: a cell static in the loaded map that is seen through (a pallet taken away) keeps a
*removed since* time and stays in the static layer until the removal has lasted ``changed_persist_s``; hit again
(log-odds back above 0: the pallet is back) it forgets the clock. Holding only additions made the static layers of
two full-scale flights differ by every old pallet place (60 of 600 pallets moved: 2,260 cells left at once, cell IoU
0.904). :func:`removed_mask` gives the cells awaiting removal. The ages of every open change and removal are saved
with the map (``static_changed_age_s``, ``static_removed_age_s``; -1: none), so the clocks run on across flights (a
change seen on two 5-minute flights has lasted 10 minutes). Cold starts (no loaded map) never create these arrays
and behave exactly as before.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from slam2d.maps.layers import MapLayers

__all__ = ["CHANGE_FILL", "SAVED_AGE", "SAVED_REMOVED_AGE", "changed_mask", "hold_removals", "load_changes",
           "removed_mask", "saved_ages", "track_changes"]

CHANGE_FILL: dict[str, tuple[float | bool, type, tuple[int, ...]]] = {
    "changed_since": (-np.inf, np.float32, ()), "prior_free": (False, bool, ()),
    "removed_since": (-np.inf, np.float32, ()), "prior_static": (False, bool, ())}
"""per-cell arrays of a loaded map: when the current change began (-inf: none), whether the loaded map had the
cell observed free (a hit there is a change), when the current removal began (-inf: none), and whether the loaded
map had the cell static (seeing through it is a removal)."""

SAVED_AGE = "static_changed_age_s"
SAVED_REMOVED_AGE = "static_removed_age_s"


def load_changes(lay: MapLayers, arrays: Mapping[str, NDArray[Any]]) -> None:
    """Start tracking changes on ``lay``, just loaded from ``arrays`` (a saved map; its optional change ages)."""
    lay.prior_map = True
    lay._fill.update(CHANGE_FILL)
    lay.prior_free = lay.logodds <= lay.config.free_logodds
    lay.prior_static = lay.static.copy()
    lay.changed_since = np.full(lay.shape, -np.inf, dtype=np.float32)
    lay.removed_since = np.full(lay.shape, -np.inf, dtype=np.float32)
    lay.pending_ages = None
    ages = {}
    for name in (SAVED_AGE, SAVED_REMOVED_AGE):
        age = arrays.get(name)
        if age is None:
            age = np.full(lay.shape, -1.0, dtype=np.float32)
        age = np.asarray(age, dtype=np.float32)
        if age.shape != lay.shape:
            raise ValueError(f"MapLayers.from_saved: {name} has shape {age.shape}, the layer {lay.shape}")
        ages[name] = age
    lay.prior_free |= ages[SAVED_AGE] >= 0  # a change still open when the map was saved
    if any(np.any(a >= 0) for a in ages.values()):
        lay.pending_ages = ages  # turned into times at the first scan (the session's clock is not known before)


def _start_clocks(lay: MapLayers, t: np.float32) -> None:
    """Turn the saved ages into times on this session's clock (at its first scan)."""
    if lay.pending_ages is None:
        return
    for since, name in ((lay.changed_since, SAVED_AGE), (lay.removed_since, SAVED_REMOVED_AGE)):
        age = lay.pending_ages[name]
        since[:] = np.where(age >= 0, t - age, -np.inf)
    lay.pending_ages = None


def hold_removals(lay: MapLayers, t: np.float32, gone: NDArray[np.int64]) -> NDArray[np.int64]:
    """Of the static cells ``gone`` (seen through this scan, log-odds below 0), those that leave the static layer
    now: all of them on a cold start; from a loaded map, its own static cells only once their removal has lasted
    ``changed_persist_s`` (the clock starts at the first such scan)."""
    if not lay.prior_map or not gone.size:
        return gone
    _start_clocks(lay, t)
    since = lay.removed_since.ravel()
    held = lay.prior_static.ravel()[gone]
    start = gone[held & ~np.isfinite(since[gone])]
    since[start] = t
    return gone[~held | ((t - since[gone]) >= lay.config.changed_persist_s)]


def track_changes(lay: MapLayers, t: np.float32, miss: NDArray[np.int64], hit: NDArray[np.int64]) -> None:
    """One scan's bookkeeping: ``miss`` cells were seen through (their log-odds already lowered), ``hit`` cells hit
    at time ``t`` (before their log-odds rise). Nothing on a cold start."""
    if not lay.prior_map:
        return
    _start_clocks(lay, t)
    since = lay.changed_since.ravel()
    lo = lay.logodds.ravel()
    since[miss[lo[miss] <= lay.config.free_logodds]] = -np.inf  # seen free again: the change is over
    start = hit[lay.prior_free.ravel()[hit] & ~np.isfinite(since[hit])]
    since[start] = t
    removed = lay.removed_since.ravel()
    removed[hit[lo[hit] >= 0.0]] = -np.inf  # evidence says occupied again: the removal is over
    lay.last_time_s = float(t)


def changed_mask(lay: MapLayers) -> NDArray[np.bool_]:
    """Cells holding a change to the loaded map (occupied, not yet static): the semi-static part of the dynamic
    layer. All False on a cold start."""
    if not lay.prior_map:
        return np.zeros(lay.shape, dtype=bool)
    return np.isfinite(lay.changed_since) & ~lay.static & (lay.logodds >= lay.config.occupied_logodds)


def removed_mask(lay: MapLayers) -> NDArray[np.bool_]:
    """Cells of the loaded static layer seen through and awaiting removal (still static). All False on a cold
    start."""
    if not lay.prior_map:
        return np.zeros(lay.shape, dtype=bool)
    return np.isfinite(lay.removed_since) & lay.static


def saved_ages(lay: MapLayers) -> dict[str, NDArray[Any]]:
    """The ages (s) of the open changes and removals for a saved map (-1: none); nothing on a cold start."""
    if not lay.prior_map:
        return {}
    if lay.pending_ages is not None:  # no scan since the load: the saved ages are still the ages
        return {k: v.copy() for k, v in lay.pending_ages.items()}
    now = np.float32(lay.last_time_s)
    added = np.where(np.isfinite(lay.changed_since) & ~lay.static, now - lay.changed_since, -1.0)
    removed = np.where(removed_mask(lay), now - lay.removed_since, -1.0)
    return {SAVED_AGE: added.astype(np.float32), SAVED_REMOVED_AGE: removed.astype(np.float32)}
