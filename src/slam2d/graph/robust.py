"""Robust kernels applied by iteratively re-weighted least squares (IRLS).

A kernel maps the squared whitened error of one factor, ``s = e^T Omega e``, to a cost ``rho(s)``; the optimiser
weights that factor's Hessian and gradient contributions by ``w = rho'(s)`` computed at the current linearisation
point. Parameters follow g2o's ``RobustKernel*`` conventions:

* ``huber`` (delta, in units of sqrt(chi2)): ``rho = s`` for ``s <= delta^2``, else ``2 delta sqrt(s) - delta^2``.
* ``cauchy`` (delta): ``rho = delta^2 log(1 + s / delta^2)``, ``w = 1 / (1 + s / delta^2)``.
* ``dcs`` (Phi, in chi2 units; dynamic covariance scaling, Agarwal et al. ICRA 2013 - the closed form of switchable
  constraints): IRLS weight ``w = k^2`` with ``k = min(1, 2 Phi / (Phi + s))`` exactly as g2o's RobustKernelDCS.
  g2o reports ``k^2 s`` as the cost, which DEcreases for ``s > Phi`` (an optimiser comparing costs is then
  rewarded for pushing residuals up); slam2d uses the integral of the weight instead, ``rho = s`` for
  ``s <= Phi`` and ``3 Phi - 4 Phi^2 / (Phi + s)`` above (continuous, increasing, bounded by ``3 Phi``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

KERNEL_CODES = {None: 0, "none": 0, "huber": 1, "cauchy": 2, "dcs": 3}
KERNEL_NAMES = {0: "none", 1: "huber", 2: "cauchy", 3: "dcs"}


def kernel_code(name: str | None) -> int:
    """Integer code of a kernel name (None / "none" = plain least squares)."""
    key = name.lower() if isinstance(name, str) else name
    if key not in KERNEL_CODES:
        raise ValueError(f"unknown robust kernel {name!r}; choose one of huber, cauchy, dcs, none")
    return KERNEL_CODES[key]


def robustify(s: Array, code: NDArray[np.int8], param: Array) -> tuple[Array, Array]:
    """Cost ``rho(s)`` and IRLS weight ``rho'(s)`` per factor. Shapes: (N,),(N,),(N,) -> (N,),(N,)."""
    rho = s.copy()
    w = np.ones_like(s)
    if not np.any(code):
        return rho, w
    for c in np.unique(code):
        if c == 0:
            continue
        m = code == c
        sm, p = s[m], param[m]
        if c == 1:  # huber
            big = sm > p * p
            r = np.sqrt(np.where(big, sm, 1.0))
            rho[m] = np.where(big, 2 * p * r - p * p, sm)
            w[m] = np.where(big, p / r, 1.0)
        elif c == 2:  # cauchy
            p2 = p * p
            rho[m] = p2 * np.log1p(sm / p2)
            w[m] = 1.0 / (1.0 + sm / p2)
        elif c == 3:  # dcs
            k = np.minimum(1.0, 2 * p / (p + sm))
            rho[m] = np.where(sm <= p, sm, 3 * p - 4 * p * p / (p + sm))
            w[m] = k * k
        else:  # pragma: no cover - codes are validated on entry
            raise ValueError(f"unknown robust kernel code {c}")
    return rho, w
