"""Solid walls for the true robot (slam2d.sim.collision), used by every driver through Simulator.step."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.models.lidar import LidarConfig
from slam2d.sim.collision import ROBOT_RADIUS_M, allowed_motion, clearance, crosses
from slam2d.sim.scenarios import SCENARIOS, ScenarioConfig
from slam2d.sim.simulator import Simulator

WALL = np.array([[0.0, 0.0, 0.0, 10.0]])  # the y axis from 0 to 10


def test_clearance_and_crossing_on_exact_cases() -> None:
    np.testing.assert_allclose(clearance([[3.0, 5.0], [-2.0, 12.0], [0.0, -1.0]], WALL), [3.0, np.hypot(2, 2), 1.0])
    assert clearance([[1.0, 1.0]], np.zeros((0, 4)))[0] == np.inf
    assert crosses([1.0, 5.0], [-1.0, 5.0], WALL) and not crosses([1.0, 5.0], [0.5, 5.0], WALL)
    assert not crosses([1.0, 11.0], [-1.0, 11.0], WALL)  # passes beyond the wall's end


def test_a_move_into_a_wall_keeps_only_its_rotation() -> None:
    facing_wall = np.array([0.35, 5.0, np.pi])
    u, blocked = allowed_motion(facing_wall, np.array([0.1, 0.0, 0.05]), WALL)
    assert blocked and np.array_equal(u, [0.0, 0.0, 0.05])
    # along the wall, or away from it, is free; so is backing out when already too close
    assert not allowed_motion(np.array([0.35, 5.0, np.pi / 2]), np.array([0.1, 0.0, 0.0]), WALL)[1]
    assert not allowed_motion(np.array([0.1, 5.0, 0.0]), np.array([0.1, 0.0, 0.0]), WALL)[1]
    # a long step cannot tunnel through
    assert allowed_motion(np.array([1.0, 5.0, np.pi]), np.array([3.0, 0.0, 0.0]), WALL)[1]


def test_holding_an_arrow_into_a_wall_stops_the_robot() -> None:
    sim = Simulator(ScenarioConfig(name="room", lidar=LidarConfig(enabled=False)), seed=0)
    sim.pose = np.array([12.0, 4.0, 0.0])  # facing the east wall (x = 20) across open floor
    xs = [sim.step(1.0, 0.0) and float(sim.pose[0]) for _ in range(200)]
    assert max(xs) <= 20.0 - ROBOT_RADIUS_M + 1e-9
    assert xs[-1] == xs[-50] and sim.collisions >= 100  # it stopped at the wall and stays there
    assert max(xs) > 20.0 - ROBOT_RADIUS_M - 0.15  # ... right at it, not before
    log = sim.to_log()  # the odometry reports the blocked steps as no translation (the true motion)
    assert np.abs(log.odometry[-50:, :2]).max() < 0.05


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_routes_never_touch_a_wall(name: str) -> None:
    """The waypoint routes keep clear of every solid segment, so collision never changes a recorded scenario."""
    sim = Simulator(ScenarioConfig(name=name, lidar=LidarConfig(enabled=False)), seed=0)
    driver = sim.driver()
    for _ in range(int(sim.config.steps or 0)):
        sim.step(*driver.command(sim.pose, sim.world.solid_segments(sim.time_s)))
    assert sim.collisions == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_explore_stays_in_the_world_and_avoids_walls_for_2000_steps(name: str) -> None:
    sim = Simulator(ScenarioConfig(name=name, driver="explore", lidar=LidarConfig(enabled=False)), seed=0)
    driver = sim.driver()
    x0, y0, x1, y1 = sim.world.bounds
    poses = []
    for _ in range(2000):
        sim.step(*driver.command(sim.pose, sim.world.solid_segments(sim.time_s)))
        poses.append(sim.pose[:2].copy())
    p = np.array(poses)
    assert np.all((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1))
    if len(sim.world.walls):
        assert clearance(p, sim.world.walls).min() >= ROBOT_RADIUS_M - 1e-9
    assert sim.collisions <= 20  # explore steers away: the walls rarely have to stop it
    # and it keeps moving (not stuck turning at a wall): at least half the distance it would cruise in open space
    cruise = 2000 * float(sim.config.dt_s or 0.1) * float(sim.config.speed_mps or 1.0)
    assert np.hypot(*np.diff(p, axis=0).T).sum() > 0.5 * cruise
