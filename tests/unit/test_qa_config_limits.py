"""QA pass on scenario and estimator config limits: values that used to run out of memory, hang or silently do
nothing are refused up front, naming the field (the memory estimate covers the layouts, not only the log)."""

from __future__ import annotations

import pytest

from slam2d.cli.main import main
from slam2d.config import with_overrides
from slam2d.filters.fastslam import FastSLAMConfig
from slam2d.graph.lidar_config import LidarSLAMConfig
from slam2d.models.lidar import LidarConfig
from slam2d.sim.scenarios import ScenarioConfig, estimate_memory_bytes
from slam2d.sim.warehouse import WarehouseConfig


@pytest.fixture(autouse=True)
def _default_memory_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SLAM2D_MAX_MEMORY_MB", raising=False)


@pytest.mark.parametrize(("scenario", "overrides", "mention"), [
    # the room's rejection sampling needed ~850 B per landmark: 1e7 landmarks ran out of memory after 40 s
    ("room", {"landmarks": 10_000_000}, "landmarks=10000000"),
    # 1e6 m of racks: ~1e7 uprights and 4e7 wall segments, out of memory while building
    ("warehouse-challenge", {"warehouse.width_m": 1e6}, "warehouse.width_m"),
    # the floor markers' pairwise duplicate check is M x M
    ("warehouse-challenge", {"warehouse.floor_markers": True, "warehouse.marker_spacing_m": 0.01},
     "warehouse.marker_spacing_m"),
    ("warehouse", {"warehouse.floor_markers": True, "warehouse.marker_spacing_m": 1e-6}, "warehouse.marker_spacing_m"),
    # ~330-560 B per beam per scan, not 64
    ("room", {"steps": 3, "lidar.beams": 10_000_000}, "lidar.beams"),
])
def test_layouts_over_the_memory_limit_are_refused_before_building(scenario, overrides, mention):
    with pytest.raises(ValueError, match="SLAM2D_MAX_MEMORY_MB") as info:
        with_overrides(ScenarioConfig(name=scenario), overrides)
    assert mention in str(info.value)


def test_the_default_scenarios_stay_far_below_the_limit():
    from slam2d.sim.scenarios import SCENARIOS

    for name in SCENARIOS:
        total, step = estimate_memory_bytes(ScenarioConfig(name=name).resolved())
        assert max(total, step) < 64 * 2**20, name
    markers = with_overrides(ScenarioConfig(name="warehouse-challenge"), {"warehouse.floor_markers": True})
    assert max(estimate_memory_bytes(markers)) < 64 * 2**20


def test_a_huge_flight_is_refused_instead_of_replaying_for_hours():
    with pytest.raises(ValueError, match=r"WarehouseConfig\.flight must be <= 10000"):
        WarehouseConfig(flight=1_000_000_000)
    assert WarehouseConfig(flight=10_000).flight == 10_000


@pytest.mark.parametrize("fov", [7.0, 1e9])
def test_lidar_field_of_view_past_a_full_turn_is_refused(fov):
    with pytest.raises(ValueError, match=r"LidarConfig\.fov_rad must be <= 2\*pi"):
        LidarConfig(fov_rad=fov)
    LidarConfig(fov_rad=2 * 3.141592653589793)  # a full turn is fine


@pytest.mark.parametrize(("value", "message"), [
    (float("nan"), r"min_range_m must be a number in \[0"),
    (-1.0, r"min_range_m must be a number in \[0"),
    (25.0, r"min_range_m must be < max_range_m"),
    (30.0, r"min_range_m must be < max_range_m"),
])
def test_lidar_slam_min_range_that_drops_every_beam_is_refused(value, message):
    """min_range_m NaN or >= max_range_m matched no beam at all: the run was dead reckoning under lidar's name."""
    with pytest.raises(ValueError, match=r"LidarSLAMConfig\." + message):
        LidarSLAMConfig(min_range_m=value)


def test_fastslam_initial_capacity_over_the_memory_limit_is_refused():
    with pytest.raises(ValueError, match=r"initial_capacity=1000000000.*SLAM2D_MAX_MEMORY_MB"):
        FastSLAMConfig(initial_capacity=1_000_000_000)
    assert FastSLAMConfig(particles=10_000, initial_capacity=64).initial_capacity == 64


def test_cli_names_the_field_before_simulating(capsys, tmp_path):
    """``run --set estimator.initial_capacity=1e9`` said only "out of memory" after simulating."""
    assert main(["run", "--estimator", "fastslam", "--set", "steps=3",
                 "--set", "estimator.initial_capacity=1000000000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slam2d run: error: ") and "initial_capacity" in err[0], err
    assert main(["simulate", "--out", str(tmp_path / "s.npz"), "--scenario", "warehouse-challenge",
                 "--set", "warehouse.flight=1000000000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warehouse.flight" in err[0], err
