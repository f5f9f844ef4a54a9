"""One list of (function, Jacobians) pairs, checked by a single finite-difference test.

Every model function ``f`` with an analytic sibling ``f_jacobians`` is listed in :data:`PAIRS` with the kinds of
its arguments, so the test suite can sample valid inputs (including headings near 0 and +-pi) and compare the
analytic Jacobians with central differences taken through ``retract``/``local`` (see geometry/se2.py).

The list is explicit (not filled by import-time side effects), so the checked set is the same whichever modules a
test happened to import first; a test pins its size. Modules are named by string and imported only when the
registry is built, so this bottom-level module imports no other slam2d module at import time.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Argument kinds: name -> (dimension, indices of angular components).
ARG_KINDS: dict[str, tuple[int, tuple[int, ...]]] = {
    "pose": (3, (2,)),
    "point": (2, ()),
    "twist": (3, ()),
    "odometry": (3, (2,)),
    "range_bearing": (2, (1,)),
    "velocity": (2, ()),
}


@dataclass(frozen=True)
class JacobianPair:
    """A function and its analytic Jacobians (one per argument, in argument order)."""

    name: str
    function: Callable[..., Any]
    jacobians: Callable[..., tuple[Any, ...]]
    arg_kinds: tuple[str, ...]
    #: indices of output components that are angles (compared with angle_diff)
    output_angles: tuple[int, ...] = ()
    #: extra keyword arguments passed to both callables (fixed, not differentiated)
    kwargs: tuple[tuple[str, Any], ...] = ()


_GEO, _MOT, _SEN, _FAC = "slam2d.geometry.se2", "slam2d.models.motion", "slam2d.models.sensors", "slam2d.graph.factors"

#: (module, function, Jacobians, argument kinds, output angle indices, fixed keyword arguments). Scalar twins
#: (``*_scalar``, ``*_elementwise``) sit beside their array versions in models/ and are listed by their adapters.
PAIRS: tuple[tuple[str, str, str, tuple[str, ...], tuple[int, ...], dict[str, Any]], ...] = (
    (_GEO, "compose", "compose_jacobians", ("pose", "pose"), (2,), {}),
    (_GEO, "inverse", "inverse_jacobians", ("pose",), (2,), {}),
    (_GEO, "between", "between_jacobians", ("pose", "pose"), (2,), {}),
    (_GEO, "transform_points", "transform_points_jacobians", ("pose", "point"), (), {}),
    (_GEO, "inverse_transform_points", "inverse_transform_points_jacobians", ("pose", "point"), (), {}),
    (_GEO, "exp", "exp_jacobians", ("twist",), (2,), {}),
    (_GEO, "log", "log_jacobians", ("pose",), (2,), {}),
    (_MOT, "rtr_to_odometry", "rtr_to_odometry_jacobians", ("twist",), (2,), {}),
    (_MOT, "odometry_predict", "odometry_predict_jacobians", ("pose", "odometry"), (2,), {}),
    (_MOT, "odometry_scalar_value", "odometry_scalar_jacobians", ("pose", "odometry"), (2,), {}),
    (_MOT, "velocity_increment", "velocity_increment_jacobians", ("velocity",), (2,), {"dt": 0.3}),
    (_MOT, "velocity_predict", "velocity_predict_jacobians", ("pose", "velocity"), (2,), {"dt": 0.3}),
    (_SEN, "range_bearing", "range_bearing_jacobians", ("pose", "point"), (1,), {}),
    (_SEN, "range_bearing_scalar_value", "range_bearing_scalar_jacobians", ("pose", "point"), (1,), {}),
    (_SEN, "range_bearing_elementwise_value", "range_bearing_elementwise_jacobians", ("pose", "point"), (1,), {}),
    (_SEN, "range_bearing_inverse", "range_bearing_inverse_jacobians", ("pose", "range_bearing"), (), {}),
    (_SEN, "bearing_only", "bearing_only_jacobians", ("pose", "point"), (0,), {}),
    (_SEN, "range_only", "range_only_jacobians", ("pose", "point"), (), {}),
    (_SEN, "absolute_position", "absolute_position_jacobians", ("pose",), (), {}),
    ("slam2d.models.floor_markers", "marker_in_robot", "marker_in_robot_jacobians", ("pose", "point"), (), {}),
    (_FAC, "between_error", "between_error_jacobians", ("pose", "pose"), (2,), {"z": (0.7, -0.3, 2.9)}),
    (_FAC, "prior_error", "prior_error_jacobians", ("pose",), (2,), {"z": (0.1, 0.2, -3.0)}),
    (_FAC, "point_error", "point_error_jacobians", ("pose", "point"), (), {"z": (1.5, -0.5)}),
    (_FAC, "range_bearing_error", "range_bearing_error_jacobians", ("pose", "point"), (1,), {"z": (3.0, 3.1)}),
    (_FAC, "bearing_error", "bearing_error_jacobians", ("pose", "point"), (0,), {"z": (-3.1,)}),
    (_FAC, "range_error", "range_error_jacobians", ("pose", "point"), (), {"z": (2.0,)}),
    (_FAC, "position_error", "position_error_jacobians", ("pose",), (), {"z": (1.0, -2.0)}),
    (_FAC, "point_prior_error", "point_prior_error_jacobians", ("point",), (), {"z": (1.0, -2.0)}),
    (_FAC, "pose_range_bearing_error", "pose_range_bearing_error_jacobians", ("pose", "pose"), (1,),
     {"z": (3.0, 3.1)}),
)


def registry() -> list[JacobianPair]:
    """Every pair of :data:`PAIRS`, resolved (imports the listed modules)."""
    out = []
    for module, fn, jac, kinds, angles, kwargs in PAIRS:
        mod = importlib.import_module(module)
        fixed = {k: np.asarray(v, dtype=np.float64) if isinstance(v, tuple) else v for k, v in kwargs.items()}
        name = f"{module}.{fn.removesuffix('_value')}"
        out.append(JacobianPair(name, getattr(mod, fn), getattr(mod, jac), kinds, angles, tuple(sorted(fixed.items()))))
    return out


def __getattr__(name: str) -> Any:
    """``REGISTRY``: :func:`registry`, built on first use (module attributes resolve lazily, PEP 562)."""
    if name == "REGISTRY":
        return registry()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def sample_arg(kind: str, rng: np.random.Generator, edge: str = "random") -> np.ndarray:
    """Draw a valid argument of ``kind``; ``edge`` in {"random", "zero", "pi", "-pi"} sets heading-like angles."""
    if kind in ("pose", "odometry"):
        xy = rng.uniform(-5.0, 5.0, size=2) if kind == "pose" else rng.uniform(0.2, 1.5, size=2)
        # 1e-5 from the cut: close to +-pi, yet a 1e-6 difference step never crosses it (log is discontinuous there)
        theta = {"random": rng.uniform(-np.pi, np.pi), "zero": 1e-7, "pi": np.pi - 1e-5, "-pi": -np.pi + 1e-5}[edge]
        return np.array([xy[0], xy[1], theta])
    if kind == "point":
        return rng.uniform(-8.0, 8.0, size=2)
    if kind == "twist":
        w = {"random": rng.uniform(-2.5, 2.5), "zero": 1e-7, "pi": 3.0, "-pi": -3.0}[edge]
        return np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), w])
    if kind == "range_bearing":
        b = {"random": rng.uniform(-np.pi, np.pi), "zero": 1e-7, "pi": np.pi - 1e-3, "-pi": -np.pi + 1e-3}[edge]
        return np.array([rng.uniform(0.5, 10.0), b])
    if kind == "velocity":
        w = {"random": rng.uniform(-1.0, 1.0), "zero": 1e-9, "pi": 1.5, "-pi": -1.5}[edge]
        return np.array([rng.uniform(0.1, 2.0), w])
    raise KeyError(kind)
