"""slam2d: classical 2D SLAM — simulator, EKF-SLAM, FastSLAM, graph SLAM, and an interactive lab."""

from slam2d.eval.trajectory import ate as ate
from slam2d.eval.trajectory import rpe as rpe
from slam2d.filters.base import Estimate as Estimate
from slam2d.filters.base import Estimator as Estimator
from slam2d.filters.dead_reckoning import DeadReckoning as DeadReckoning
from slam2d.filters.dead_reckoning import DeadReckoningConfig as DeadReckoningConfig
from slam2d.lab.registry import estimator_names as estimator_names
from slam2d.lab.registry import make_estimator as make_estimator
from slam2d.lab.runner import RunResult as RunResult
from slam2d.lab.runner import run as run
from slam2d.lab.runner import run_named as run_named
from slam2d.log import Log as Log
from slam2d.log import LogFormatError as LogFormatError
from slam2d.log import Observations as Observations
from slam2d.log import Step as Step
from slam2d.sim.scenarios import SCENARIOS as SCENARIOS
from slam2d.sim.scenarios import ScenarioConfig as ScenarioConfig
from slam2d.sim.simulator import Simulator as Simulator
from slam2d.sim.simulator import simulate as simulate

__all__ = [
    "SCENARIOS", "DeadReckoning", "DeadReckoningConfig", "Estimate", "Estimator", "Log", "LogFormatError",
    "Observations", "RunResult", "ScenarioConfig", "Simulator", "Step", "ate", "estimator_names", "make_estimator",
    "rpe", "run", "run_named", "simulate",
]
