"""Topological maps: the room's skeleton graph has exactly one cycle (around the pillar); trajectory places."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid
from slam2d.maps.topology import TopologyConfig, three_views, topology_from_grid, topology_from_trajectory
from slam2d.sim import simulate


def grid_for(scenario: str) -> tuple[OccupancyGrid, np.ndarray]:
    log = simulate(scenario, seed=0)
    assert log.walls is not None and log.true_poses is not None and log.scan_step is not None
    w = log.walls.reshape(-1, 2)
    lo, hi = w.min(axis=0) - 1.05, w.max(axis=0) + 1.05
    g = OccupancyGrid((lo[0], lo[1], hi[0], hi[1]), OccupancyConfig(resolution_m=0.1))
    g.integrate(log.true_poses[log.scan_step], log.scan_ranges_m, log.scan_angles_rad, log.scan_max_range_m)
    return g, log.true_poses


@pytest.mark.parametrize("scenario", ["room", "loop"])
def test_skeleton_graph_has_the_one_loop(scenario: str) -> None:
    g, _ = grid_for(scenario)
    t = topology_from_grid(g)
    assert t.cycles() == 1  # room: around the pillar; loop: around the central block
    assert t.skeleton is not None and t.skeleton.any()
    # every place is in known free space, away from walls
    flat, inside = g.cell_index(t.places)
    assert inside.all() and g.free().reshape(-1)[flat].all()
    assert np.all(t.clearance_m >= TopologyConfig().min_clearance_m)
    assert np.all(t.edge_length_m >= 0) and t.edges.max() < len(t.places)


def test_synthetic_two_rooms_and_a_door() -> None:
    """Two rooms joined by a door: one connected graph, no cycle, the connection passes through the door."""
    cfg = OccupancyConfig(resolution_m=0.1)
    g = OccupancyGrid((-0.55, -0.55, 20.5, 8.5), cfg)
    free = np.zeros(g.shape, dtype=bool)
    x, y = g.cell_centres()
    xx, yy = np.meshgrid(x, y)
    free |= (xx > 0.3) & (xx < 9.7) & (yy > 0.3) & (yy < 7.7)
    free |= (xx > 10.3) & (xx < 19.7) & (yy > 0.3) & (yy < 7.7)
    free |= (xx >= 9.6) & (xx <= 10.4) & (yy > 3.4) & (yy < 4.6)  # the door
    g.logodds[:] = np.where(free, -2.0, 2.0)
    t = topology_from_grid(g, TopologyConfig(min_spur_m=1.5))
    assert t.cycles() == 0
    assert t.skeleton is not None
    door = t.skeleton[(yy > 3.3) & (yy < 4.7) & (np.abs(xx - 10.0) < 0.3)]
    assert door.any()
    from scipy.ndimage import label

    assert label(t.skeleton, structure=np.ones((3, 3)))[1] == 1


def test_trajectory_topology() -> None:
    log = simulate("room", seed=0)
    assert log.true_poses is not None
    t = topology_from_trajectory(log.true_poses, spacing_m=2.0)
    assert t.cycles() == 1  # two laps of one loop: the second lap reuses the places
    d = np.hypot(*(t.places[:, None] - t.places[None]).transpose(2, 0, 1))
    assert np.all(d[np.triu_indices(len(d), 1)] > 2.0)  # places are spread out
    assert np.all(t.edge_length_m < 4.5)
    with pytest.raises(ValueError, match="spacing_m"):
        topology_from_trajectory(log.true_poses, spacing_m=0.0)


def test_three_views_of_the_room() -> None:
    log = simulate("room", seed=0)
    v = three_views(log)
    assert set(v) == {"landmarks", "grid", "topology", "trajectory_topology"}
    lm = v["landmarks"]
    assert lm["means"].shape[1] == 2 and len(lm["ids"]) >= 20 and np.all(lm["counts"] >= 10)
    assert v["grid"]["logodds"].ndim == 2 and v["topology"]["edges"].shape[1] == 2
    with pytest.raises(ValueError, match="true poses"):
        three_views(dataclasses.replace(log, true_poses=None))
