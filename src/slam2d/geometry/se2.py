"""SE(2) poses as ``[x, y, theta]`` arrays, batch axes first.

Conventions (stated once, used by every Jacobian in the library):

* ``T_a_b`` maps coordinates in frame b to frame a: ``T_w_c = compose(T_w_b, T_b_c)``.
* Perturbations are additive with wrap: ``retract(x, d) = [x+dx, y+dy, wrap(theta+dtheta)]`` and
  ``local(x, y) = [y - x with angle_diff on theta]``. Jacobians ``J_out_in`` are d local(out) / d delta(in).
* Headings are wrapped to [-pi, pi) after every operation that produces one.

Invariants (tested with hypothesis over batch shapes):
``compose(a, inverse(a)) == identity``; ``between(a, b) == compose(inverse(a), b)``;
``compose(a, between(a, b)) == b``; ``retract(p, local(p, q)) == q``; ``exp(log(p)) == p``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry.angles import angle_diff, wrap_angle

Array = NDArray[np.float64]


def _f(a: ArrayLike) -> Array:
    return np.asarray(a, dtype=np.float64)


def _pose(a: ArrayLike, what: str = "pose") -> Array:
    """``a`` as float64 poses (..., 3); a ValueError for any other last axis (e.g. a transposed (3, N) batch, which
    would otherwise be read as rows of garbage: batch axes come first)."""
    p = np.asarray(a, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"{what} must have shape (..., 3) [x, y, theta] with batch axes first, got {p.shape}")
    return p


def _xy(a: ArrayLike) -> Array:
    """``a`` as float64 points (..., 2); a ValueError for any other last axis."""
    p = np.asarray(a, dtype=np.float64)
    if p.shape[-1:] != (2,):
        raise ValueError(f"points must have shape (..., 2) [x, y] with batch axes first, got {p.shape}")
    return p


def matrix_from_rows(*rows: list[Array]) -> Array:
    """Stack rows of broadcast scalars into (..., n, m) matrices."""
    entries = [e for r in rows for e in r]
    width = len(rows[0])
    if any(len(r) != width for r in rows):
        raise ValueError(f"matrix_from_rows: rows of different lengths {[len(r) for r in rows]}")
    shape = np.broadcast_shapes(*[np.shape(e) for e in entries])
    # one buffer filled entry by entry (the entries are the matrix's n*m cells, not data): a nested np.stack of
    # broadcast views cost several times more, and Jacobians are built on every factor evaluation
    out = np.empty((*shape, len(rows), width), dtype=np.result_type(*entries))
    for k, e in enumerate(entries):
        out[..., k // width, k % width] = e
    return out


def compose(a: ArrayLike, b: ArrayLike) -> Array:
    """Pose composition ``a (+) b`` (b expressed in the frame of a). Shapes: (...,3),(...,3) -> (...,3)."""
    a, b = _pose(a, "a"), _pose(b, "b")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def compose_chain(start: ArrayLike, increments: ArrayLike) -> Array:
    """Poses ``start (+) u_1 (+) ... (+) u_k`` for k = 0..T (dead reckoning), vectorised: headings are a cumulative
    sum, positions a cumulative sum of the increments rotated by the heading before each. Shapes: (3,),(T,3) ->
    (T+1,3)."""
    u = _f(increments)
    u = u.reshape(-1, 3) if u.size == 0 or u.shape == (3,) else _pose(u, "increments")
    if u.ndim != 2:
        raise ValueError(f"increments must have shape (T, 3), got {u.shape}")
    p0 = _pose(start, "start")
    if p0.shape != (3,):
        raise ValueError(f"start must have shape (3,), got {p0.shape}")
    heading = p0[2] + np.concatenate([[0.0], np.cumsum(u[:, 2])])
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    step_xy = np.stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1]], axis=-1)
    xy = p0[:2] + np.vstack([np.zeros((1, 2)), np.cumsum(step_xy, axis=0)])
    return np.column_stack([xy, wrap_angle(heading)])


def compose_jacobians(a: ArrayLike, b: ArrayLike) -> tuple[Array, Array]:
    """``(J_ab_a, J_ab_b)``, each (..., 3, 3)."""
    a, b = _pose(a, "a"), _pose(b, "b")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    one, zero = np.ones_like(c), np.zeros_like(c)
    ja = matrix_from_rows(
        [one, zero, -s * b[..., 0] - c * b[..., 1]],
        [zero, one, c * b[..., 0] - s * b[..., 1]],
        [zero, zero, one],
    )
    jb = matrix_from_rows([c, -s, zero], [s, c, zero], [zero, zero, one])
    return ja, np.broadcast_to(jb, ja.shape).copy()




def inverse(a: ArrayLike) -> Array:
    """Inverse pose. Shapes: (...,3) -> (...,3)."""
    a = _pose(a, "a")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def inverse_jacobians(a: ArrayLike) -> tuple[Array]:
    """``(J_inv_a,)``, (..., 3, 3)."""
    a = _pose(a, "a")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    one, zero = np.ones_like(c), np.zeros_like(c)
    j = matrix_from_rows(
        [-c, -s, s * a[..., 0] - c * a[..., 1]],
        [s, -c, c * a[..., 0] + s * a[..., 1]],
        [zero, zero, -one],
    )
    return (j,)




def between(a: ArrayLike, b: ArrayLike) -> Array:
    """Relative pose ``a (-) b = inverse(a) (+) b``: b in the frame of a. Shapes: (...,3),(...,3) -> (...,3)."""
    a, b = _pose(a, "a"), _pose(b, "b")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, angle_diff(b[..., 2], a[..., 2])], axis=-1)


def between_jacobians(a: ArrayLike, b: ArrayLike) -> tuple[Array, Array]:
    """``(J_ab_a, J_ab_b)``, each (..., 3, 3)."""
    a, b = _pose(a, "a"), _pose(b, "b")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    one, zero = np.ones_like(c), np.zeros_like(c)
    ja = matrix_from_rows(
        [-c, -s, -s * dx + c * dy],
        [s, -c, -c * dx - s * dy],
        [zero, zero, -one],
    )
    jb = matrix_from_rows([c, s, zero], [-s, c, zero], [zero, zero, one])
    return ja, jb




def transform_points(pose: ArrayLike, p: ArrayLike) -> Array:
    """Map points from the pose's frame to the outer frame: ``p_w = R p_b + t``. Shapes: (...,3),(...,2) -> (...,2)."""
    pose, p = _pose(pose), _xy(p)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack(
        [pose[..., 0] + c * p[..., 0] - s * p[..., 1], pose[..., 1] + s * p[..., 0] + c * p[..., 1]], axis=-1
    )


def transform_points_jacobians(pose: ArrayLike, p: ArrayLike) -> tuple[Array, Array]:
    """``(J_pw_pose (...,2,3), J_pw_p (...,2,2))``."""
    pose, p = _pose(pose), _xy(p)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    c, s = np.broadcast_arrays(c, s, p[..., 0])[:2]
    one, zero = np.ones_like(c), np.zeros_like(c)
    jpose = matrix_from_rows([one, zero, -s * p[..., 0] - c * p[..., 1]], [zero, one, c * p[..., 0] - s * p[..., 1]])
    jp = matrix_from_rows([c, -s], [s, c])
    return jpose, jp




def inverse_transform_points(pose: ArrayLike, p: ArrayLike) -> Array:
    """Map points from the outer frame into the pose's frame: ``p_b = R^T (p_w - t)``."""
    pose, p = _pose(pose), _xy(p)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    dx, dy = p[..., 0] - pose[..., 0], p[..., 1] - pose[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def inverse_transform_points_jacobians(pose: ArrayLike, p: ArrayLike) -> tuple[Array, Array]:
    """``(J_pb_pose (...,2,3), J_pb_p (...,2,2))``."""
    pose, p = _pose(pose), _xy(p)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    dx, dy = p[..., 0] - pose[..., 0], p[..., 1] - pose[..., 1]
    c, s = np.broadcast_arrays(c, s, dx)[:2]
    jpose = matrix_from_rows([-c, -s, -s * dx + c * dy], [s, -c, -c * dx - s * dy])
    jp = matrix_from_rows([c, s], [-s, c])
    return jpose, jp




def _exp_coeffs(w: Array) -> tuple[Array, Array, Array, Array]:
    """A = sin(w)/w, B = (1-cos w)/w and their derivatives, with Taylor branches near 0."""
    small = np.abs(w) < 1e-4
    ws = np.where(small, 1.0, w)
    a = np.where(small, 1 - w**2 / 6, np.sin(ws) / ws)
    b = np.where(small, w / 2 - w**3 / 24, (1 - np.cos(ws)) / ws)
    da = np.where(small, -w / 3, (ws * np.cos(ws) - np.sin(ws)) / ws**2)
    db = np.where(small, 0.5 - w**2 / 8, (ws * np.sin(ws) - (1 - np.cos(ws))) / ws**2)
    return a, b, da, db


def exp(v: ArrayLike) -> Array:
    """Exponential map of a twist ``[vx, vy, w]`` (constant-velocity arc for unit time). Shapes: (...,3) -> (...,3)."""
    v = _pose(v, "twist")
    a, b, _, _ = _exp_coeffs(v[..., 2])
    x = a * v[..., 0] - b * v[..., 1]
    y = b * v[..., 0] + a * v[..., 1]
    return np.stack([x, y, wrap_angle(v[..., 2])], axis=-1)


def exp_jacobians(v: ArrayLike) -> tuple[Array]:
    """``(J_pose_v,)``, (..., 3, 3)."""
    v = _pose(v, "twist")
    a, b, da, db = _exp_coeffs(v[..., 2])
    one, zero = np.ones_like(a), np.zeros_like(a)
    j = matrix_from_rows(
        [a, -b, da * v[..., 0] - db * v[..., 1]],
        [b, a, db * v[..., 0] + da * v[..., 1]],
        [zero, zero, one],
    )
    return (j,)




def log(pose: ArrayLike) -> Array:
    """Logarithm map, the inverse of :func:`exp` for headings in [-pi, pi). Shapes: (...,3) -> (...,3)."""
    pose = _pose(pose)
    w = wrap_angle(pose[..., 2])
    a, b, _, _ = _exp_coeffs(w)
    det = a * a + b * b
    vx = (a * pose[..., 0] + b * pose[..., 1]) / det
    vy = (-b * pose[..., 0] + a * pose[..., 1]) / det
    return np.stack([vx, vy, w], axis=-1)


def log_jacobians(pose: ArrayLike) -> tuple[Array]:
    """``(J_v_pose,)`` = inverse of the exp Jacobian at ``log(pose)``."""
    (j,) = exp_jacobians(log(pose))
    return (np.asarray(np.linalg.inv(j), dtype=np.float64),)




def retract(x: ArrayLike, delta: ArrayLike) -> Array:
    """Additive-with-wrap retraction used by every filter and optimiser in slam2d."""
    x, delta = _pose(x, "x"), _pose(delta, "delta")
    out = x + delta
    out[..., 2] = wrap_angle(out[..., 2])
    return out


def local(x: ArrayLike, y: ArrayLike) -> Array:
    """Inverse of :func:`retract`: ``retract(x, local(x, y)) == y``."""
    x, y = _pose(x, "x"), _pose(y, "y")
    out = y - x
    out[..., 2] = angle_diff(y[..., 2], x[..., 2])
    return out


def rotation_matrix(theta: ArrayLike) -> Array:
    """2x2 rotation matrices. Shapes: (...) -> (..., 2, 2)."""
    t = _f(theta)
    c, s = np.cos(t), np.sin(t)
    return matrix_from_rows([c, -s], [s, c])


def covariance_in_frame(cov: ArrayLike, theta: ArrayLike) -> Array:
    """An ``[x, y, theta]`` covariance (or information) matrix given in one frame, expressed in a frame turned by
    ``theta`` from it: ``J C J^T`` with ``J = diag(R(theta)^T, 1)``. A ``between`` factor's translation error is in
    the frame of its END pose (g2o EdgeSE2: ``R(dtheta)^T (...)``), so a relative pose whose covariance is over x, y
    in the START frame (odometry, an ICP result T_i_j) enters with ``theta = dtheta``: unturned, a covariance long
    along a corridor in the start frame would lie across it after a 90-degree turn. Shapes: (...,3,3),(...) ->
    (...,3,3)."""
    t = _f(theta)
    c, s = np.cos(t), np.sin(t)
    one, zero = np.ones_like(c), np.zeros_like(c)
    j = matrix_from_rows([c, s, zero], [-s, c, zero], [zero, zero, one])
    return np.asarray(j @ _f(cov) @ np.swapaxes(j, -1, -2), dtype=np.float64)
