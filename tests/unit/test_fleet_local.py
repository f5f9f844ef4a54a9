"""A small fleet in one process (fleet.local.run_local) in the warehouse with floor markers: every drone's keyframes
in the merged frame (the server's final poses, no alignment) against the truth.

With a survey of the markers (1 cm per axis, drawn once) the issue's bound holds for every drone: < 10 cm. Before
the keyframe edges fused the wheel odometry (fixed 3 cm edges on a scan match that slides along the aisles) the
same flights gave 12-28 cm over 3 minutes with five drones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam2d.fleet.drone import DroneConfig
from slam2d.fleet.joint import JointConfig
from slam2d.fleet.local import merged_ate, run_local
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator
from slam2d.sim.warehouse import WarehouseConfig

DRONES = 3
MINUTES = 2.0


def _fleet_ate(db: Path, surveyed: bool) -> list[float]:
    joint = JointConfig()
    if surveyed:
        world = Simulator(ScenarioConfig(name="warehouse", warehouse=WarehouseConfig(floor_markers=True))).world
        joint = JointConfig(surveyed_markers=world.marker_survey(0.01, np.random.default_rng([0, 17])))
    run = run_local(db, DRONES, DroneConfig(minutes=MINUTES, seed=0, floor_markers=True), joint)
    try:
        out = []
        for d in run.drones:
            r = d.result()
            out.append(merged_ate(r.truth, run.server.joint.drone_poses(d.drone)[: len(r.truth)]))
        return out
    finally:
        run.server.close()


@pytest.mark.parametrize(("surveyed", "bound_m"), [(True, 0.10), (False, 0.5)])
def test_every_drone_in_the_merged_frame(tmp_path: Path, surveyed: bool, bound_m: float) -> None:
    """Surveyed markers: every drone < 10 cm (the issue's bound; measured 3.5-3.7 cm, the old edges 10-35 cm).
    Markers placed by the drones alone (nothing absolute but the docks): < 50 cm (measured 10-35 cm, the old
    edges 1.4-2.3 m)."""
    ate = _fleet_ate(tmp_path / "f.db", surveyed)
    assert len(ate) == DRONES and all(np.isfinite(ate))
    assert max(ate) < bound_m, ate
