"""The challenge-scale warehouse: validation, flights, forklift routes, floor markers, and the culled ray caster."""

import numpy as np
import pytest

from slam2d import _jacobians
from slam2d.config import with_overrides
from slam2d.log import Log
from slam2d.models.floor_markers import marker_in_robot
from slam2d.models.lidar import LidarConfig, cast_rays
from slam2d.sim import ScenarioConfig, Simulator, simulate
from slam2d.sim.raycast import cast_rays_culled
from slam2d.sim.warehouse import (
    PALLET_SIZE_M,
    WarehouseConfig,
    boxes_to_segments,
    build_warehouse,
    static_structure,
)

CHALLENGE = ScenarioConfig(name="warehouse-challenge")


def _cfg(**over):
    return with_overrides(CHALLENGE, over)


# ------------------------------------------------------------------ validation
@pytest.mark.parametrize(("over", "field"), [
    ({"aisles": 40}, "warehouse.aisles"),
    ({"pallets": 5000}, "warehouse.pallets"),
    ({"cross_aisles": 30}, "warehouse.cross_aisles"),
    ({"moving_objects": 1000}, "moving_objects"),
    ({"road_m": 1.0}, "warehouse.road_m"),
    ({"relocate_fraction": 1.5}, "warehouse.relocate_fraction"),
    ({"flight": -1}, "warehouse.flight"),
    ({"flight": 1, "pallets": 850, "relocate_fraction": 0.2}, "warehouse.relocate_fraction"),
])
def test_requests_the_layout_cannot_hold_name_the_field(over, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        _cfg(**over)


def test_small_warehouse_refuses_more_forklifts_instead_of_capping():
    with pytest.raises(ValueError, match=r"moving_objects = 20 does not fit"):
        with_overrides(ScenarioConfig(name="warehouse"), {"moving_objects": 20})
    assert len(Simulator(ScenarioConfig(name="warehouse", moving_objects=2)).world.moving) == 2
    with pytest.raises(ValueError, match="warehouse cannot be set for scenario 'room'"):
        ScenarioConfig(name="room", warehouse=WarehouseConfig(flight=1))


def test_the_error_says_how_many_fit_and_that_many_do():
    with pytest.raises(ValueError, match=r"at most (\d+) fit") as e:
        WarehouseConfig(aisles=40)
    most = int(str(e.value).rsplit("at most ", 1)[1].split()[0])
    WarehouseConfig(aisles=most)
    with pytest.raises(ValueError):
        WarehouseConfig(aisles=most + 1)
    w = WarehouseConfig()
    WarehouseConfig(pallets=w.bay_count)


def test_defaults_are_the_challenge():
    cfg = CHALLENGE.resolved()
    w = cfg.warehouse
    assert (w.width_m, w.depth_m) == (100.0, 100.0) and cfg.moving_objects == 20
    assert cfg.lidar.beams == 360 and cfg.lidar.max_range_m == 30.0 and cfg.dt_s == pytest.approx(1 / 30)
    np.testing.assert_allclose(np.diff(cfg.lidar.angles()), 2 * np.pi / 360)  # evenly all round, no duplicate
    # a lidar override keeps the rest of the preset
    short = _cfg(**{"lidar.max_range_m": 20}).resolved().lidar
    assert short.max_range_m == 20.0 and short.beams == 360
    sim = Simulator(CHALLENGE, seed=0)
    assert len(sim.world.moving) == 20 and sim.world.bounds == (0.0, 0.0, 100.0, 100.0)


# ------------------------------------------------------------------ flights
def _layout(seed, **over):
    cfg = with_overrides(CHALLENGE, over).resolved()
    from slam2d.sim import spawn_streams

    return build_warehouse(cfg.warehouse, int(cfg.moving_objects), spawn_streams(seed)["world"])


def test_world_is_deterministic_per_seed_and_flight():
    a, b = _layout(3, flight=2), _layout(3, flight=2)
    np.testing.assert_array_equal(a.world.walls, b.world.walls)
    np.testing.assert_array_equal(a.world.moving_positions(7.0), b.world.moving_positions(7.0))
    c = _layout(4, flight=2)
    assert not np.array_equal(a.occupied, c.occupied)
    # the same world through the simulator: bit-identical logs
    cfg = _cfg(flight=1, steps=20)
    assert simulate(cfg, seed=5).equals(simulate(cfg, seed=5))


def test_pallets_move_between_flights_but_racks_do_not():
    w = WarehouseConfig()
    f0, f1, f2 = (_layout(0, flight=f) for f in (0, 1, 2))
    n_struct = len(static_structure(w))
    np.testing.assert_array_equal(f0.world.walls[:n_struct], f1.world.walls[:n_struct])
    np.testing.assert_array_equal(f0.world.landmarks, f2.world.landmarks)  # uprights identical
    for prev, cur in ((f0, f1), (f1, f2)):
        assert len(cur.occupied) == w.pallets
        moved = len(np.setdiff1d(prev.occupied, cur.occupied))
        assert moved == round(w.relocate_fraction * w.pallets)
    # the pallet segments are exactly the occupied slots' boxes
    np.testing.assert_array_equal(f1.world.walls[n_struct:], boxes_to_segments(f1.slot_centres[f1.occupied],
                                                                               PALLET_SIZE_M))
    # flight 2 builds on flight 1 (a chain of days), not on flight 0 again
    assert len(np.setdiff1d(f0.occupied, f2.occupied)) > len(np.setdiff1d(f0.occupied, f1.occupied))


def _inside(points, boxes, margin=0.0):
    """(K,2) points x (R,4) boxes -> (K,) inside any box shrunk by margin."""
    p = points[:, None, :]
    return np.any((p[..., 0] > boxes[:, 0] + margin) & (p[..., 0] < boxes[:, 2] - margin)
                  & (p[..., 1] > boxes[:, 1] + margin) & (p[..., 1] < boxes[:, 3] - margin), axis=1)


def test_forklifts_stay_on_roads_and_never_enter_racks():
    w = WarehouseConfig()
    lay = _layout(1)
    racks = w.rack_footprints()
    ys, xs = w.road_centres_y(), w.cross_centres_x()
    for t in np.linspace(0.0, 600.0, 241):
        for m in lay.world.moving:
            corners = m.corners(float(t))
            edge_pts = np.vstack([corners, 0.5 * (corners + np.roll(corners, -1, axis=0)), corners.mean(axis=0)])
            assert not np.any(_inside(edge_pts, racks, margin=-0.05)), (t, corners)
            assert np.all((corners > 0) & (corners < [w.width_m, w.depth_m]))
            c = m.position(float(t))
            on_road = np.min(np.abs(ys - c[1])) < 1e-6 or np.min(np.abs(xs - c[0])) < 1e-6
            assert on_road, c
    # the drone's route also stays out of the racks (sampled along every leg)
    wp = lay.waypoints
    legs = wp[:-1, None, :] + np.linspace(0, 1, 50)[None, :, None] * (wp[1:] - wp[:-1])[:, None, :]
    assert not np.any(_inside(legs.reshape(-1, 2), racks, margin=-0.5))


# ------------------------------------------------------------------ floor markers
def test_floor_marker_readings_match_the_truth_within_noise(tmp_path):
    cfg = _cfg(floor_markers=True, steps=500, speed_mps=3.0, **{"camera.std_m": 0.02, "lidar.enabled": False})
    log = simulate(cfg, seed=2)
    assert log.marker_step is not None and log.true_markers is not None
    assert log.marker_xy_m is not None and log.marker_id is not None
    assert len(np.unique(log.marker_id)) >= 4
    pred = marker_in_robot(log.true_poses[log.marker_step], log.true_markers[log.marker_id])
    err = log.marker_xy_m - pred
    assert abs(err.std() - 0.02) < 0.003 and np.abs(err.mean(axis=0)).max() < 0.004
    # every marker inside the footprint was read, none outside
    d = np.hypot(*(log.true_poses[1:, None, :2] - log.true_markers[None]).transpose(2, 0, 1))  # (T, M)
    expect = np.argwhere(d <= 1.0)
    got = np.stack([log.marker_step - 1, log.marker_id], axis=-1)
    assert {tuple(r) for r in expect} == {tuple(r) for r in got}
    # the readings travel with the log: steps, round trip, head
    s = next(st for st in log if st.markers is not None and len(st.markers))
    assert s.markers is not None and np.all(np.isin(s.markers.ids, log.marker_id[log.marker_step == s.index]))
    back = Log.load(log.save(tmp_path / "m.npz"))
    assert back.equals(log)
    head = log.head(100)
    assert head.marker_step is not None and np.all(head.marker_step <= 100)
    assert simulate("warehouse-challenge", seed=2, steps=5).marker_step is None  # markers are optional


def test_floor_marker_jacobian_is_registered():
    assert any(p.name.endswith("marker_in_robot") for p in _jacobians.REGISTRY)


# ------------------------------------------------------------------ ray caster
def test_culled_caster_is_bit_identical_to_the_dense_one():
    rng = np.random.default_rng(0)
    lay = _layout(0)
    lidar = CHALLENGE.resolved().lidar
    for _ in range(8):
        pose = np.array([*rng.uniform(1, 99, 2), rng.uniform(-np.pi, np.pi)])
        segs = lay.world.segments_near(3.0, pose[:2], 30.0)
        np.testing.assert_array_equal(cast_rays_culled(pose, lidar.angles(), segs, 30.0),
                                      cast_rays(pose, lidar.angles(), segs, 30.0))
    # random segment soups, several beam layouts (half turn, odd fov, full turn with a duplicate beam), poses on a
    # segment's line and on an endpoint
    soup = rng.uniform(-10, 10, size=(300, 4))
    for cfg in (LidarConfig(), LidarConfig(beams=100, fov_rad=3.0), LidarConfig(beams=64, fov_rad=2 * np.pi),
                LidarConfig(beams=360, fov_rad=2 * np.pi * 359 / 360)):
        poses = [np.array([*rng.uniform(-5, 5, 2), rng.uniform(-4, 4)]) for _ in range(30)]
        poses += [np.array([*soup[0, :2], 0.3]), np.array([*(0.5 * (soup[1, :2] + soup[1, 2:])), -2.0])]
        for pose in poses:
            np.testing.assert_array_equal(cast_rays_culled(pose, cfg.angles(), soup, 12.0),
                                          cast_rays(pose, cfg.angles(), soup, 12.0))
    uneven = np.sort(rng.uniform(-1, 1, 50))  # not evenly spaced: falls back to the dense caster
    np.testing.assert_array_equal(cast_rays_culled(np.zeros(3), uneven, soup, 12.0),
                                  cast_rays(np.zeros(3), uneven, soup, 12.0))


def test_range_cull_drops_only_segments_the_lidar_cannot_reach():
    lay = _layout(0)
    xy = np.array([30.0, 40.0])
    near = lay.world.segments_near(2.0, xy, 30.0)
    full = lay.world.segments_at(2.0)
    assert 0 < len(near) < 0.6 * len(full)
    for heading in np.linspace(-3, 3, 7):
        pose = np.array([*xy, heading])
        a = np.linspace(-np.pi, np.pi, 90)
        np.testing.assert_array_equal(cast_rays(pose, a, near, 30.0), cast_rays(pose, a, full, 30.0))


def test_fleet_is_placed_in_one_pass_exactly_as_object_by_object():
    lay = _layout(2)
    n_walls = len(lay.world.walls)
    for t in (0.0, 1.7, 33.3, 1234.5):
        per_object = np.vstack([m.segments(t) for m in lay.world.moving])
        np.testing.assert_allclose(lay.world.segments_at(t)[n_walls:], per_object, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(lay.world.moving_positions(t),
                                      np.array([m.position(t) for m in lay.world.moving]))


def test_a_forklift_under_the_drone_is_flown_over_not_scanned_from_inside():
    lay = _layout(0)
    m = lay.world.moving[0]
    t = 12.0
    centre = m.position(t)
    near = lay.world.segments_near(t, centre + 0.1, 30.0)
    own = m.segments(t)
    assert not any(np.allclose(own[0], s, atol=1e-9) for s in near)
    # from 3 m away it is an obstacle like any other
    _, d = lay.world._fleet_state(t)
    side = centre + 3.0 * np.array([-d[0, 1], d[0, 0]])
    near = lay.world.segments_near(t, side, 30.0)
    assert sum(any(np.allclose(o, s, atol=1e-9) for s in near) for o in own) == 4


def test_marker_model_agrees_with_the_se2_inverse_transform():
    from slam2d.geometry import se2

    rng = np.random.default_rng(4)
    pose = np.column_stack([rng.normal(size=(50, 2)) * 10, rng.uniform(-np.pi, np.pi, 50)])
    pts = rng.normal(size=(50, 2)) * 10
    np.testing.assert_allclose(marker_in_robot(pose, pts), se2.inverse_transform_points(pose, pts), atol=1e-12)


def test_the_lidar_sees_the_moved_pallets_and_nothing_else_changes():
    f0, f1 = _layout(6, flight=0), _layout(6, flight=1)
    w = WarehouseConfig()
    moved = np.setxor1d(f0.occupied, f1.occupied)
    moved_boxes = boxes_to_segments(f0.slot_centres[moved], PALLET_SIZE_M)
    lidar = CHALLENGE.resolved().lidar
    changed_beams = 0
    for y in w.aisle_centres_y()[::2]:
        for x in np.arange(6.0, 95.0, 16.0):
            pose = np.array([x, y, 0.3])
            r0 = cast_rays_culled(pose, lidar.angles(), f0.world.walls, 30.0)
            r1 = cast_rays_culled(pose, lidar.angles(), f1.world.walls, 30.0)
            diff = np.flatnonzero(r0 != r1)
            changed_beams += len(diff)
            if len(diff):
                # every changed beam ends on a moved pallet in one of the two flights
                r_pallet = cast_rays(pose, lidar.angles()[diff], moved_boxes, 30.0)
                assert np.all(np.isclose(r_pallet, np.minimum(r0[diff], r1[diff]), atol=1e-9))
    assert changed_beams > 30  # pallets are visible from the aisles


def test_a_streaming_simulator_yields_the_same_steps_and_keeps_no_log():
    cfg = _cfg(floor_markers=True, steps=40).resolved()
    log = simulate(cfg, seed=3)
    live = Simulator(cfg, seed=3, record=False)
    driver = live.driver()
    for t in range(1, 41):
        v, w = driver.command(live.pose, None)
        s = live.step(v, w)
        ref = log.step(t)
        np.testing.assert_array_equal(s.odometry, ref.odometry)
        assert s.scan is not None and ref.scan is not None
        np.testing.assert_array_equal(s.scan.ranges_m, ref.scan.ranges_m)
        assert s.markers is not None and ref.markers is not None
        np.testing.assert_array_equal(s.markers.ids, ref.markers.ids)
    assert live.record is False and live._rec["scan"] == []
    with pytest.raises(ValueError, match="record=False"):
        live.to_log()


def test_a_marker_survey_is_the_truth_off_by_its_sigma_and_repeats_per_generator():
    world = Simulator(_cfg(floor_markers=True)).world
    a = world.marker_survey(0.01, np.random.default_rng(3))
    assert [r[0] for r in a] == list(range(len(world.floor_markers))) and len(a) >= 4
    err = np.array([r[1:] for r in a]) - world.floor_markers
    assert 0.005 < err.std() < 0.02
    again, other = (world.marker_survey(0.01, np.random.default_rng(s)) for s in (3, 4))
    assert a == again != other
    assert Simulator(_cfg()).world.marker_survey(0.01, np.random.default_rng(0)) == ()
