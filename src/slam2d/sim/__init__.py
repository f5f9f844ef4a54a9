"""Deterministic simulator: worlds, scenarios, drivers, and ``simulate(scenario, seed) -> Log``."""

from slam2d.sim.scenarios import SCENARIOS as SCENARIOS
from slam2d.sim.scenarios import Layout as Layout
from slam2d.sim.scenarios import ScenarioConfig as ScenarioConfig
from slam2d.sim.scenarios import ScenarioSpec as ScenarioSpec
from slam2d.sim.scenarios import register_scenario as register_scenario
from slam2d.sim.simulator import STREAMS as STREAMS
from slam2d.sim.simulator import Simulator as Simulator
from slam2d.sim.simulator import simulate as simulate
from slam2d.sim.simulator import spawn_streams as spawn_streams
from slam2d.sim.trajectory import AutoExplorer as AutoExplorer
from slam2d.sim.trajectory import ManualDriver as ManualDriver
from slam2d.sim.trajectory import WaypointFollower as WaypointFollower
from slam2d.sim.warehouse import WarehouseConfig as WarehouseConfig
from slam2d.sim.world import MovingObject as MovingObject
from slam2d.sim.world import World as World
