"""What every page session shares: validated commands, the hello/state messages, and small drawing helpers.

A session receives validated commands (keys, parameters, actions), advances its simulation by wall-clock time and
produces frame sections (see ``slam2d.web.frames``). Every number a page shows is computed by library calls; the
browser only draws.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from slam2d.models.sensors import range_bearing_inverse_jacobians
from slam2d.web.checks import Check
from slam2d.web.params import CommandError, Param

Array = NDArray[np.float64]
Sections = list[tuple[str, Any]]

#: the keys a page may send, and what they do to the (v, w) command
DRIVE_KEYS = ("ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight")
MAX_PATH_POINTS = 1500
HEAT_MAX = 96


class PathBuffer:
    """A growing path of poses (T, 3): amortised O(1) ``append``; ``np.asarray`` gives the filled rows as a view
    (a list of arrays would be copied into a new array on every frame)."""

    def __init__(self, first: Any) -> None:
        self._a = np.zeros((1024, 3))
        self._n = 0
        self.append(first)

    def append(self, pose: Any) -> None:
        if self._n == len(self._a):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self._n] = pose
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i: Any) -> Any:
        return self._a[: self._n][i]

    def __array__(self, dtype: Any = None, copy: Any = None) -> Array:
        view = self._a[: self._n]
        return view.astype(dtype) if dtype is not None else (view.copy() if copy else view)


def downsample(points: Array, limit: int = MAX_PATH_POINTS) -> Array:
    """At most ``limit`` rows (limit >= 2): every s-th row, s the smallest power of two that fits, and always the
    last one (the current pose). With a power-of-two stride the rows already sent stay the same rows while the path
    grows (until the stride doubles), so the page can keep what it drew of them."""
    n = len(points)
    if n <= limit:
        return points
    s = 1
    while (n - 1) // s + 2 > limit:
        s *= 2
    idx = np.arange(0, n, s)
    return points[idx] if idx[-1] == n - 1 else points[np.append(idx, n - 1)]


def block_average(mat: Array, limit: int = HEAT_MAX) -> Array:
    """Average ``mat`` (n,n) over an at most ``limit`` x ``limit`` grid of blocks (identity when n <= limit)."""
    m = np.asarray(mat, dtype=np.float64)
    n = m.shape[0]
    if n <= limit:
        return m
    edges = np.linspace(0, n, limit + 1).astype(np.int64)
    # block sums via cumulative sums in both axes, then divide by block areas
    cs = np.zeros((n + 1, n + 1))
    cs[1:, 1:] = m.cumsum(0).cumsum(1)
    s = cs[edges[1:]][:, edges[1:]] - cs[edges[:-1]][:, edges[1:]] - cs[edges[1:]][:, edges[:-1]] + \
        cs[edges[:-1]][:, edges[:-1]]
    sizes = np.diff(edges)
    return np.asarray(s / (sizes[:, None] * sizes[None, :]))


def abs_correlation(cov: Array, limit: int = HEAT_MAX) -> Array:
    """|correlation| of a covariance matrix, block-averaged to at most ``limit`` x ``limit``. Shapes: (n,n) -> (m,m).

    Correlation rather than covariance, so the colour scale does not depend on units (m vs rad) and the growing
    off-diagonal blocks that make EKF-SLAM work are visible.
    """
    c = np.asarray(cov, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(c), 1e-300, None))
    return block_average(np.abs(c / d[:, None] / d[None, :]), limit)


def observation_covariances(pose: Array, z: Array, r_obs: Array) -> Array:
    """World-frame covariance of the landmarks placed by observations: ``G_z R G_z^T``.

    Shapes: pose (3,), z (K,2), r_obs (2,2) -> (K,2,2).
    """
    if len(z) == 0:
        return np.zeros((0, 2, 2))
    _, gz = range_bearing_inverse_jacobians(np.broadcast_to(pose, (len(z), 3)), z)
    return np.asarray(gz @ r_obs @ np.swapaxes(gz, -1, -2))


def seed_param() -> Param:
    return Param("seed", "random seed", "int", 0, lo=0, hi=2**31 - 1, step=1, live=False)


class Session:
    """Base class: parameters, validation of commands, hello message. Subclasses advance and draw.

    ``scalars`` are the names of the numbers in the frame's NUMS section; ``labels`` gives each a human label with
    its unit; ``rows()`` says which of them apply right now (the page hides the others).
    """

    page = "base"
    title = "session"
    scalars: tuple[str, ...] = ()
    labels: ClassVar[Mapping[str, str]] = {}

    def __init__(self, params: Sequence[Param], seed: int = 0) -> None:
        self.params = {p.name: p for p in params}
        self.values: dict[str, Any] = {p.name: p.default for p in params}
        if "seed" in self.values:
            self.values["seed"] = int(seed)
        self.notices: list[str] = []
        self.actions: tuple[tuple[str, str], ...] = ()
        self.keys_down: set[str] = set()
        self.check: Check | None = None
        self.task: str | None = None  # the chapter's "Try this" prompt (slam2d.web.tasks)
        self.task_result: str | None = None  # written by the session when it sees the task done
        self._state_changed = False

    def complete_task(self, result: str) -> None:
        """The task is done: show ``result`` (once; the page gets the new state with the next frame)."""
        if self.task is not None and self.task_result is None:
            self.task_result = result
            self._state_changed = True

    def push_state(self) -> None:
        """Send the state with the next frame (e.g. a notice written while advancing, not by a command)."""
        self._state_changed = True

    def take_state_change(self) -> bool:
        changed, self._state_changed = self._state_changed, False
        return changed

    # --- commands -----------------------------------------------------------------------------------------------
    def apply(self, msg: Mapping[str, Any]) -> dict[str, Any] | None:
        """Apply one validated command; returns an optional reply. Raises CommandError for bad commands."""
        kind = msg.get("type")
        if kind == "key":
            key, down = msg.get("key"), msg.get("down")
            if key not in DRIVE_KEYS or not isinstance(down, bool):
                raise CommandError(f"key command needs key in {list(DRIVE_KEYS)} and down true/false (got {dict(msg)})")
            (self.keys_down.add if down else self.keys_down.discard)(str(key))
            return None
        if kind == "param":
            name = msg.get("name")
            if not isinstance(name, str) or name not in self.params:
                raise CommandError(f"unknown parameter {name!r}; valid parameters: {sorted(self.params)}")
            if "value" not in msg:
                raise CommandError(f"parameter command for {name!r} has no value")
            value = self.params[name].coerce(msg["value"])
            old = self.values[name]
            self.values[name] = value
            try:
                self.on_param(name, value, old)
            except (ValueError, TypeError) as e:
                self.values[name] = old
                raise CommandError(f"cannot set {name!r} to {value!r}: {e}") from None
            return self.state()
        if kind == "action":
            name = msg.get("name")
            valid = [a for a, _ in self.actions]
            if name not in valid:
                raise CommandError(f"unknown action {name!r}; valid actions: {valid}")
            self.on_action(str(name))
            return self.state()
        if kind == "answer":
            return self.answer(msg)
        if kind == "ping":
            return {"type": "pong"}
        raise CommandError(f"unknown command type {kind!r}; valid types: key, param, action, answer, ping")

    def answer(self, msg: Mapping[str, Any]) -> dict[str, Any]:
        """Judge an answer to the chapter's check question: ``{"type": "answer", "choice": i}``."""
        if self.check is None:
            raise CommandError(f"page {self.page!r} has no check question")
        choice = msg.get("choice")
        n = len(self.check.choices)
        if isinstance(choice, bool) or not isinstance(choice, int) or not 0 <= choice < n:
            raise CommandError(f"answer needs choice = an integer in 0..{n - 1} (got {choice!r})")
        return self.check.judge(choice)

    def on_param(self, name: str, value: Any, old: Any) -> None:
        """React to a parameter change (values[name] is already set)."""

    def on_action(self, name: str) -> None:
        """React to a button."""

    # --- output -------------------------------------------------------------------------------------------------
    def hello(self) -> dict[str, Any]:
        return {**self.state(), "type": "hello", "page": self.page, "title": self.title,
                "scalars": list(self.scalars), "labels": {k: self.labels.get(k, k) for k in self.scalars},
                "params": [p.describe() for p in self.params.values()],
                "actions": [{"name": a, "label": lab} for a, lab in self.actions],
                "check": self.check.describe() if self.check is not None else None}

    def state(self) -> dict[str, Any]:
        """What changes with commands but not every frame: values, notices, drawing bounds, rows that apply."""
        task = None if self.task is None else {"prompt": self.task, "result": self.task_result}
        return {"type": "state", "values": dict(self.values), "notices": list(self.notices),
                "bounds": list(self.bounds()), "rows": list(self.rows()), "inactive": list(self.inactive()),
                "task": task}

    def inactive(self) -> Sequence[str]:
        """Controls that change nothing under the current settings (the page greys them out)."""
        return ()

    def rows(self) -> Sequence[str]:
        """The scalars that mean something for the current settings (all by default)."""
        return self.scalars

    def bounds(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, 10.0, 10.0)

    def advance(self, wall_dt_s: float) -> None:
        """Advance by ``wall_dt_s`` seconds of wall-clock time."""

    def sections(self) -> Sections:
        return []
