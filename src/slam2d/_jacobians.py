"""One registry of (function, Jacobians) pairs, checked by a single finite-difference test.

Every model function ``f`` with an analytic sibling ``f_jacobians`` registers itself here with the kinds of its
arguments, so the test suite can sample valid inputs (including headings near 0 and +-pi) and compare the
analytic Jacobians with central differences taken through ``retract``/``local`` (see geometry/se2.py).
"""

from __future__ import annotations

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


REGISTRY: list[JacobianPair] = []


def register(
    function: Callable[..., Any],
    jacobians: Callable[..., tuple[Any, ...]],
    arg_kinds: tuple[str, ...],
    output_angles: tuple[int, ...] = (),
    name: str | None = None,
    **kwargs: Any,
) -> None:
    """Add a pair to the registry (called at import time by the defining module)."""
    REGISTRY.append(
        JacobianPair(
            name=name or f"{function.__module__}.{function.__name__}",
            function=function,
            jacobians=jacobians,
            arg_kinds=arg_kinds,
            output_angles=output_angles,
            kwargs=tuple(sorted(kwargs.items())),
        )
    )


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
