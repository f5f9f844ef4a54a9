"""Changes to a loaded map (slam2d.maps.layer_changes): pallets put on ground the saved map saw free stay in the
dynamic layer, removed ones stay in the static layer awaiting removal; both until changed_persist_s; cold starts
are untouched."""

from __future__ import annotations

import numpy as np
from test_map_layers import POSES, ROOM, mapped_room, scan_at, segment_distances_min, wall_cells

from slam2d.maps.layer_changes import SAVED_AGE, SAVED_REMOVED_AGE, changed_mask, removed_mask
from slam2d.maps.layers import LayersConfig, MapLayers
from slam2d.sim.warehouse import boxes_to_segments

PALLET = boxes_to_segments(np.array([[5.0, 4.6]]), (1.2, 1.0))  # on open floor, well inside the room


def fly(lay: MapLayers, world: np.ndarray, t: float, seconds: float, rng: np.random.Generator) -> float:
    """``seconds`` of 10 Hz scans of ``world`` from the usual poses; returns the time after them."""
    for k in range(round(seconds * 10)):
        pose = POSES[k % len(POSES)]
        pts = scan_at(pose, world, rng)
        lay.integrate(pose, pts, lay.classify(pose, pts), t)
        t += 0.1
    return t


def near_pallet(lay: MapLayers, cells: np.ndarray) -> int:
    return int(np.count_nonzero(segment_distances_min(lay.cell_centres(cells), PALLET) < 0.1))


def test_pallet_on_ground_the_loaded_map_saw_free_stays_dynamic_until_changed_persist_s() -> None:
    rng = np.random.default_rng(2)
    cold, t = mapped_room(rng)
    assert near_pallet(cold, cold.static_cells()) == 0
    walls = set(wall_cells(cold).tolist())
    loaded = MapLayers.from_saved(None, cold.saved())
    world = np.vstack([ROOM, PALLET])
    t_cold = fly(cold, world, t, 4 * cold.config.persist_s, np.random.default_rng(3))
    t_load = fly(loaded, world, 0.0, 4 * cold.config.persist_s, np.random.default_rng(3))
    assert near_pallet(cold, cold.static_cells()) > 10, "without a loaded map the pallet joins after persist_s"
    assert near_pallet(loaded, loaded.static_cells()) == 0, "a change to the loaded map stays out of the static layer"
    dyn = np.flatnonzero(loaded.dynamic_occupancy(t_load - 0.1).ravel() > 0.5)
    assert near_pallet(loaded, dyn) > 10, "... and is held in the dynamic layer (not decayed)"
    assert near_pallet(loaded, np.flatnonzero(changed_mask(loaded).ravel())) == near_pallet(loaded, dyn)
    assert walls <= set(loaded.static_cells().tolist())
    assert near_pallet(cold, np.flatnonzero(cold.dynamic_occupancy(t_cold - 0.1).ravel() > 0.5)) == 0

    # the change's age is saved with the map and runs on in the next session: with changed_persist_s = 30 s the
    # pallet (20 s old) joins after about 10 s more of sightings, not before
    cfg = LayersConfig(changed_persist_s=30.0)
    saved = loaded.saved()
    age = saved[SAVED_AGE].ravel()
    pallet_cells = np.flatnonzero(changed_mask(loaded).ravel())
    assert np.all((age[pallet_cells] > 0) & (age[pallet_cells] <= 19.9 + 1e-4)) and np.median(age[pallet_cells]) > 19
    assert np.all(age[~np.isfinite(loaded.changed_since.ravel())] == -1)
    again = MapLayers.from_saved(cfg, saved)
    t2 = fly(again, world, 1000.0, 8.0, np.random.default_rng(4))  # another clock: ages, not times, are saved
    assert near_pallet(again, again.static_cells()) == 0
    fly(again, world, t2, 4.0, np.random.default_rng(5))
    assert near_pallet(again, again.static_cells()) > 10, "a change that lasts changed_persist_s joins the map"


def test_removed_pallet_stays_static_until_the_removal_has_lasted_changed_persist_s() -> None:
    rng = np.random.default_rng(6)
    cold, t = mapped_room(rng)
    t_cold = fly(cold, np.vstack([ROOM, PALLET]), t, 4 * cold.config.persist_s, rng)
    assert near_pallet(cold, cold.static_cells()) > 10
    walls = set(wall_cells(cold).tolist())
    saved_with_pallet = cold.saved()
    loaded = MapLayers.from_saved(None, saved_with_pallet)
    before = near_pallet(loaded, loaded.static_cells())
    # the pallet has gone: a cold start drops it at once (one corner cell whose surface these beams never cross
    # stays); from the loaded map it stays static, awaiting removal, and is not put into the dynamic layer
    t = fly(loaded, ROOM, 0.0, 5.0, np.random.default_rng(1))
    fly(cold, ROOM, t_cold, 5.0, np.random.default_rng(1))
    assert near_pallet(cold, cold.static_cells()) <= 1 < before
    assert near_pallet(loaded, loaded.static_cells()) == before
    held = near_pallet(loaded, np.flatnonzero(removed_mask(loaded).ravel()))
    assert held >= before - 1 and held > 10
    assert near_pallet(loaded, np.flatnonzero(loaded.dynamic_occupancy(t - 0.1).ravel() > 0.5)) == 0
    assert walls <= set(loaded.static_cells().tolist())
    assert not removed_mask(loaded).ravel()[np.array(sorted(walls))].any()

    # the removal's age is saved with the map and runs on: with changed_persist_s = 8 s the cells (about 5 s into
    # their removal) are still static 2 s into the next session and gone 4 s later
    saved = loaded.saved()
    age = saved[SAVED_REMOVED_AGE].ravel()
    cells = np.flatnonzero(removed_mask(loaded).ravel())
    assert np.all((age[cells] > 0) & (age[cells] <= 5.0)) and np.all(np.delete(age, cells) == -1)
    again = MapLayers.from_saved(LayersConfig(changed_persist_s=8.0), saved)
    t2 = fly(again, ROOM, 500.0, 2.0, np.random.default_rng(2))
    assert near_pallet(again, again.static_cells()) == before
    fly(again, ROOM, t2, 4.0, np.random.default_rng(3))
    assert near_pallet(again, again.static_cells()) <= 1, "a removal that lasts changed_persist_s leaves the map"
    assert walls <= set(again.static_cells().tolist())

    # put back before its removal is due: the clock stops, the pallet never left the map
    back = MapLayers.from_saved(LayersConfig(changed_persist_s=8.0), saved_with_pallet)
    t3 = fly(back, ROOM, 0.0, 5.0, np.random.default_rng(4))
    t3 = fly(back, np.vstack([ROOM, PALLET]), t3, 3.0, np.random.default_rng(5))
    assert near_pallet(back, np.flatnonzero(removed_mask(back).ravel())) <= 1
    fly(back, np.vstack([ROOM, PALLET]), t3, 10.0, np.random.default_rng(6))
    assert near_pallet(back, back.static_cells()) >= before - 1


def test_cold_start_is_untouched_by_the_change_rule() -> None:
    runs = []
    for cfg in (LayersConfig(), LayersConfig(changed_persist_s=1.0)):
        rng = np.random.default_rng(7)
        lay = MapLayers(cfg)
        t = fly(lay, ROOM, 0.0, 6.0, rng)
        t = fly(lay, np.vstack([ROOM, PALLET]), t, 12.0, rng)
        runs.append((lay, t))
    (a, ta), (b, tb) = runs
    assert not a.prior_map and not hasattr(a, "changed_since") and sorted(a.saved()) == sorted(MapLayers.SAVED)
    for name in MapLayers._FILL:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.dynamic_occupancy(ta), b.dynamic_occupancy(tb))
    assert a.nbytes() == b.nbytes() and (a.promoted, a.demoted) == (b.promoted, b.demoted)
    assert near_pallet(a, a.static_cells()) > 10  # the cold start promotes the pallet after persist_s as before
