"""What the library offers right now: the lab asks here instead of assuming a back end exists.

Optional modules are imported lazily and only when a page needs them, so the lab runs on any subset of the
library and each page says plainly what is missing ("not available yet: ...") instead of pretending.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from slam2d.lab.registry import estimator_names

#: the estimators each page would like to show, best first, with a human name for the notice
ESTIMATOR_LABELS = {
    "ekf": "EKF-SLAM (estimator 'ekf')",
    "fastslam": "FastSLAM 1.0 (estimator 'fastslam')",
    "fastslam2": "FastSLAM 2.0 (estimator 'fastslam2')",
    "graph": "graph SLAM (estimator 'graph')",
}


def has_estimator(name: str) -> bool:
    return name in estimator_names()


def optional_attr(module: str, attr: str) -> Any | None:
    """``module.attr`` if the module imports and has it, else None (never raises for a missing part)."""
    try:
        mod = importlib.import_module(module)
    except ImportError:
        return None
    return getattr(mod, attr, None)


def associate_function() -> Callable[..., Any] | None:
    """``slam2d.association.associate`` (the dispatcher over methods) once the association work has landed."""
    return optional_attr("slam2d.association", "associate")


def optional_module(module: str) -> Any | None:
    """The module if it (and everything it needs) imports, else None."""
    try:
        return importlib.import_module(module)
    except ImportError:
        return None


def module_exists(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def status() -> dict[str, Any]:
    """A summary for the index page and ``/api/status``."""
    return {
        "estimators": estimator_names(),
        "associate": associate_function() is not None,
        "ekf_augment_state": optional_attr("slam2d.filters.ekf_slam", "augment_state") is not None,
        "occupancy": module_exists("slam2d.maps.occupancy"),
        "topology": module_exists("slam2d.maps.topology"),
        "features": module_exists("slam2d.frontend.features"),
        "graph": module_exists("slam2d.graph"),
    }
