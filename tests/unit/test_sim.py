import numpy as np
import pytest

from slam2d import Log, LogFormatError, ScenarioConfig, Simulator, simulate
from slam2d.config import with_overrides
from slam2d.log import DYNAMIC_ID
from slam2d.sim import SCENARIOS


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_same_seed_is_bit_identical_and_other_seed_differs(name):
    a = simulate(name, seed=5, steps=60)
    b = simulate(name, seed=5, steps=60)
    c = simulate(name, seed=6, steps=60)
    assert a.equals(b)
    assert not a.equals(c)


def test_adding_a_sensor_does_not_change_the_motion_noise():
    base = simulate("room", seed=2, steps=80)
    more = simulate(ScenarioConfig(name="room", gps_every=5, sensor=ScenarioConfig().sensor.__class__(
        clutter_rate=2.0, descriptor_dim=4)), seed=2, steps=80)
    np.testing.assert_array_equal(base.odometry, more.odometry)
    np.testing.assert_array_equal(base.true_poses, more.true_poses)
    assert more.gps_xy is not None and len(more.gps_xy) == 16
    assert more.obs_descriptor is not None and more.obs_descriptor.shape[1] == 4


def test_scenario_shapes():
    room = simulate("room", seed=0)
    assert len(room.true_landmarks) == 30
    loop = simulate("loop", seed=0)
    start, end = loop.true_poses[0, :2], loop.true_poses[-1, :2]
    path = np.sum(np.hypot(*np.diff(loop.true_poses[:, :2], axis=0).T))
    assert 190 < path < 260  # one full lap of the ~200 m corridor plus overlap
    # the loop returns: some late pose is within 2 m of the start
    assert np.min(np.hypot(*(loop.true_poses[300:, :2] - start).T)) < 2.0
    assert not np.allclose(start, end)
    wh = simulate("warehouse", seed=0)
    assert np.any(wh.obs_id == DYNAMIC_ID)
    assert wh.dynamic_xy is not None and wh.dynamic_xy.shape[1] == 3
    g = simulate("grid", seed=0, landmarks=400, steps=20)
    assert len(g.true_landmarks) == 400


def test_scan_present_where_walls_exist():
    room = simulate("room", seed=0, steps=10)
    assert room.scan_ranges_m is not None and room.scan_ranges_m.shape == (10, 181)
    assert np.all(room.scan_ranges_m <= room.scan_max_range_m)
    assert simulate("grid", seed=0, steps=10).scan_ranges_m is None


def test_observations_are_consistent_with_truth():
    log = simulate("room", seed=1, steps=100)
    from slam2d.geometry import angle_diff
    from slam2d.models import range_bearing

    lm = log.true_landmarks
    idx = log.obs_id >= 0
    pred = range_bearing(log.true_poses[log.obs_step[idx]], lm[log.obs_id[idx]])
    err_r = log.obs_range_m[idx] - pred[:, 0]
    err_b = angle_diff(log.obs_bearing_rad[idx], pred[:, 1])
    assert abs(err_r.std() - 0.1) < 0.01 and abs(err_b.std() - 0.02) < 0.002


def test_log_round_trip_and_step_access(tmp_path):
    log = simulate("warehouse", seed=3, steps=40, gps_every=4)
    path = log.save(tmp_path / "w.npz")
    back = Log.load(path)
    assert back.equals(log)
    s = back.step(7)
    assert s.index == 7 and s.gps is None and back.step(8).gps is not None
    np.testing.assert_array_equal(s.odometry, log.odometry[6])
    assert len(s.observations) == int(np.sum(log.obs_step == 7))
    assert s.scan is not None and s.scan.ranges_m.shape == (181,)
    assert sum(len(st.observations) for st in back) == len(log.obs_step)
    head = log.head(10)
    assert head.num_steps == 10 and head.true_poses.shape == (11, 3)


def test_corrupt_and_truncated_logs_give_one_line_errors(tmp_path):
    path = simulate("room", seed=0, steps=20).save(tmp_path / "r.npz")
    data = path.read_bytes()
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogFormatError, match="trunc.npz"):
        Log.load(trunc)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"hello")
    with pytest.raises(LogFormatError, match="junk.npz.*not a slam2d log"):
        Log.load(junk)
    with pytest.raises(LogFormatError, match="no such file"):
        Log.load(tmp_path / "missing.npz")
    # bit flips inside the archive are caught too (zip CRC)
    flipped = bytearray(data)
    flipped[200] ^= 0xFF
    bad = tmp_path / "flip.npz"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(LogFormatError, match="flip.npz"):
        Log.load(bad)


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*room"):
        ScenarioConfig(name="nope")
    with pytest.raises(ValueError, match="sensor.range_std_m"):
        with_overrides(ScenarioConfig(), {"sensor.range_std_m": "-1"})
    with pytest.raises(ValueError, match="steps"):
        with_overrides(ScenarioConfig(), {"steps": "0"})
    with pytest.raises(ValueError, match="unknown key 'bogus'"):
        with_overrides(ScenarioConfig(), {"bogus": 1})
    with pytest.raises(ValueError, match="landmarks cannot be set"):
        ScenarioConfig(name="warehouse", landmarks=5)
    cfg = with_overrides(ScenarioConfig(name="grid"), {"landmarks": "1000", "sensor.max_range_m": "5"})
    assert cfg.landmarks == 1000 and cfg.sensor.max_range_m == 5.0


def test_live_simulator_steps_with_commands():
    sim = Simulator(ScenarioConfig(name="room"), seed=0)
    p0 = sim.pose.copy()
    for _ in range(10):
        sim.step(1.0, 0.0)
    assert sim.pose[0] == pytest.approx(p0[0] + 10 * 0.2)
    log = sim.to_log()
    assert log.num_steps == 10
