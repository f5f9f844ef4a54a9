"""Runner, estimator registry, experiments and sweeps."""

from slam2d.lab.registry import ESTIMATORS as ESTIMATORS
from slam2d.lab.registry import estimator_names as estimator_names
from slam2d.lab.registry import make_config as make_config
from slam2d.lab.registry import make_estimator as make_estimator
from slam2d.lab.registry import register_estimator as register_estimator
from slam2d.lab.runner import RunResult as RunResult
from slam2d.lab.runner import run as run
from slam2d.lab.runner import run_named as run_named
from slam2d.lab.runner import score as score
