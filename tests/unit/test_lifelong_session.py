"""Lifelong lidar sessions with saved maps (issue 17): the static layer is saved with the map, a later flight
relocalises, localises against the saved layer and updates it; its map keeps the saved keyframes and cell lattice.
"""

from pathlib import Path

import numpy as np
import pytest

from slam2d.config import with_overrides
from slam2d.graph.lidar import LifelongLidarConfig
from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
from slam2d.lab.runner import run
from slam2d.maps.layers import LayersConfig, MapLayers
from slam2d.maps.store import MapStore
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import simulate, spawn_streams

SMALL = {"warehouse.width_m": "30", "warehouse.depth_m": "22", "warehouse.aisles": "2",
         "warehouse.cross_aisles": "1", "warehouse.pallets": "18", "moving_objects": "1", "dt_s": "0.1",
         "warehouse.floor_markers": "true"}
WORLD = "test-world"


def _small(flight: int, steps: int) -> ScenarioConfig:
    return with_overrides(ScenarioConfig(name="warehouse-challenge"),
                          {**SMALL, "warehouse.flight": str(flight), "steps": str(steps)})


def _session(flight: int, steps: int, prior=None) -> tuple[LidarSession, object]:
    log = simulate(_small(flight, steps), 0)
    est = LidarSession(LidarSessionConfig(lidar=LifelongLidarConfig()), prior=prior, world_id=WORLD)
    res = run(est, log, rng=spawn_streams(0)["estimator"], progress=False)
    return est, (log, res)


def _static_cells(lay: MapLayers) -> set[tuple[int, ...]]:
    """Global integer cells of a layer's static cells (layers on one lattice compare cell by cell)."""
    return set(map(tuple, np.floor(lay.static_points() / lay.resolution).astype(int).tolist()))


@pytest.fixture(scope="module")
def first_flight(tmp_path_factory):
    """Flight 1 (cold start): its saved map, the session, and its largest position error (the map's drift)."""
    est, (log, res) = _session(0, 500)
    path = Path(tmp_path_factory.mktemp("maps")) / "f1.db"
    est.save_map(str(path))
    drift = float(np.max(np.hypot(*(res.trajectory[:, :2] - log.true_poses[:, :2]).T)))
    return MapStore.read(path), est, drift


def test_saved_static_layer_round_trips_and_matches_like_the_original(first_flight):
    snap, est, _ = first_flight
    lay = est.lidar.map_layers()
    back = MapLayers.from_saved(LayersConfig(), snap.layers)
    assert np.array_equal(back.static, lay.static) and np.array_equal(back.mean, lay.mean)
    assert np.array_equal(back.origin, lay.origin)
    # a scan's points matched from an offset guess: the same answer on both layers
    pts = back.static_points()[::7] - np.array([3.0, 2.0])
    guess = np.array([3.1, 1.95, 0.01])
    a, b = lay.match(pts, guess), back.match(pts, guess)
    assert np.allclose(a.pose, b.pose, atol=1e-3) and abs(a.inliers - b.inliers) <= 0.02 * len(pts)
    # the saved grid is the static layer: occupied exactly at the static cells
    assert np.array_equal(snap.occupancy_logodds > 1.0, lay.static)


def test_from_saved_refuses_a_map_without_layers_and_another_cell_size(first_flight):
    snap, _, _ = first_flight
    with pytest.raises(ValueError, match="not made by a lifelong session"):
        MapLayers.from_saved(LayersConfig(), {"floor_markers": np.zeros((1, 2))})
    with pytest.raises(ValueError, match="resolution_m"):
        MapLayers.from_saved(LayersConfig(resolution_m=0.2), snap.layers)


def test_a_later_flight_relocalises_onto_the_saved_layer_and_keeps_its_frame(first_flight):
    snap, _, drift = first_flight
    est, (log, res) = _session(1, 400, prior=snap)  # pallets moved since flight 1
    assert est.relocalised and est.accepted_step is not None and est.accepted_step < 100
    after = res.trajectory[est.accepted_step:] - log.true_poses[est.accepted_step:]
    err = np.hypot(after[:, 0], after[:, 1])
    # tracked in the saved map's frame: off the truth by no more than that map's own drift (flight 1's error)
    assert np.max(err) < drift + 0.05, (np.max(err), drift)
    two = est.snapshot()
    k = len(snap.keyframe_poses)
    assert np.array_equal(two.keyframe_poses[:k], snap.keyframe_poses)  # the saved keyframes never move
    off = (two.occupancy_origin - snap.occupancy_origin) / snap.occupancy_resolution_m
    assert np.allclose(off, np.round(off), atol=1e-6)  # the same cell lattice (the layer may have grown)
    f1 = MapLayers.from_saved(LayersConfig(), snap.layers)
    f2 = MapLayers.from_saved(LayersConfig(), two.layers)
    c1, c2 = _static_cells(f1), _static_cells(f2)
    assert len(c1 & c2) / len(c1 | c2) > 0.85  # the same racks; pallets moved and new ground seen


def test_dotted_layer_override_reaches_the_session_config():
    cfg = with_overrides(LifelongLidarConfig(), {"layers.persist_s": "4"})
    assert LidarSession(LidarSessionConfig(lidar=cfg), world_id=WORLD).lifelong
    assert cfg.layers is not None and cfg.layers.persist_s == 4.0
