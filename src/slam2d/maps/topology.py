"""Topological maps: places and their connections, from an occupancy grid (skeleton) or from a trajectory.

From a grid (:func:`topology_from_grid`): the free space is cleaned (small holes closed), thinned to a one-pixel
skeleton with scikit-image's ``skeletonize`` (an approximation of the generalised Voronoi diagram: points as far
from the walls on both sides), and read as a graph: skeleton pixels with one neighbour are dead ends, with three or
more are junctions; clusters of adjacent junction pixels are one place; the skeleton runs between places are the
connections (length in m). Dead-end spurs shorter than ``min_spur_m`` (skeleton noise from bumpy walls) are
dropped. Each place carries its clearance (distance to the nearest non-free cell).

From a trajectory (:func:`topology_from_trajectory`): a new place whenever the robot is farther than ``spacing_m``
from every existing place; consecutive places visited are connected. Revisits reuse places, so loops appear.

:func:`three_views` renders one simulated log three ways for the lab, as plain arrays: landmark map (means,
covariances, ids, counts), occupancy grid (log-odds), topology (places, edges).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from slam2d.config import check_positive
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True, slots=True, kw_only=True)
class TopologyConfig:
    """Skeleton-graph settings."""

    close_holes_m: float = 0.3
    """non-free blobs smaller than this across (clutter, unknown specks) are treated as free before thinning (m)."""
    min_clearance_m: float = 0.2
    """skeleton pixels closer than this to a non-free cell are dropped (slivers behind furniture) (m)."""
    min_spur_m: float = 1.0
    """dead-end branches shorter than this are dropped (m)."""

    def __post_init__(self) -> None:
        check_positive(self, "close_holes_m", "min_spur_m")
        if self.min_clearance_m < 0:
            raise ValueError(f"TopologyConfig.min_clearance_m must be >= 0 (got {self.min_clearance_m})")


@dataclass(frozen=True)
class TopologicalMap:
    """Places and connections. Shapes (P places, E edges): places (P,2) world xy, clearance_m (P,), kind (P,) str
    ('junction' / 'end' / 'place'), edges (E,2) place indices, edge_length_m (E,); skeleton (rows, cols) bool or
    None (grid-derived maps)."""

    places: Array
    clearance_m: Array
    kind: NDArray[np.str_]
    edges: IntArray
    edge_length_m: Array
    skeleton: NDArray[np.bool_] | None = None

    def cycles(self) -> int:
        """Independent cycles of the graph: E - P + (connected components)."""
        p = len(self.places)
        if p == 0:
            return 0
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        e = self.edges
        adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(p, p)) if len(e) else coo_matrix((p, p))
        ncomp, _ = connected_components(adj, directed=False)
        return int(len(e) - p + ncomp)


def _neighbours(mask: NDArray[np.bool_]) -> IntArray:
    """Number of 8-neighbours set, per pixel."""
    k = _EIGHT.astype(np.int64)
    k[1, 1] = 0
    return np.asarray(ndimage.convolve(mask.astype(np.int64), k, mode="constant"), dtype=np.int64)


def topology_from_grid(grid: OccupancyGrid, config: TopologyConfig | None = None) -> TopologicalMap:
    """Skeleton graph of the grid's free space (see the module docstring)."""
    from skimage.morphology import skeletonize

    cfg = config or TopologyConfig()
    res = grid.resolution
    free = grid.free()
    blocked = ~free
    # remove small blocked specks (fill them as free) so they do not create skeleton loops
    lab, n = ndimage.label(blocked, structure=_EIGHT)
    if n:
        sizes = ndimage.sum(np.ones_like(lab), lab, index=np.arange(1, n + 1))
        small = np.concatenate([[False], sizes * res * res < cfg.close_holes_m**2])
        free = free | small[lab]
    clearance = ndimage.distance_transform_edt(free) * res
    skel = np.asarray(skeletonize(free), dtype=bool) & (clearance >= cfg.min_clearance_m)

    for _ in range(20):  # prune dead-end spurs (a few passes: removing one spur can expose another)
        graph = _skeleton_graph(skel, clearance, res)
        spur = _spur_pixels(skel, graph, cfg.min_spur_m, res)
        if not spur.any():
            break
        skel = skel & ~spur
        skel = np.asarray(skeletonize(skel), dtype=bool)
    graph = _skeleton_graph(skel, clearance, res)
    places, clear, kind, edges, lengths, _ = graph
    xy = grid.origin + (places[:, ::-1] + 0.5) * res if len(places) else np.zeros((0, 2))
    return TopologicalMap(xy, clear, kind, edges, lengths, skel)


def _pixel_graph(mask: NDArray[np.bool_]) -> tuple[Any, IntArray, IntArray]:
    """Sparse 8-neighbour graph over the set pixels of ``mask`` (weights 1 or sqrt 2); returns (graph, rows, cols)."""
    from scipy.sparse import coo_matrix

    rows, cols = np.nonzero(mask)
    index = -np.ones(mask.shape, dtype=np.int64)
    index[rows, cols] = np.arange(len(rows))
    src: list[IntArray] = []
    dst: list[IntArray] = []
    wts: list[Array] = []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):  # each undirected pair once
        r2, c2 = rows + dr, cols + dc
        ok = (r2 >= 0) & (r2 < mask.shape[0]) & (c2 >= 0) & (c2 < mask.shape[1])
        j = np.full(len(rows), -1)
        j[ok] = index[r2[ok], c2[ok]]
        hit = j >= 0
        src.append(np.flatnonzero(hit))
        dst.append(j[hit])
        wts.append(np.full(int(hit.sum()), np.hypot(dr, dc)))
    s_, d_, w_ = np.concatenate(src), np.concatenate(dst), np.concatenate(wts)
    n = len(rows)
    g = coo_matrix((np.concatenate([w_, w_]), (np.concatenate([s_, d_]), np.concatenate([d_, s_]))), shape=(n, n))
    return g.tocsr(), rows, cols


def _skeleton_graph(skel: NDArray[np.bool_], clearance: Array, res: float
                    ) -> tuple[Array, Array, NDArray[np.str_], IntArray, Array, dict[str, Any]]:
    """Places (row, col), clearance (m), kind, edges, edge lengths (m), and label images for pruning.

    A skeleton run that touches fewer than two places (a loop back to one junction, or a ring with no junction
    at all, e.g. around a pillar) gets two extra places on it, at its widest pixel and the pixel geodesically
    farthest from that, so that the cycle survives in the graph.
    """
    from scipy.sparse.csgraph import dijkstra

    nb = _neighbours(skel) * skel
    node_px = skel & ((nb == 1) | (nb >= 3))
    node_lab, n_nodes = ndimage.label(node_px, structure=_EIGHT)
    path_px = skel & ~node_px
    path_lab, n_paths = ndimage.label(path_px, structure=_EIGHT)
    idx = np.arange(1, n_nodes + 1)
    places = [np.asarray(ndimage.center_of_mass(node_px, node_lab, idx), dtype=np.float64).reshape(-1, 2)]
    clear = [np.asarray(ndimage.maximum(clearance, node_lab, idx), dtype=np.float64).reshape(-1)]
    size = np.asarray(ndimage.sum(node_px, node_lab, idx)).reshape(-1)
    is_end = np.asarray(ndimage.maximum(nb == 1, node_lab, idx), dtype=bool).reshape(-1) & (size == 1)
    kinds = [np.where(is_end, "end", "junction")]
    edges: list[tuple[int, int]] = []
    lengths: list[float] = []
    if n_paths:
        path_len = np.asarray(ndimage.sum(path_px, path_lab, np.arange(1, n_paths + 1))).reshape(-1) * res
        # which places does each run touch? look at the 8 neighbours of every run pixel at once
        rows, cols = np.nonzero(path_px)
        tp, tn = [], []
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r2 = np.clip(rows + dr, 0, skel.shape[0] - 1)
                c2 = np.clip(cols + dc, 0, skel.shape[1] - 1)
                lab = node_lab[r2, c2]
                hit = lab > 0
                tp.append(path_lab[rows[hit], cols[hit]])
                tn.append(lab[hit])
        touch = np.unique(np.stack([np.concatenate(tp), np.concatenate(tn)], axis=1), axis=0).reshape(-1, 2)
        n_touch = np.bincount(touch[:, 0], minlength=n_paths + 1)
        for p in np.unique(touch[:, 0]):  # loop over runs (tens), not pixels
            ns = touch[touch[:, 0] == p, 1] - 1
            for a in range(len(ns)):
                for b in range(a + 1, len(ns)):
                    edges.append((int(ns[a]), int(ns[b])))
                    lengths.append(float(path_len[p - 1]))
        loops = np.flatnonzero(n_touch[1:] < 2) + 1
        next_id = n_nodes
        extra_pl, extra_cl = [], []
        for p in loops:
            comp = path_lab == p
            g, rr, cc = _pixel_graph(comp)
            a = int(np.argmax(clearance[rr, cc]))
            d = dijkstra(g, indices=a)
            d = np.where(np.isfinite(d), d, -1)
            b = int(np.argmax(d))
            pa, pb = next_id, next_id + 1
            next_id += 2
            extra_pl += [[rr[a], cc[a]], [rr[b], cc[b]]]
            extra_cl += [clearance[rr[a], cc[a]], clearance[rr[b], cc[b]]]
            dab = float(d[b]) * res
            ns = touch[touch[:, 0] == p, 1] - 1
            if len(ns) == 1:
                n0 = int(ns[0])
                rest = max(float(path_len[p - 1]) - dab, 0.0)
                edges += [(n0, pa), (pa, pb), (pb, n0)]
                lengths += [0.5 * rest, dab, 0.5 * rest]
            else:
                edges += [(pa, pb), (pa, pb)]
                lengths += [dab, max(float(path_len[p - 1]) - dab, 0.0)]
        if extra_pl:
            places.append(np.asarray(extra_pl, dtype=np.float64))
            clear.append(np.asarray(extra_cl, dtype=np.float64))
            kinds.append(np.full(len(extra_pl), "place"))
    e_arr = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return (np.vstack(places), np.concatenate(clear), np.concatenate(kinds), e_arr,
            np.asarray(lengths, dtype=np.float64), {"node_lab": node_lab, "path_lab": path_lab, "n_paths": n_paths})


def _spur_pixels(skel: NDArray[np.bool_], graph: tuple[Any, ...], min_spur_m: float, res: float
                 ) -> NDArray[np.bool_]:
    """Pixels of dead-end branches shorter than ``min_spur_m``: the path next to an end place, and the end pixel."""
    places, _, kind, _, _, info = graph
    node_lab, path_lab = info["node_lab"], info["path_lab"]
    out = np.zeros_like(skel)
    if len(places) == 0 or "n_paths" not in info:
        return out
    ends = np.flatnonzero(kind == "end")
    if len(ends) == 0:
        return out
    end_px = np.isin(node_lab, ends + 1)
    grown = ndimage.binary_dilation(end_px, structure=_EIGHT)
    cand = np.unique(path_lab[grown & (path_lab > 0)])
    if len(cand):
        sizes = np.asarray(ndimage.sum(np.ones_like(path_lab), path_lab, cand)).reshape(-1) * res
        out |= np.isin(path_lab, cand[sizes < min_spur_m])
    # end pixels that lead into a removed path or sit right next to a junction
    out |= end_px & ndimage.binary_dilation(out | (skel & ~end_px & (path_lab == 0)), structure=_EIGHT)
    return out


def topology_from_trajectory(poses: ArrayLike, spacing_m: float = 2.0) -> TopologicalMap:
    """Places every ``spacing_m`` along a trajectory; connections between consecutively visited places.

    Shapes: poses (T,2+) -> TopologicalMap (no skeleton; clearance is NaN).
    """
    if not spacing_m > 0:
        raise ValueError(f"topology_from_trajectory: spacing_m must be > 0 (got {spacing_m})")
    xy = np.asarray(poses, dtype=np.float64)[:, :2]
    places: list[Array] = []
    visit = np.zeros(len(xy), dtype=np.int64)
    for t, p in enumerate(xy):  # sequential by nature: each decision depends on the places made so far
        if places:
            d = np.hypot(*(np.asarray(places) - p).T)
            k = int(np.argmin(d))
            if d[k] <= spacing_m:
                visit[t] = k
                continue
        places.append(p.copy())
        visit[t] = len(places) - 1
    change = np.flatnonzero(np.diff(visit) != 0) + 1
    seq = visit[np.concatenate([[0], change])]
    pairs = np.stack([seq[:-1], seq[1:]], axis=1) if len(seq) > 1 else np.zeros((0, 2), dtype=np.int64)
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    pl = np.asarray(places).reshape(-1, 2)
    lengths = np.hypot(*(pl[pairs[:, 0]] - pl[pairs[:, 1]]).T) if len(pairs) else np.zeros(0)
    return TopologicalMap(pl, np.full(len(pl), np.nan), np.full(len(pl), "place"), pairs.astype(np.int64), lengths)


def three_views(log: Any, resolution_m: float = 0.1) -> dict[str, Any]:
    """One simulated log as a landmark map, an occupancy grid and a topological map (plain arrays for the lab).

    Uses the log's true poses, so the three views show the world rather than an estimator's errors.
    Keys: ``landmarks`` {means, covs, ids, counts}, ``grid`` {logodds, origin, resolution}, ``topology`` {places,
    kind, clearance, edges, edge_length}, ``trajectory_topology`` {places, edges}.
    """
    from slam2d.maps.landmarks import PersistentLandmarkMapper
    from slam2d.models.sensors import SensorConfig

    if log.true_poses is None:
        raise ValueError("three_views: needs a log with true poses (simulated)")
    poses = log.true_poses
    sensor = SensorConfig(**log.metadata.get("sensor", {}))
    mapper = PersistentLandmarkMapper(sensor)
    for t in range(1, log.num_steps + 1):
        mapper.observe(poses[t], log.observations_at(t).z, t)
    m = mapper.map
    c = m.confirmed
    out: dict[str, Any] = {"landmarks": {"means": m.means[c], "covs": m.covs[c], "ids": m.ids[c],
                                         "counts": m.counts[c]}}
    if log.scan_step is not None and log.scan_ranges_m is not None:
        lo = np.min(poses[:, :2], axis=0) - log.scan_max_range_m
        hi = np.max(poses[:, :2], axis=0) + log.scan_max_range_m
        if log.walls is not None and len(log.walls):
            w = log.walls.reshape(-1, 2)
            lo, hi = w.min(axis=0) - 1.0, w.max(axis=0) + 1.0
        g = OccupancyGrid((lo[0], lo[1], hi[0], hi[1]), OccupancyConfig(resolution_m=resolution_m))
        g.integrate(poses[log.scan_step], log.scan_ranges_m, log.scan_angles_rad, log.scan_max_range_m)
        topo = topology_from_grid(g)
        out["grid"] = {"logodds": g.logodds, "origin": g.origin, "resolution": g.resolution}
        out["topology"] = {"places": topo.places, "kind": topo.kind, "clearance": topo.clearance_m,
                           "edges": topo.edges, "edge_length": topo.edge_length_m}
    tt = topology_from_trajectory(poses)
    out["trajectory_topology"] = {"places": tt.places, "edges": tt.edges}
    return out
