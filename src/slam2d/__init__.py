"""slam2d: classical 2D SLAM — simulator, EKF-SLAM, FastSLAM, graph SLAM, and an interactive lab.

The root package is lazy: ``import slam2d.geometry`` loads nothing above geometry, and ``slam2d.run`` imports the
runner (and what it needs) only when first used.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: public name -> module that defines it
_EXPORTS = {
    "ate": "slam2d.eval.trajectory",
    "rpe": "slam2d.eval.trajectory",
    "Estimate": "slam2d.estimator",
    "Estimator": "slam2d.estimator",
    "EstimatorStateError": "slam2d.estimator",
    "CapabilityError": "slam2d.estimator",
    "DeadReckoning": "slam2d.filters.dead_reckoning",
    "DeadReckoningConfig": "slam2d.filters.dead_reckoning",
    "estimator_names": "slam2d.lab.registry",
    "make_estimator": "slam2d.lab.registry",
    "RunResult": "slam2d.lab.runner",
    "run": "slam2d.lab.runner",
    "run_named": "slam2d.lab.runner",
    "Log": "slam2d.log",
    "LogFormatError": "slam2d.log",
    "Observations": "slam2d.log",
    "Step": "slam2d.log",
    "SCENARIOS": "slam2d.sim.scenarios",
    "ScenarioConfig": "slam2d.sim.scenarios",
    "Simulator": "slam2d.sim.simulator",
    "simulate": "slam2d.sim.simulator",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'slam2d' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # for type checkers and IDEs: the same names, imported eagerly
    from slam2d.estimator import CapabilityError as CapabilityError
    from slam2d.estimator import Estimate as Estimate
    from slam2d.estimator import Estimator as Estimator
    from slam2d.estimator import EstimatorStateError as EstimatorStateError
    from slam2d.eval.trajectory import ate as ate
    from slam2d.eval.trajectory import rpe as rpe
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
