"""Factor types of the 2D graph back end: residuals with analytic Jacobians, one vectorised call per type.

Every factor type evaluates a whole batch at once: ``evaluate(vars, z) -> (e, J)`` where ``vars`` are the stacked
variable values BATCH-LAST (poses ``(3, N)``, points ``(2, N)``), ``z`` the measurements ``(meas_dim, N)``, ``e`` the
``(m, N)`` error and ``J`` the ``(m, D, N)`` Jacobian with respect to the concatenated variables (``D`` = sum of their
dimensions), taken with the library's additive-with-wrap retraction (``geometry/se2.py``). (The public single-factor
functions below use the library's usual batch-first shapes.) Angular error rows go
through the wrap, so the error is always the shortest angle.

Error conventions (all are "prediction minus measurement" in the measurement space):

* ``between`` (odometry and loop closures), g2o's EdgeSE2 exactly:
  ``e = [R(dth)^T (R(th_i)^T (t_j - t_i) - [dx, dy]) ; wrap(th_j - th_i - dth)]``.
* ``prior`` on a pose: ``e = [x - zx, y - zy, wrap(th - zth)]``.
* ``point`` (pose -> landmark in the pose frame; g2o EDGE_SE2_XY, iSAM LANDMARK): ``e = R(th)^T (l - t) - z``.
* ``range_bearing``: ``e = [|l - t| - r, wrap(atan2(l - t) - th - b)]``; ``bearing``/``range`` take one row.
* ``position`` (absolute position / GPS of a pose): ``e = t - z``.
* ``pose_range_bearing`` (robot i sights robot j): ``e = [|t_j - t_i| - r, wrap(atan2(t_j - t_i) - th_i - b)]``.
* ``point_prior``: ``e = l - z``.

Each residual has a public ``*_error`` function and a ``*_error_jacobians`` sibling listed in
``slam2d._jacobians`` so the finite-difference test of the whole library covers them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry.angles import wrap_angle

Array = NDArray[np.float64]

#: dimension of each variable kind
VAR_DIM = {"pose": 3, "point": 2}


def _f(a: ArrayLike) -> Array:
    return np.asarray(a, dtype=np.float64)


# ---------------------------------------------------------------------------------------------------- evaluators
# Evaluators work BATCH-LAST: variables (d, N), measurements (meas_dim, N); they return e (m, N) and J (m, D, N).
# With the batch axis last every component is a contiguous length-N vector, so the element-wise formulas (and the
# block products in problem.py) run at memory speed instead of looping over tiny 3x3 matrices.


def eval_between(xi: Array, xj: Array, z: Array) -> tuple[Array, Array]:
    """g2o EdgeSE2 error and Jacobian w.r.t. [xi, xj]. Shapes: (3,N),(3,N),(3,N) -> (3,N),(3,6,N)."""
    n = xi.shape[1]
    c, s = np.cos(xi[2]), np.sin(xi[2])
    cz, sz = np.cos(z[2]), np.sin(z[2])
    dx, dy = xj[0] - xi[0], xj[1] - xi[1]
    u0 = c * dx + s * dy
    u1 = -s * dx + c * dy
    a0, a1 = u0 - z[0], u1 - z[1]
    e = np.empty((3, n))
    e[0] = cz * a0 + sz * a1
    e[1] = -sz * a0 + cz * a1
    e[2] = wrap_angle(xj[2] - xi[2] - z[2])
    # R(dth)^T R(th_i)^T = R(th_i + dth)^T
    cc = c * cz - s * sz
    ss = s * cz + c * sz
    J = np.zeros((3, 6, n))
    J[0, 0], J[0, 1] = -cc, -ss
    J[1, 0], J[1, 1] = ss, -cc
    # d/dth_i of R_i^T d is [u1, -u0]; rotate by R(dth)^T
    J[0, 2] = cz * u1 - sz * u0
    J[1, 2] = -sz * u1 - cz * u0
    J[2, 2] = -1.0
    J[0, 3], J[0, 4] = cc, ss
    J[1, 3], J[1, 4] = -ss, cc
    J[2, 5] = 1.0
    return e, J


def eval_prior(x: Array, z: Array) -> tuple[Array, Array]:
    """Pose prior. Shapes: (3,N),(3,N) -> (3,N),(3,3,N)."""
    e = x - z
    e[2] = wrap_angle(e[2])
    J = np.zeros((3, 3, x.shape[1]))
    J[0, 0] = J[1, 1] = J[2, 2] = 1.0
    return e, J


def eval_point(x: Array, lm: Array, z: Array) -> tuple[Array, Array]:
    """Landmark position in the pose frame. Shapes: (3,N),(2,N),(2,N) -> (2,N),(2,5,N)."""
    n = x.shape[1]
    c, s = np.cos(x[2]), np.sin(x[2])
    dx, dy = lm[0] - x[0], lm[1] - x[1]
    u0 = c * dx + s * dy
    u1 = -s * dx + c * dy
    e = np.stack([u0 - z[0], u1 - z[1]])
    J = np.empty((2, 5, n))
    J[0, 0], J[0, 1], J[0, 2] = -c, -s, u1
    J[1, 0], J[1, 1], J[1, 2] = s, -c, -u0
    J[0, 3], J[0, 4] = c, s
    J[1, 3], J[1, 4] = -s, c
    return e, J


def _rb_parts(x: Array, lm: Array) -> tuple[Array, Array, Array, Array, Array]:
    dx, dy = lm[0] - x[0], lm[1] - x[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    return dx, dy, q, r, np.arctan2(dy, dx) - x[2]


def eval_range_bearing(x: Array, lm: Array, z: Array) -> tuple[Array, Array]:
    """Range and bearing to a landmark. Shapes: (3,N),(2,N),(2,N) -> (2,N),(2,5,N)."""
    dx, dy, q, r, b = _rb_parts(x, lm)
    e = np.stack([r - z[0], wrap_angle(b - z[1])])
    J = np.zeros((2, 5, x.shape[1]))
    J[0, 0], J[0, 1] = -dx / r, -dy / r
    J[1, 0], J[1, 1], J[1, 2] = dy / q, -dx / q, -1.0
    J[:, 3:] = -J[:, :2]
    return e, J


def eval_pose_range_bearing(xi: Array, xj: Array, z: Array) -> tuple[Array, Array]:
    """Range and bearing from pose i to the POSITION of pose j (one robot sighting another; j's heading is not
    observed). Shapes: (3,N),(3,N),(2,N) -> (2,N),(2,6,N)."""
    dx, dy, q, r, b = _rb_parts(xi, xj[:2])
    e = np.stack([r - z[0], wrap_angle(b - z[1])])
    J = np.zeros((2, 6, xi.shape[1]))
    J[0, 0], J[0, 1] = -dx / r, -dy / r
    J[1, 0], J[1, 1], J[1, 2] = dy / q, -dx / q, -1.0
    J[:, 3:5] = -J[:, :2]
    return e, J


def eval_bearing(x: Array, lm: Array, z: Array) -> tuple[Array, Array]:
    """Bearing only. Shapes: (3,N),(2,N),(1,N) -> (1,N),(1,5,N)."""
    dx, dy, q, _, b = _rb_parts(x, lm)
    e = wrap_angle(b - z[0])[None]
    J = np.zeros((1, 5, x.shape[1]))
    J[0, 0], J[0, 1], J[0, 2] = dy / q, -dx / q, -1.0
    J[0, 3], J[0, 4] = -dy / q, dx / q
    return e, J


def eval_range(x: Array, lm: Array, z: Array) -> tuple[Array, Array]:
    """Range only. Shapes: (3,N),(2,N),(1,N) -> (1,N),(1,5,N)."""
    dx, dy, _, r, _ = _rb_parts(x, lm)
    e = (r - z[0])[None]
    J = np.zeros((1, 5, x.shape[1]))
    J[0, 0], J[0, 1] = -dx / r, -dy / r
    J[0, 3], J[0, 4] = dx / r, dy / r
    return e, J


def eval_position(x: Array, z: Array) -> tuple[Array, Array]:
    """Absolute position of a pose. Shapes: (3,N),(2,N) -> (2,N),(2,3,N)."""
    e = x[:2] - z
    J = np.zeros((2, 3, x.shape[1]))
    J[0, 0] = J[1, 1] = 1.0
    return e, J


def eval_point_prior(lm: Array, z: Array) -> tuple[Array, Array]:
    """Landmark position prior. Shapes: (2,N),(2,N) -> (2,N),(2,2,N)."""
    J = np.zeros((2, 2, lm.shape[1]))
    J[0, 0] = J[1, 1] = 1.0
    return lm - z, J


# ------------------------------------------------------------------------------------------------- factor kinds


@dataclass(frozen=True)
class FactorKind:
    """Static description of one factor type."""

    name: str
    var_kinds: tuple[str, ...]
    """kinds of the variables, in argument order ("pose" / "point")."""
    dim: int
    """residual dimension m."""
    meas_dim: int
    """measurement vector length."""
    angle_rows: tuple[int, ...]
    """error rows that are angles."""
    evaluate: Callable[..., tuple[Array, Array]]

    @property
    def var_dims(self) -> tuple[int, ...]:
        return tuple(VAR_DIM[k] for k in self.var_kinds)


KINDS: dict[str, FactorKind] = {
    k.name: k
    for k in [
        FactorKind("between", ("pose", "pose"), 3, 3, (2,), eval_between),
        FactorKind("prior", ("pose",), 3, 3, (2,), eval_prior),
        FactorKind("point", ("pose", "point"), 2, 2, (), eval_point),
        FactorKind("range_bearing", ("pose", "point"), 2, 2, (1,), eval_range_bearing),
        FactorKind("bearing", ("pose", "point"), 1, 1, (0,), eval_bearing),
        FactorKind("range", ("pose", "point"), 1, 1, (), eval_range),
        FactorKind("position", ("pose",), 2, 2, (), eval_position),
        FactorKind("point_prior", ("point",), 2, 2, (), eval_point_prior),
        FactorKind("pose_range_bearing", ("pose", "pose"), 2, 2, (1,), eval_pose_range_bearing),
    ]
}


# ------------------------------------------------------------------------- single-factor API for the FD registry


def _one(kind: str, args: tuple[ArrayLike, ...], z: ArrayLike) -> tuple[Array, Array]:
    """Evaluate one factor; returns batch-first e (1, m) and J (1, m, D)."""
    k = KINDS[kind]
    vs = tuple(_f(a).reshape(d, 1) for a, d in zip(args, k.var_dims, strict=True))
    e, J = k.evaluate(*vs, _f(z).reshape(k.meas_dim, 1))
    return e.T, np.moveaxis(J, -1, 0)


def _split(kind: str, J: Array) -> tuple[Array, ...]:
    dims = KINDS[kind].var_dims
    cuts = np.cumsum((0,) + dims)
    return tuple(J[0, :, cuts[i] : cuts[i + 1]] for i in range(len(dims)))


def between_error(xi: ArrayLike, xj: ArrayLike, z: ArrayLike) -> Array:
    """g2o EdgeSE2 error of one factor. Shapes: (3,),(3,),(3,) -> (3,)."""
    return _one("between", (xi, xj), z)[0][0]


def between_error_jacobians(xi: ArrayLike, xj: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dxi, de/dxj)``, each (3, 3)."""
    return _split("between", _one("between", (xi, xj), z)[1])


def prior_error(x: ArrayLike, z: ArrayLike) -> Array:
    """Pose prior error. Shapes: (3,),(3,) -> (3,)."""
    return _one("prior", (x,), z)[0][0]


def prior_error_jacobians(x: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx,)`` (3, 3)."""
    return _split("prior", _one("prior", (x,), z)[1])


def point_error(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> Array:
    """Landmark-in-pose-frame error. Shapes: (3,),(2,),(2,) -> (2,)."""
    return _one("point", (x, lm), z)[0][0]


def point_error_jacobians(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx (2,3), de/dl (2,2))``."""
    return _split("point", _one("point", (x, lm), z)[1])


def range_bearing_error(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> Array:
    """Range-bearing error. Shapes: (3,),(2,),(2,) -> (2,)."""
    return _one("range_bearing", (x, lm), z)[0][0]


def range_bearing_error_jacobians(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx (2,3), de/dl (2,2))``."""
    return _split("range_bearing", _one("range_bearing", (x, lm), z)[1])


def bearing_error(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> Array:
    """Bearing-only error. Shapes: (3,),(2,),(1,) -> (1,)."""
    return _one("bearing", (x, lm), z)[0][0]


def bearing_error_jacobians(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx (1,3), de/dl (1,2))``."""
    return _split("bearing", _one("bearing", (x, lm), z)[1])


def range_error(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> Array:
    """Range-only error. Shapes: (3,),(2,),(1,) -> (1,)."""
    return _one("range", (x, lm), z)[0][0]


def range_error_jacobians(x: ArrayLike, lm: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx (1,3), de/dl (1,2))``."""
    return _split("range", _one("range", (x, lm), z)[1])


def position_error(x: ArrayLike, z: ArrayLike) -> Array:
    """Absolute-position error. Shapes: (3,),(2,) -> (2,)."""
    return _one("position", (x,), z)[0][0]


def position_error_jacobians(x: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dx (2,3),)``."""
    return _split("position", _one("position", (x,), z)[1])


def point_prior_error(lm: ArrayLike, z: ArrayLike) -> Array:
    """Landmark prior error. Shapes: (2,),(2,) -> (2,)."""
    return _one("point_prior", (lm,), z)[0][0]


def point_prior_error_jacobians(lm: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dl (2,2),)``."""
    return _split("point_prior", _one("point_prior", (lm,), z)[1])


def pose_range_bearing_error(xi: ArrayLike, xj: ArrayLike, z: ArrayLike) -> Array:
    """Robot-robot range-bearing error. Shapes: (3,),(3,),(2,) -> (2,)."""
    return _one("pose_range_bearing", (xi, xj), z)[0][0]


def pose_range_bearing_error_jacobians(xi: ArrayLike, xj: ArrayLike, z: ArrayLike) -> tuple[Array, ...]:
    """``(de/dxi (2,3), de/dxj (2,3))``."""
    return _split("pose_range_bearing", _one("pose_range_bearing", (xi, xj), z)[1])


