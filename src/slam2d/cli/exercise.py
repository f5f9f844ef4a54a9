"""``slam2d exercise check FILE.py``: check a learner's ``augment_state`` against the library's.

The build-it exercise of the EKF-SLAM chapter: write ``augment_state(mu, P, z_range, z_bearing, R_obs) ->
(mu_new, P_new)`` that appends a newly seen landmark to the EKF state — the inverse observation model for the mean,
the cross-covariance rows ``G_r P[:3, :]`` and the new block ``G_r P_rr G_r^T + G_z R G_z^T``. The checker runs the
lesson's case (robot (5, 3, pi/4), range 2, bearing 0 -> landmark (6.414, 4.414), P from 5x5 to 7x7) and random
cases, and says which part differs.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
AugmentFn = Callable[..., Any]

#: the lesson's expected landmark for robot (5, 3, pi/4), range 2, bearing 0 (to the 3 decimals the lesson prints)
LESSON_LANDMARK = (6.414, 4.414)


@dataclass(frozen=True)
class Case:
    name: str
    mu: Array
    P: Array
    z_range: float
    z_bearing: float
    R_obs: Array


@dataclass(frozen=True)
class Verdict:
    case: str
    ok: bool
    message: str


def reference_augment_state() -> AugmentFn:
    """The library's ``augment_state`` (EKF-SLAM), the answer a learner's function is checked against."""
    from slam2d.filters.ekf_slam import augment_state

    return augment_state


def _spd(rng: np.random.Generator, n: int, scale: float) -> Array:
    a = rng.standard_normal((n, n)) * scale
    return a @ a.T + 1e-3 * np.eye(n)


def lesson_case() -> Case:
    """Robot (5, 3, pi/4) with one landmark already mapped (P is 5x5); the new sighting is range 2, bearing 0."""
    mu = np.array([5.0, 3.0, np.pi / 4, 8.0, 1.0])
    P = _spd(np.random.default_rng(7), 5, 0.1)
    return Case("lesson: robot (5, 3, pi/4), range 2, bearing 0, one prior landmark", mu, P, 2.0, 0.0,
                np.diag([0.1**2, 0.02**2]))


def random_cases(count: int = 20, seed: int = 0) -> list[Case]:
    """Random states with 0..6 prior landmarks, random covariances, measurements and sensor noise."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        n = 3 + 2 * int(rng.integers(0, 7))
        mu = rng.uniform(-10, 10, n)
        mu[2] = rng.uniform(-np.pi, np.pi)
        out.append(Case(f"random #{i + 1} (state dim {n})", mu, _spd(rng, n, float(rng.uniform(0.01, 0.5))),
                        float(rng.uniform(0.5, 15.0)), float(rng.uniform(-np.pi, np.pi)),
                        np.diag([rng.uniform(0.01, 0.5) ** 2, rng.uniform(0.005, 0.1) ** 2])))
    return out


def _where(diff: Array, n: int) -> str:
    """Name the parts of the (n+2)x(n+2) covariance that differ."""
    bad = np.abs(diff) > 1e-8 * (1.0 + np.abs(diff).max())
    parts = []
    if bad[:n, :n].any():
        parts.append("the old block P[:n,:n] (it must not change)")
    if bad[n:, :n].any() or bad[:n, n:].any():
        parts.append("the cross-covariance rows/columns (expected G_r P[:3, :])")
    if bad[n:, n:].any():
        parts.append("the new landmark block (expected G_r P_rr G_r^T + G_z R G_z^T)")
    return ", ".join(parts) or "values"


def check_case(fn: AugmentFn, ref: AugmentFn, case: Case, atol: float = 1e-9) -> Verdict:
    n = len(case.mu)
    want_mu, want_P = (np.asarray(a, dtype=np.float64) for a in ref(case.mu.copy(), case.P.copy(), case.z_range,
                                                                     case.z_bearing, case.R_obs.copy()))
    try:
        got = fn(case.mu.copy(), case.P.copy(), case.z_range, case.z_bearing, case.R_obs.copy())
        mu_new, P_new = (np.asarray(a, dtype=np.float64) for a in got)
    except (Exception, SystemExit) as e:  # sys.exit() in the learner's function is a failed case, not our exit
        return Verdict(case.name, False, f"raised {type(e).__name__}: {e}")
    if mu_new.shape != (n + 2,) or P_new.shape != (n + 2, n + 2):
        return Verdict(case.name, False, f"shapes: got mu {mu_new.shape} and P {P_new.shape}, expected "
                                         f"({n + 2},) and ({n + 2}, {n + 2})")
    if not np.allclose(mu_new, want_mu, atol=atol, rtol=1e-9):
        k = int(np.argmax(np.abs(mu_new - want_mu)))
        what = "the old state (it must not change)" if k < n else "the new landmark position"
        return Verdict(case.name, False, f"mean differs in {what}: entry {k} is {mu_new[k]:.6g}, expected "
                                         f"{want_mu[k]:.6g}")
    scale = max(1.0, float(np.abs(want_P).max()))
    if not np.allclose(P_new, want_P, atol=atol * scale, rtol=1e-8):
        return Verdict(case.name, False, f"covariance differs in {_where(P_new - want_P, n)}; largest difference "
                                         f"{np.abs(P_new - want_P).max():.3g}")
    return Verdict(case.name, True, f"ok (landmark at {mu_new[-2]:.3f}, {mu_new[-1]:.3f})")


def check(fn: AugmentFn, ref: AugmentFn, random_count: int = 20) -> list[Verdict]:
    """Every verdict: the lesson's case (also against its printed landmark), then random cases."""
    lesson = lesson_case()
    verdicts = [check_case(fn, ref, lesson)]
    if verdicts[0].ok:
        mu_new = np.asarray(fn(lesson.mu.copy(), lesson.P.copy(), lesson.z_range, lesson.z_bearing,
                               lesson.R_obs.copy())[0])
        if not np.allclose(mu_new[-2:], LESSON_LANDMARK, atol=1e-3):
            verdicts[0] = Verdict(lesson.name, False, f"landmark at {mu_new[-2:]}, the lesson says {LESSON_LANDMARK}")
    verdicts += [check_case(fn, ref, c) for c in random_cases(random_count)]
    return verdicts


def load_learner(path: str | Path) -> AugmentFn:
    """Import ``augment_state`` from a learner's file; ValueError with a clear message otherwise."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(21, "is a directory, not a Python file", str(p))
    if not p.is_file():
        raise FileNotFoundError(2, "no such file", str(p))
    spec = importlib.util.spec_from_file_location(f"_slam2d_exercise_{abs(hash(str(p.resolve())))}", p)
    if spec is None or spec.loader is None:
        raise ValueError(f"{p}: not a Python file")
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
    except (Exception, SystemExit) as e:  # a file that calls sys.exit() on import must not end the check as a pass
        raise ValueError(f"{p}: importing it failed: {type(e).__name__}: {e}") from None
    fn = getattr(mod, "augment_state", None)
    if not callable(fn):
        raise ValueError(f"{p}: defines no function augment_state(mu, P, z_range, z_bearing, R_obs)")
    try:
        inspect.signature(fn).bind(None, None, None, None, None)
    except TypeError:
        raise ValueError(f"{p}: augment_state must take (mu, P, z_range, z_bearing, R_obs); "
                         f"it has {inspect.signature(fn)}") from None
    return fn


def register(sub: Any) -> None:
    p = sub.add_parser("exercise", help="check a build-it exercise against the library",
                       description="Build-it exercises. 'check FILE.py' imports augment_state from FILE.py and "
                                   "compares it with slam2d.filters.ekf_slam.augment_state on the lesson's case and "
                                   "random cases.")
    p.add_argument("action", choices=["check"], help="what to do")
    p.add_argument("file", help="the learner's Python file defining augment_state(mu, P, z_range, z_bearing, R_obs)")
    p.add_argument("--random", type=int, default=20, help="number of random cases (default 20)")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    ref = reference_augment_state()
    if not 0 <= args.random <= 100_000:
        raise ValueError(f"--random must be in 0..100000 (got {args.random})")
    fn = load_learner(args.file)
    verdicts = check(fn, ref, args.random)
    for v in verdicts:
        print(f"{'PASS' if v.ok else 'FAIL'}  {v.case}: {v.message}")
    passed = sum(v.ok for v in verdicts)
    print(f"{passed}/{len(verdicts)} cases pass" + ("" if passed == len(verdicts) else
                                                     " — compare the failing part with the chapter's formulas"))
    return 0 if passed == len(verdicts) else 1
