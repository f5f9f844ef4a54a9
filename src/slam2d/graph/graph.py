"""Factor graph structure (keys + stacked factor arrays) and variable values, kept apart.

Poses and points are two separate key namespaces (as in iSAM: pose 3 and landmark 3 are different variables).
A :class:`FactorGraph` only stores factors: for each factor type, stacked key arrays, measurements, the upper
Cholesky factor ``L`` of each information matrix (``Omega = L^T L``, so the whitened error is ``L e``) and an
optional per-factor robust kernel. :class:`Values` stores the current estimate of every variable.

Adding factors is batched (``add_between(i_keys, j_keys, z, information)``) and bumps ``structure_version`` so an
optimiser can tell whether its symbolic analysis is still valid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam2d.graph.factors import KINDS
from slam2d.graph.robust import KERNEL_CODES, kernel_code

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class GraphError(ValueError):
    """Invalid graph content (bad information matrix, NaN, missing variable, unknown factor type, ...)."""


def _keys(a: ArrayLike, n: int | None, what: str) -> IntArray:
    k = np.asarray(a)
    if k.ndim == 0:
        k = k.reshape(1)
    if k.ndim != 1 or (k.size and not np.issubdtype(k.dtype, np.integer)):
        raise GraphError(f"{what}: keys must be a 1-D integer array (got dtype {k.dtype}, shape {k.shape})")
    if n is not None and k.size != n:
        raise GraphError(f"{what}: expected {n} keys, got {k.size}")
    return k.astype(np.int64)


def _rows(a: ArrayLike, width: int, what: str) -> Array:
    """A float64 copy of ``a`` as (N, width) rows: one (width,) vector is one row and an empty array none; any other
    shape (a transposed (width, N) array, a flat vector) is a GraphError rather than a silent reshape."""
    v = np.array(a, dtype=np.float64)
    if v.size == 0:
        return np.zeros((0, width))
    if v.shape == (width,):
        return v.reshape(1, width)
    if v.ndim != 2 or v.shape[1] != width:
        raise GraphError(f"{what}: values must have shape (N, {width}), got {v.shape}")
    return v


def _check_values(name: str, k: IntArray, v: Array, existing: IntArray) -> None:
    """GraphError unless keys ``k`` match values ``v`` in number, are unique (also against ``existing``) and the
    values are finite."""
    if k.size != v.shape[0]:
        raise GraphError(f"Values: {k.size} {name} keys but {v.shape[0]} {name} values")
    if np.unique(k).size != k.size or np.any(np.isin(k, existing)):
        raise GraphError(f"Values: duplicate {name} keys")
    if not np.all(np.isfinite(v)):
        bad = k[~np.all(np.isfinite(v), axis=1)][0]
        raise GraphError(f"Values: {name} {bad} has a non-finite value")


@dataclass
class Values:
    """Variable estimates: poses ``(P, 3)`` with keys ``(P,)`` and points ``(L, 2)`` with keys ``(L,)``.

    A Values owns its arrays: the constructor copies what it is given, so writing into ``values.poses`` never
    reaches the caller's arrays (and the caller's later writes never reach the Values).
    Shapes: pose_keys (P,), poses (P, 3), point_keys (L,), points (L, 2).
    """

    pose_keys: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    poses: Array = field(default_factory=lambda: np.zeros((0, 3)))
    point_keys: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    points: Array = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        self.pose_keys = _keys(self.pose_keys, None, "Values.pose_keys")  # astype: always a copy
        self.point_keys = _keys(self.point_keys, None, "Values.point_keys")
        self.poses = _rows(self.poses, 3, "Values.poses")
        self.points = _rows(self.points, 2, "Values.points")
        _check_values("pose", self.pose_keys, self.poses, np.zeros(0, np.int64))
        _check_values("point", self.point_keys, self.points, np.zeros(0, np.int64))

    def copy(self) -> Values:
        return Values(self.pose_keys, self.poses, self.point_keys, self.points)

    def add_poses(self, keys: ArrayLike, poses: ArrayLike) -> None:
        """Append poses (keys must be new)."""
        k = _keys(keys, None, "add_poses")
        v = _rows(poses, 3, "add_poses")
        _check_values("pose", k, v, self.pose_keys)
        self.pose_keys, self.poses = np.concatenate([self.pose_keys, k]), np.concatenate([self.poses, v])

    def add_points(self, keys: ArrayLike, points: ArrayLike) -> None:
        """Append points (keys must be new)."""
        k = _keys(keys, None, "add_points")
        v = _rows(points, 2, "add_points")
        _check_values("point", k, v, self.point_keys)
        self.point_keys, self.points = np.concatenate([self.point_keys, k]), np.concatenate([self.points, v])

    def pose(self, key: int) -> Array:
        """The pose with this key (raises KeyError)."""
        idx = np.flatnonzero(self.pose_keys == key)
        if idx.size == 0:
            raise KeyError(f"pose {key}")
        return self.poses[idx[0]].copy()

    def point(self, key: int) -> Array:
        """The point with this key (raises KeyError)."""
        idx = np.flatnonzero(self.point_keys == key)
        if idx.size == 0:
            raise KeyError(f"point {key}")
        return self.points[idx[0]].copy()


@dataclass
class FactorBlock:
    """All factors of one type, stacked. Shapes: keys (k, N); z (N, meas_dim); sqrt_info (N, m, m);
    kernel (N,) int codes; kernel_param (N,)."""

    kind: str
    keys: IntArray
    z: Array
    sqrt_info: Array
    kernel: NDArray[np.int8]
    kernel_param: Array

    @property
    def size(self) -> int:
        return int(self.z.shape[0])

    @property
    def information(self) -> Array:
        """Omega = L^T L, (N, m, m)."""
        return np.asarray(np.swapaxes(self.sqrt_info, 1, 2) @ self.sqrt_info)


def sqrt_information(information: ArrayLike, m: int, what: str) -> Array:
    """Upper factor ``L`` with ``Omega = L^T L`` for a batch of information matrices; GraphError names the first
    non-finite, non-symmetric or non-positive-definite one. Shapes: (N, m, m) -> (N, m, m)."""
    om = np.asarray(information, dtype=np.float64)
    if om.ndim == 2:
        om = om[None]
    if om.shape[1:] != (m, m):
        raise GraphError(f"{what}: information must be (N, {m}, {m}), got {om.shape}")
    bad = ~np.all(np.isfinite(om), axis=(1, 2))
    if np.any(bad):
        raise GraphError(f"{what}: information of factor {int(np.flatnonzero(bad)[0])} is not finite")
    asym = np.abs(om - np.swapaxes(om, 1, 2)).max(axis=(1, 2)) > 1e-9 * np.maximum(1.0, np.abs(om).max(axis=(1, 2)))
    if np.any(asym):
        raise GraphError(f"{what}: information of factor {int(np.flatnonzero(asym)[0])} is not symmetric")
    # batched Cholesky: numpy raises for the whole batch, so locate the offender with eigenvalues
    ev = np.linalg.eigvalsh(om)
    notpd = ~(ev[:, 0] > 1e-13 * ev[:, -1])  # numerically singular: Cholesky would fail (or be meaningless)
    if np.any(notpd):
        i = int(np.flatnonzero(notpd)[0])
        raise GraphError(f"{what}: information of factor {i} is not positive definite (eigenvalues {ev[i]})")
    lower = np.linalg.cholesky(om)  # Omega = C C^T, C lower  ->  L = C^T
    return np.ascontiguousarray(np.swapaxes(lower, 1, 2))


class FactorGraph:
    """Factors of a 2D SLAM problem, one stacked block per factor type.

    Methods ``add_<type>`` append a batch; measurements and information matrices are validated on entry
    (GraphError). ``robust`` optionally attaches a kernel to the appended factors: a name from
    ``robust.KERNEL_CODES`` and a parameter (``robust_param``, in units of the whitened error, i.e. sqrt(chi2)).
    """

    def __init__(self) -> None:
        self._parts: dict[str, list[FactorBlock]] = {}
        self._cache: dict[str, FactorBlock] = {}
        self.structure_version = 0

    # ----------------------------------------------------------------------------------------------- adding
    def _add(self, kind: str, keys: list[ArrayLike], z: ArrayLike, information: ArrayLike,
             robust: str | None, robust_param: float) -> None:
        k = KINDS[kind]
        zz = np.asarray(z, dtype=np.float64)
        n = zz.shape[0] if zz.ndim >= 1 else 1
        zz = zz.reshape(n, k.meas_dim) if zz.size == n * k.meas_dim else zz
        if zz.shape != (n, k.meas_dim):
            raise GraphError(f"add_{kind}: measurements must be (N, {k.meas_dim}), got {np.shape(z)}")
        if not np.all(np.isfinite(zz)):
            raise GraphError(f"add_{kind}: measurement {int(np.flatnonzero(~np.isfinite(zz).all(1))[0])} not finite")
        ks = np.stack([_keys(a, n, f"add_{kind}") for a in keys]) if n else np.zeros((len(keys), 0), np.int64)
        om = np.asarray(information, dtype=np.float64)
        if om.ndim not in (2, 3) or om.shape[-2:] != (k.dim, k.dim) or (om.ndim == 3 and om.shape[0] not in (1, n)):
            raise GraphError(f"add_{kind}: information must be ({k.dim}, {k.dim}) or ({n}, {k.dim}, {k.dim}) for {n} "
                             f"measurements, got {om.shape}")
        if om.ndim == 2 or om.shape[0] != n:
            om = np.broadcast_to(om, (n, k.dim, k.dim))
        L = sqrt_information(om, k.dim, f"add_{kind}") if n else np.zeros((0, k.dim, k.dim))
        if kind == "between" and n and np.any(ks[0] == ks[1]):
            raise GraphError(f"add_between: factor {int(np.flatnonzero(ks[0] == ks[1])[0])} connects a pose to itself")
        code = kernel_code(robust)
        if robust is not None and not (robust_param > 0 and np.isfinite(robust_param)):
            raise GraphError(f"add_{kind}: robust_param must be > 0 (got {robust_param})")
        block = FactorBlock(kind, ks, zz.copy(), L, np.full(n, code, np.int8), np.full(n, float(robust_param)))
        self._parts.setdefault(kind, []).append(block)
        self._cache.pop(kind, None)
        self.structure_version += 1

    def add_between(self, i_keys: ArrayLike, j_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                    robust: str | None = None, robust_param: float = 1.0) -> None:
        """Relative-pose factors (odometry, loop closures): z (N,3) = pose j in the frame of pose i."""
        self._add("between", [i_keys, j_keys], z, information, robust, robust_param)

    def add_prior(self, keys: ArrayLike, z: ArrayLike, information: ArrayLike, *, robust: str | None = None,
                  robust_param: float = 1.0) -> None:
        """Pose priors: z (N,3)."""
        self._add("prior", [keys], z, information, robust, robust_param)

    def add_point(self, pose_keys: ArrayLike, point_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                  robust: str | None = None, robust_param: float = 1.0) -> None:
        """Landmark position in the pose frame (g2o EDGE_SE2_XY, iSAM LANDMARK): z (N,2)."""
        self._add("point", [pose_keys, point_keys], z, information, robust, robust_param)

    def add_range_bearing(self, pose_keys: ArrayLike, point_keys: ArrayLike, z: ArrayLike, information: ArrayLike,
                          *, robust: str | None = None, robust_param: float = 1.0) -> None:
        """Range (m) and bearing (rad) to a landmark: z (N,2)."""
        self._add("range_bearing", [pose_keys, point_keys], z, information, robust, robust_param)

    def add_bearing(self, pose_keys: ArrayLike, point_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                    robust: str | None = None, robust_param: float = 1.0) -> None:
        """Bearing-only (rad): z (N,1)."""
        self._add("bearing", [pose_keys, point_keys], z, information, robust, robust_param)

    def add_range(self, pose_keys: ArrayLike, point_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                  robust: str | None = None, robust_param: float = 1.0) -> None:
        """Range-only (m): z (N,1)."""
        self._add("range", [pose_keys, point_keys], z, information, robust, robust_param)

    def add_position(self, pose_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                     robust: str | None = None, robust_param: float = 1.0) -> None:
        """Absolute position of a pose (GPS): z (N,2)."""
        self._add("position", [pose_keys], z, information, robust, robust_param)

    def add_point_prior(self, point_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                        robust: str | None = None, robust_param: float = 1.0) -> None:
        """Landmark position prior: z (N,2)."""
        self._add("point_prior", [point_keys], z, information, robust, robust_param)

    def add_pose_range_bearing(self, i_keys: ArrayLike, j_keys: ArrayLike, z: ArrayLike, information: ArrayLike, *,
                               robust: str | None = None, robust_param: float = 1.0) -> None:
        """Range (m) and bearing (rad) from pose i to the position of pose j (robot-robot sightings): z (N,2)."""
        self._add("pose_range_bearing", [i_keys, j_keys], z, information, robust, robust_param)

    # --------------------------------------------------------------------------------------------- reading
    def block(self, kind: str) -> FactorBlock:
        """All factors of one type, concatenated (cached until the next add)."""
        if kind not in KINDS:
            raise GraphError(f"unknown factor type {kind!r}; known: {sorted(KINDS)}")
        if kind not in self._cache:
            parts = self._parts.get(kind, [])
            nv = len(KINDS[kind].var_kinds)
            m = KINDS[kind].dim
            if not parts:
                blk = FactorBlock(kind, np.zeros((nv, 0), np.int64), np.zeros((0, KINDS[kind].meas_dim)),
                                  np.zeros((0, m, m)), np.zeros(0, np.int8), np.zeros(0))
            elif len(parts) == 1:
                blk = parts[0]
            else:
                blk = FactorBlock(kind, np.concatenate([p.keys for p in parts], axis=1),
                                  np.concatenate([p.z for p in parts]), np.concatenate([p.sqrt_info for p in parts]),
                                  np.concatenate([p.kernel for p in parts]),
                                  np.concatenate([p.kernel_param for p in parts]))
                self._parts[kind] = [blk]
            self._cache[kind] = blk
        return self._cache[kind]

    def kinds(self) -> list[str]:
        """Factor types present (non-empty), in a fixed order."""
        return [k for k in KINDS if k in self._parts and self.block(k).size > 0]

    def blocks(self) -> list[FactorBlock]:
        return [self.block(k) for k in self.kinds()]

    @property
    def num_factors(self) -> int:
        return sum(b.size for b in self.blocks())

    def set_robust(self, kind: str | None, kernel: str | None, param: float = 1.0) -> None:
        """Set the robust kernel of every factor of ``kind`` (all types when None). Does not change structure."""
        code = kernel_code(kernel)
        if kernel is not None and not (param > 0 and np.isfinite(param)):
            raise GraphError(f"set_robust: param must be > 0 (got {param})")
        for k in ([kind] if kind else self.kinds()):
            b = self.block(k)
            b.kernel[:] = code
            b.kernel_param[:] = param

    def with_robust(self, kinds: Sequence[str], kernel: str | None, param: float = 1.0) -> FactorGraph:
        """A graph with the same factors whose factors of ``kinds`` (every type when empty) carry ``kernel``; this
        graph is left unchanged. Measurements and information matrices are shared with this graph (treat them as
        read-only), kernel arrays of the selected types are new; ``structure_version`` is the same."""
        code = kernel_code(kernel)
        if kernel is not None and not (param > 0 and np.isfinite(param)):
            raise GraphError(f"with_robust: param must be > 0 (got {param})")
        unknown = sorted(set(kinds) - set(KINDS))
        if unknown:
            raise GraphError(f"with_robust: unknown factor type(s) {unknown}; known: {sorted(KINDS)}")
        out = FactorGraph()
        for k in self.kinds():
            b = self.block(k)
            if not kinds or k in kinds:
                b = replace(b, kernel=np.full(b.size, code, np.int8), kernel_param=np.full(b.size, float(param)))
            out._parts[k] = [b]
        out.structure_version = self.structure_version
        return out

    def pose_keys_used(self) -> IntArray:
        out = [b.keys[i] for b in self.blocks() for i, vk in enumerate(KINDS[b.kind].var_kinds) if vk == "pose"]
        return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)

    def point_keys_used(self) -> IntArray:
        out = [b.keys[i] for b in self.blocks() for i, vk in enumerate(KINDS[b.kind].var_kinds) if vk == "point"]
        return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)


__all__ = ["KERNEL_CODES", "FactorBlock", "FactorGraph", "GraphError", "Values", "sqrt_information"]
