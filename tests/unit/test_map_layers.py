"""Static and dynamic map layers (slam2d.maps.layers) and the lidar estimator's lifelong mode."""

from __future__ import annotations

import numpy as np
import pytest

from slam2d.config import with_overrides
from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig, scan_points
from slam2d.log import Scan
from slam2d.maps.layers import DYNAMIC, STATIC, LayersConfig, MapLayers
from slam2d.models.lidar import cast_rays
from slam2d.sim import ScenarioConfig, Simulator
from slam2d.sim.warehouse import boxes_to_segments
from slam2d.sim.world import box_walls, segment_distances

ANGLES = np.linspace(-np.pi, np.pi, 360, endpoint=False)
ROOM = np.vstack([box_walls(0.0, 0.0, 12.0, 9.0), [[3.0, 6.0, 7.0, 6.0]], boxes_to_segments(np.array([[9.0, 2.0]]),
                                                                                                (0.4, 0.4))])
POSES = [np.array([2.0 + 0.1 * k, 3.0, 0.05 * k]) for k in range(8)]


def scan_at(pose: np.ndarray, segments: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    r = cast_rays(pose, ANGLES, segments, 20.0) + rng.normal(0.0, 0.01, len(ANGLES))
    return scan_points(Scan(r, ANGLES, 20.0), 0.05, 19.9)


def mapped_room(rng: np.random.Generator, seconds: float = 8.0) -> tuple[MapLayers, float]:
    """Layers after ``seconds`` of 10 Hz scans of the room from a few nearby poses."""
    lay = MapLayers()
    t = 0.0
    for k in range(int(seconds * 10)):
        pose = POSES[k % len(POSES)]
        pts = scan_at(pose, ROOM, rng)
        lay.integrate(pose, pts, lay.classify(pose, pts), t, bootstrap=k == 0)
        t += 0.1
    lay.refresh_field()
    return lay, t


def wall_cells(lay: MapLayers) -> np.ndarray:
    """Static cells of the layer whose centres lie within 0.1 m of a room wall."""
    cells = lay.static_cells()
    d = segment_distances_min(lay.cell_centres(cells), ROOM)
    return cells[d < 0.1]


def segment_distances_min(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(P,) distance of each point (P,2) to the nearest segment (S,4) (inf without segments)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return segment_distances(p, segments).min(axis=1) if len(segments) else np.full(len(p), np.inf)


def test_many_point_distances_match_one_point_at_a_time() -> None:
    rng = np.random.default_rng(9)
    pts = rng.uniform(-1, 13, (50, 2))
    np.testing.assert_allclose(segment_distances(pts, ROOM), [segment_distances(p, ROOM) for p in pts])


def test_static_layer_is_the_room_and_match_recovers_an_offset() -> None:
    rng = np.random.default_rng(0)
    lay, _ = mapped_room(rng)
    pts = lay.static_points()
    d = segment_distances_min(pts, ROOM)
    assert len(pts) > 300 and np.all(d < 0.1)  # every static cell is on a wall (within one cell)
    pose = np.array([5.0, 2.5, 0.3])
    scan = scan_at(pose, ROOM, rng)
    m = lay.match(scan, pose + np.array([0.15, -0.1, 0.04]))
    assert m.constrained and m.inliers > 0.8 * len(scan)
    # from 18 cm / 2.3 deg off to ~1 cm: the guess is also a prior (sigma 3 cm), which keeps a little of the offset
    assert np.hypot(*(m.pose[:2] - pose[:2])) < 0.02 and abs(m.pose[2] - pose[2]) < 0.003


def test_new_object_is_dynamic_decays_and_never_enters_the_static_layer() -> None:
    rng = np.random.default_rng(1)
    lay, t = mapped_room(rng)
    static_before = lay.static.copy()
    box = boxes_to_segments(np.array([[6.0, 3.0]]), (1.0, 0.6))  # a forklift-sized box on known-free floor
    pose = POSES[0]
    for _ in range(10):  # seen for 1 s: shorter than persist_s
        pts = scan_at(pose, np.vstack([ROOM, box]), rng)
        lab = lay.classify(pose, pts)
        on_box = segment_distances_min(se2.transform_points(pose, pts), box) < 0.05
        assert on_box.sum() >= 5 and np.all(lab[on_box] == DYNAMIC)
        assert np.mean(lab[~on_box] == STATIC) > 0.95
        lay.integrate(pose, pts, lab, t)
        t += 0.1
    lay.refresh_field()
    assert not np.any(static_before & ~lay.static), "nothing of the room lost"
    assert np.all(segment_distances_min(lay.static_points(), box) > 0.1), "nothing of the box in the static layer"
    occ = lay.dynamic_occupancy(t)  # 0.1 s after the last scan
    box_cells, _ = lay.cell_index(se2.transform_points(pose, pts[lab == DYNAMIC]))
    np.testing.assert_allclose(occ.ravel()[box_cells], np.exp(-0.1 / lay.config.dynamic_decay_s), rtol=1e-4)
    # decay: exp(-age / tau) exactly, and gone after a few time constants (nothing seen since)
    tau = lay.config.dynamic_decay_s
    later = lay.dynamic_occupancy(t + tau)
    last = lay.dyn_seen.ravel()[box_cells]
    hit = np.isfinite(last)
    np.testing.assert_allclose(later.ravel()[box_cells][hit], np.exp(-(t + tau - last[hit]) / tau), rtol=1e-5)
    assert lay.dynamic_points(t + 4 * tau).shape == (0, 2)
    # the box leaves: beams through its cells clear the dynamic layer without waiting for the decay (every
    # second beam is traced, so a few scans from nearby poses)
    for pose in POSES[:4]:
        pts = scan_at(pose, ROOM, rng)
        lay.integrate(pose, pts, lay.classify(pose, pts), t)
    assert lay.dynamic_occupancy(t).ravel()[box_cells].max() == 0.0


def test_moved_pallet_persists_into_the_static_layer_and_leaves_it_without_touching_walls() -> None:
    rng = np.random.default_rng(2)
    lay, t = mapped_room(rng)
    walls = set(wall_cells(lay).tolist())
    pallet = boxes_to_segments(np.array([[5.0, 4.6]]), (1.2, 1.0))
    world = np.vstack([ROOM, pallet])
    pose = POSES[0]

    def pallet_static() -> int:
        cells = lay.static_cells()
        return int(np.count_nonzero(segment_distances_min(lay.cell_centres(cells), pallet) < 0.1))

    seen = []
    for k in range(int(2 * lay.config.persist_s * 10)):  # in view for twice persist_s
        pose = POSES[k % len(POSES)]
        pts = scan_at(pose, world, rng)
        lay.integrate(pose, pts, lay.classify(pose, pts), t)
        seen.append(pallet_static())
        t += 0.1
    early = seen[int(lay.config.persist_s * 10) - 3]
    assert seen[-1] > 10, "a pallet in view for twice persist_s joins the static layer"
    # cells known free before the pallet came wait persist_s; the few never seen free (its hidden corners) only
    # new_persist_s, as unexplored ground does
    assert early < 0.25 * seen[-1], "... most of it not before persist_s of sightings"
    assert walls <= set(lay.static_cells().tolist()), "no wall cell lost"
    for k in range(30):  # the pallet is taken away: seen through, it leaves the static layer
        pose = POSES[k % len(POSES)]
        pts = scan_at(pose, ROOM, rng)
        lay.integrate(pose, pts, lay.classify(pose, pts), t)
        t += 0.1
    assert pallet_static() == 0
    assert walls <= set(lay.static_cells().tolist())


def small_warehouse(moving: int, speed: float = 1.2, width: float = 30.0) -> ScenarioConfig:
    """A 30 (or ``width``) x 24 m warehouse: 2 aisles, 3 rack rows cut once, 12 pallets; the drone's lap is
    ~183 m (~110 m 24 m wide)."""
    return with_overrides(ScenarioConfig(name="warehouse-challenge"),
                          {"dt_s": 0.1, "width_m": width, "depth_m": 24.0, "aisles": 2, "cross_aisles": 1,
                           "pallets": 12, "moving_objects": moving, "speed_mps": speed})


def lifelong() -> LidarSLAM:
    return LidarSLAM(LidarSLAMConfig(layers=LayersConfig(), loop_closure=False))


def test_layer_fields_can_be_overridden_by_dotted_key() -> None:
    from slam2d.graph.lidar import LifelongLidarConfig

    cfg = with_overrides(LifelongLidarConfig(), {"layers.persist_s": "3", "layers.inlier_m": 0.2})
    assert cfg.layers is not None and cfg.layers.persist_s == 3.0 and cfg.layers.inlier_m == 0.2
    assert with_overrides(LifelongLidarConfig(), {"layers": "none", "loop_closure": "true"}).layers is None
    with pytest.raises(ValueError, match=r"LifelongLidarConfig\.layers\.persist_s must be"):
        with_overrides(LifelongLidarConfig(), {"layers.persist_s": "-1"})
    with pytest.raises(ValueError, match=r"LidarSLAMConfig\.layers is off \(None\)"):
        with_overrides(LidarSLAMConfig(), {"layers.persist_s": "3"})


def test_lifelong_needs_loop_closure_off() -> None:
    with pytest.raises(ValueError, match="loop_closure=False"):
        LidarSLAMConfig(layers=LayersConfig())
    with pytest.raises(ValueError, match="lifelong mode is off"):
        LidarSLAM().map_layers()


def test_forklift_points_are_dynamic_and_absent_from_the_static_layer() -> None:
    sim = Simulator(small_warehouse(moving=8), seed=3, record=False)
    driver = sim.driver()
    est = lifelong()
    est.reset(sim.pose, rng=np.random.default_rng(0))
    on_fork = dyn_on_fork = dyn_off_fork = off_fork = 0
    for i in range(700):
        st = sim.step(*driver.command(sim.pose, None))
        est.step(st)
        if i < 200:  # warm-up: the floor has to be seen free before anything can "appear" on it
            continue
        pts, lab = est.last_labels()
        world = se2.transform_points(sim.pose, pts)
        boxes = sim.world.segments_at(sim.time_s)[len(sim.world.walls):]
        fork = segment_distances_min(world, boxes) < 0.05
        on_fork += int(fork.sum())
        dyn_on_fork += int(np.count_nonzero(lab[fork] == DYNAMIC))
        off_fork += int((~fork).sum())
        dyn_off_fork += int(np.count_nonzero(lab[~fork] == DYNAMIC))
    est.finalize()
    e = est.estimate()
    assert np.hypot(*(e.pose[:2] - sim.pose[:2])) < 0.1
    assert on_fork > 500, "the drive must actually see forklifts"
    assert dyn_on_fork / on_fork > 0.8
    assert dyn_off_fork / off_fork < 0.02
    # static layer vs the simulator's truth: no static cell inside a forklift's box now, none off the structure
    lay = est.map_layers()
    cells = lay.static_points()
    boxes = sim.world.segments_at(sim.time_s)[len(sim.world.walls):]
    d_fork = segment_distances_min(cells, boxes)
    d_wall = segment_distances_min(cells, sim.world.walls)
    assert np.count_nonzero((d_fork < 0.1) & (d_wall > 0.2)) == 0
    assert np.count_nonzero(d_wall > 0.2) < 0.01 * len(cells)


def test_keyframes_and_memory_stay_bounded_over_laps() -> None:
    sim = Simulator(small_warehouse(moving=4, speed=4.0, width=24.0), seed=4, record=False)
    driver = sim.driver()
    est = lifelong()
    est.reset(sim.pose, rng=np.random.default_rng(0))
    counts = []
    lap = 400
    for i in range(3 * lap):
        est.step(sim.step(*driver.command(sim.pose, None)))
        if (i + 1) % lap == 0:
            s = est.layer_stats()
            counts.append((s.keyframes, s.grid_bytes))
    # the route (~110 m) takes < 400 steps at 4 m/s: the second and third 400 fly over mapped ground
    assert counts[0][0] > 15
    assert counts[2][0] - counts[1][0] <= 2 and counts[2][1] == counts[1][1]
    assert est.tracking_failures < 30
