"""The joint graph merges two drones in one process: drone A reports its true keyframe poses, drone B flies the
same route with a heading bias of 2 mrad per metre in its chain; the inter-robot loops the server finds from the compact
point sets alone pull B's merged trajectory back onto the truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slam2d.fleet import joint
from slam2d.fleet.drone import start_pose
from slam2d.fleet.joint import JointGraph
from slam2d.fleet.protocol import Edge, Keyframe, info_upper, pack_descriptor, pack_points, unpack_points
from slam2d.geometry import se2
from slam2d.graph.factors import between_error
from slam2d.graph.lidar import scan_points
from slam2d.maps.store import range_histogram
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator


def fly(seed: int, seconds: float) -> tuple[np.ndarray, list[bytes], list[bytes]]:
    """True keyframe poses (one per metre), packed scan points and descriptors of a drone on drone 0's route."""
    sim = Simulator(ScenarioConfig(name="warehouse"), seed=seed, record=False)
    pose, wp = start_pose(sim, 0)
    sim.pose, sim.waypoints = pose.copy(), wp
    driver = sim.driver()
    poses, pts, desc = [], [], []
    last = None
    while sim.time_s < seconds:
        s = sim.step(*driver.command(sim.pose, sim.world.solid_segments(sim.time_s)))
        if s.scan is None or (last is not None and np.hypot(*(sim.pose[:2] - last[:2])) < 1.0):
            continue
        last = sim.pose.copy()
        poses.append(last)
        pts.append(pack_points(scan_points(s.scan, 0.05, 25.0)))
        desc.append(pack_descriptor(range_histogram(s.scan.ranges_m, s.scan.max_range_m)))
    return np.asarray(poses), pts, desc


def chain(reported: np.ndarray) -> list[Edge]:
    info = np.asarray(info_upper(np.diag(np.array([0.03, 0.03, 0.01]) ** -2)))
    return [Edge(k - 1, k, se2.between(reported[k - 1], reported[k]), info) for k in range(1, len(reported))]


def biased(truth: np.ndarray, bias_rad_per_kf: float) -> np.ndarray:
    """What a front end with a gyro bias reports: the true increments, each turned ``bias`` too far."""
    inc = se2.between(truth[:-1], truth[1:])
    inc[:, 2] += bias_rad_per_kf
    return se2.compose_chain(truth[0], inc)


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_joint_graph_merges_two_drones() -> None:
    """A turns 2 mrad per metre too far, B 2 mrad too little: each alone drifts by metres; the merged graph, tied by
    the inter-robot loops it found, cancels the biases against each other."""
    truth_a, pts_a, desc_a = fly(1, 60.0)
    truth_b, pts_b, desc_b = fly(2, 60.0)
    rep_a, rep_b = biased(truth_a, 0.002), biased(truth_b, -0.002)
    alone_a, alone_b = rms(rep_a, truth_a), rms(rep_b, truth_b)
    assert min(alone_a, alone_b) > 0.3  # the error the merge has to remove

    g = JointGraph()
    g.add_drone(0, truth_a[0])
    g.add_drone(1, truth_b[0])
    edges_a, edges_b = chain(rep_a), chain(rep_b)
    loops = []
    for lo in range(0, max(len(truth_a), len(truth_b)), 5):  # deltas of five keyframes, the drones in turn
        for d, rep, pts, desc, edges in ((0, rep_a, pts_a, desc_a, edges_a), (1, rep_b, pts_b, desc_b, edges_b)):
            hi = min(lo + 5, len(rep))
            kfs = [Keyframe(k, float(k), rep[k], desc[k], pts[k]) for k in range(lo, hi)]
            new = g.add_keyframes(d, kfs, [e for e in edges if lo <= e.b < hi])
            for lp in g.search_loops(new, float(lo)):
                loops.append(lp)
                g.add_loop(lp)
            if g.needs_solve():
                g.solve()
    g.solve(20)
    assert len(loops) >= 5
    assert all({lp.drone_a, lp.drone_b} == {0, 1} for lp in loops)
    truth = {0: truth_a, 1: truth_b}
    for lp in loops:  # every loop agrees with the truth within its own uncertainty, as the graph's factor measures
        # it (a sliding loop leaves its axis free: its error along the aisle may be large, its information there small)
        e = between_error(truth[lp.drone_a][lp.a], truth[lp.drone_b][lp.b], lp.z)
        assert float(e @ lp.info @ e) < 16.27, (e, np.linalg.eigvalsh(lp.info))
    merged_a, merged_b = rms(g.drone_poses(0), truth_a), rms(g.drone_poses(1), truth_b)
    assert merged_a < 0.5 * alone_a, (alone_a, merged_a)
    assert merged_b < 0.5 * alone_b, (alone_b, merged_b)


def test_an_inter_robot_loop_weighs_a_displacement_in_the_old_frame_as_its_icp_covariance_after_a_turn(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Drone 1 sees what drone 0 saw at keyframe 12, from the same place turned 0.8 rad (the search allows up to
    1 rad). ICP's covariance, made long along drone 0's x, is over x, y in drone 0's keyframe frame; the between
    factor's error is in drone 1's. Turned into that frame, a 3 cm slip along drone 0's x weighs as loosely as the
    covariance says; unturned, it weighed as a mix with the sure direction across."""
    cov = np.diag([0.04**2, 0.002**2, 0.001**2])
    real_icp = joint.icp
    monkeypatch.setattr(joint, "icp", lambda *a, **k: replace(real_icp(*a, **k), covariance=cov))
    truth, pts, desc = fly(1, 20.0)
    k, turn = 12, 0.8
    g = JointGraph()
    g.add_drone(0, truth[0])
    g.add_keyframes(0, [Keyframe(i, float(i), truth[i], desc[i], pts[i]) for i in range(len(truth))],
                    chain(truth))
    seen = se2.inverse_transform_points(np.array([0.0, 0.0, turn]), unpack_points(pts[k]))
    pose = se2.compose(truth[k], np.array([0.0, 0.0, turn]))
    g.add_drone(1, pose)
    new = g.add_keyframes(1, [Keyframe(0, 100.0, pose, desc[k], pack_points(seen))], [])
    loops = g.search_loops(new, 100.0)
    assert loops, "the loop was not found"
    lidar = g.lidar
    floor = np.array([lidar.min_sigma_xy_m, lidar.min_sigma_xy_m]) ** 2
    for lp in loops:
        assert abs(lp.z[2] - turn) < 0.05
        along = between_error(np.zeros(3), lp.z + [0.03, 0.0, 0.0], lp.z)
        across = between_error(np.zeros(3), lp.z + [0.0, 0.03, 0.0], lp.z)
        assert along @ lp.info @ along <= 0.03**2 / (cov[0, 0] + floor[0]) * (1 + 1e-9)  # loose (free if sliding)
        assert across @ lp.info @ across == pytest.approx(0.03**2 / (cov[1, 1] + floor[1]), rel=1e-9)
