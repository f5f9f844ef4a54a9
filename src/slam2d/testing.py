"""Public helpers for checking your own models: finite-difference Jacobians through the SE(2) manifold."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.geometry.angles import wrap_angle


def numerical_jacobian(
    f: Callable[[NDArray[np.float64]], ArrayLike],
    x: ArrayLike,
    *,
    eps: float = 1e-6,
    input_angles: Sequence[int] = (),
    output_angles: Sequence[int] = (),
) -> NDArray[np.float64]:
    """Central-difference Jacobian of ``f`` at ``x`` (a single point, shape (n,)).

    Perturbations are additive; the components listed in ``input_angles`` are wrapped after perturbing, and the
    output components in ``output_angles`` are differenced with wrap (the ``retract``/``local`` convention of
    ``slam2d.geometry.se2``). Returns an (m, n) array.
    """
    x0 = np.asarray(x, dtype=np.float64).ravel()
    cols = []
    for i in range(x0.size):
        xp, xm = x0.copy(), x0.copy()
        xp[i] += eps
        xm[i] -= eps
        for k in input_angles:
            xp[k], xm[k] = wrap_angle(xp[k]), wrap_angle(xm[k])
        d = np.asarray(f(xp), dtype=np.float64).ravel() - np.asarray(f(xm), dtype=np.float64).ravel()
        for k in output_angles:
            d[k] = wrap_angle(d[k])
        cols.append(d / (2 * eps))
    return np.stack(cols, axis=-1)


def assert_jacobian_matches(
    f: Callable[[NDArray[np.float64]], ArrayLike],
    x: ArrayLike,
    analytic: ArrayLike,
    *,
    rtol: float = 1e-5,
    atol: float = 1e-7,
    input_angles: Sequence[int] = (),
    output_angles: Sequence[int] = (),
) -> None:
    """Raise ``AssertionError`` when ``analytic`` differs from the central-difference Jacobian of ``f`` at ``x``."""
    num = numerical_jacobian(f, x, input_angles=input_angles, output_angles=output_angles)
    np.testing.assert_allclose(np.asarray(analytic).reshape(num.shape), num, rtol=rtol, atol=atol)
