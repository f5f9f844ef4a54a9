"""A lidar SLAM session that may start from a saved map: relocalise globally, then localise and keep mapping in the
map's frame; and save its map (``SupportsSaveMap``).

Without a prior map it is :class:`~slam2d.graph.lidar.LidarSLAM` (a cold start at the given initial pose). With
one (a :class:`~slam2d.maps.store.MapSnapshot`), the initial pose is ignored (the start is unknown): every step
goes to a :class:`~slam2d.frontend.relocalise.Relocaliser` until it accepts a pose; the online pose meanwhile is its
best hypothesis (or dead reckoning in the session frame while it has none). On acceptance the lidar estimator is
reset at the accepted pose and seeded with the map's keyframes (``LidarSLAM.seed_prior_map``), and from then on
it tracks, adds keyframes and closes loops against them. The poses before the acceptance are re-expressed in the
map's frame through the accepted hypothesis (odometry between them and the acceptance), so the final trajectory is
in the map's frame throughout.

Loops between a new keyframe and one of the map's are counted (``map_loops``) but not reported as
``Estimate.new_loops``: those name poses of this run only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam2d.estimator import Diagnostics, Estimate, EstimatorLifecycle
from slam2d.frontend.relocalise import RelocaliseConfig, Relocaliser
from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAM, LidarSLAMConfig
from slam2d.log import Scan, Step
from slam2d.maps.layers import MapLayers
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid
from slam2d.maps.store import MapSnapshot, MapStore, range_histogram

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class LidarSessionConfig:
    """A lidar SLAM session with saved maps."""

    lidar: LidarSLAMConfig = field(default_factory=LidarSLAMConfig)
    """the lidar estimator (tracking, keyframes, loops)."""
    relocalise: RelocaliseConfig = field(default_factory=RelocaliseConfig)
    """global relocalisation against the prior map."""
    save_resolution_m: float = 0.1
    """cell size of the static occupancy layer written by ``save_map`` (m)."""


class LidarSession(EstimatorLifecycle):
    """See the module docstring. ``prior``: the map to start from (None: cold start); ``world_id``: the world a saved
    map belongs to (the prior's when there is one)."""

    def __init__(self, config: LidarSessionConfig | None = None, *, prior: MapSnapshot | None = None,
                 world_id: str | None = None, metadata: dict[str, Any] | None = None) -> None:
        self.config = config or LidarSessionConfig()
        self.prior = prior
        self.world_id = world_id or (prior.world_id if prior is not None else None)
        self.metadata = dict(metadata or {})
        self.lidar = LidarSLAM(self.config.lidar)

    def reset(self, initial_pose: Array, *, rng: np.random.Generator) -> None:
        self._lifecycle_reset()
        self._rng = rng
        self._pre: list[Array] = []  # session-frame (odometry) poses of the steps before acceptance, step 0 first
        self.accepted_step: int | None = None
        self.accepted_time_s: float | None = None
        self.map_loops = 0
        self.accepted_pose: Array | None = None
        self._markers: dict[int, list[Array]] = {}
        if self.prior is None:
            self.relocaliser: Relocaliser | None = None
            self.lidar.reset(initial_pose, rng=rng)
            self._pose = np.asarray(initial_pose, dtype=np.float64).copy()
        else:
            self.relocaliser = Relocaliser(self.prior, self.config.relocalise, rng=rng)
            self.lidar = LidarSLAM(self.config.lidar)
            self._pre.append(np.zeros(3))
            self._pose = np.zeros(3)

    @property
    def lifelong(self) -> bool:
        """The lidar estimator keeps map layers: the saved map's static layer is reused, not rebuilt."""
        return self.config.lidar.layers is not None

    @property
    def relocalised(self) -> bool:
        return self.relocaliser is None or self.accepted_step is not None

    def step(self, step: Step) -> None:
        self._check_step()
        if not self.relocalised:
            assert self.relocaliser is not None
            status = self.relocaliser.step(step)
            self._pre.append(self.relocaliser.odo.copy())
            if status.decided and status.pose is not None and step.scan is not None:
                self._accept(step, status.pose, status.information)
            else:
                self._pose = status.pose.copy() if status.pose is not None else self.relocaliser.odo.copy()
            return
        self.lidar.step(step)
        est = self.lidar.estimate()
        self.map_loops += sum(lp.accepted for lp in est.new_loops if lp.a < 0 or lp.b < 0)
        self._pose = est.pose
        self._collect_markers(step)

    def _accept(self, step: Step, pose: Array, information: Array | None) -> None:
        assert self.prior is not None and step.scan is not None
        self.accepted_step, self.accepted_time_s = int(step.index), float(step.time_s)
        self.accepted_pose = pose.copy()
        # the steps so far, in the map frame: the accepted pose and the odometry between each and now
        t_map_session = se2.compose(pose, se2.inverse(self._pre[-1]))
        self._pre_map = se2.compose(t_map_session, np.asarray(self._pre)).reshape(-1, 3)
        self.lidar.reset(pose, rng=self._rng)
        p = self.prior
        if self.lifelong:
            # the static layer is the saved one; the scans from the next step on are localised against it
            self.lidar.seed_prior_layers(MapLayers.from_saved(self.config.lidar.layers, p.layers), p.keyframe_poses)
            self._pose = pose.copy()
            self._collect_markers(step)
            return
        scans = [Scan(r.astype(np.float64), p.scan_angles_rad, p.scan_max_range_m) for r in p.keyframe_scans]
        info = information if information is not None else np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.01**2])
        self.lidar.seed_prior_map(p.keyframe_poses, scans, step.scan, pose, info, int(step.index))
        self._pose = pose.copy()
        self._collect_markers(step)

    def _collect_markers(self, step: Step) -> None:
        """Floor markers read after relocalisation (or in a cold start), placed at the current pose: the map's
        ``floor_markers`` layer."""
        if step.markers is None or not len(step.markers):
            return
        world = se2.transform_points(self._pose, step.markers.xy_m)
        for i, xy in zip(step.markers.ids.tolist(), world, strict=True):
            self._markers.setdefault(int(i), []).append(xy)

    def estimate(self) -> Estimate:
        self._check_ready()
        if not self.relocalised:
            return Estimate(pose=self._pose.copy(), pose_cov=None)
        est = self.lidar.estimate()
        loops = tuple(lp for lp in est.new_loops if lp.a >= 0 and lp.b >= 0)
        traj = est.trajectory
        if traj is not None and self.accepted_step is not None:
            traj = np.vstack([self._pre_map[:-1], traj])
        return Estimate(pose=est.pose, pose_cov=est.pose_cov, trajectory=traj, new_loops=loops,
                        diagnostics=est.diagnostics)

    def finalize(self) -> None:
        # never relocalised: nothing to optimise; the online poses are the best hypotheses of their steps
        if self._lifecycle_finalize() and self.relocalised:
            self.lidar.finalize()

    def close_loop_now(self, z: Array) -> bool:
        """The lidar estimator's on-demand loop search (False before relocalisation)."""
        self._check_step()
        return self.relocalised and self.lidar.close_loop_now(z)

    @property
    def diagnostics(self) -> Diagnostics:
        return self.lidar.estimate().diagnostics if self.relocalised else Diagnostics()

    # ------------------------------------------------------------------ saved maps
    def snapshot(self) -> MapSnapshot:
        """The map estimated so far: keyframes (the prior's included), pose graph, static layer, markers."""
        if self.world_id is None:
            raise ValueError("LidarSession: no world id to save the map under (give world_id=...)")
        if not self.relocalised:
            raise ValueError("LidarSession: not relocalised in the prior map yet; nothing new to save")
        lid = self.lidar
        poses = lid.keyframe_poses
        scans = lid.keyframe_scans()
        edges, z, info = lid.pose_graph_edges()
        layers: dict[str, NDArray[Any]] = {}
        if self.lifelong:
            lay = lid.map_layers()
            grid = lay.static_grid()
            layers.update(lay.saved())
            if self.prior is not None:  # the map's keyframes stay as saved (they never move in lifelong mode)
                p, k = self.prior, len(self.prior.keyframe_poses)
                edges = np.vstack([p.edge_nodes, edges + k])
                z, info = np.vstack([p.edge_poses, z]), np.concatenate([p.edge_information, info])
                poses = np.vstack([p.keyframe_poses, poses])
                scans = [Scan(r.astype(np.float64), p.scan_angles_rad, p.scan_max_range_m)
                         for r in p.keyframe_scans] + scans
        if len(poses) == 0:
            raise ValueError("LidarSession: no keyframe yet (no scan was processed); nothing to save")
        beams = {len(s.ranges_m) for s in scans}
        if len(beams) != 1:
            raise ValueError(f"LidarSession: keyframe scans have different beam counts {sorted(beams)}")
        ranges = np.stack([np.asarray(s.ranges_m, dtype=np.float32) for s in scans])
        max_range = float(scans[-1].max_range_m)
        if not self.lifelong:
            grid = self._static_layer(poses, scans)
        prior_markers = None if self.prior is None else self.prior.layers.get("floor_markers")
        n_mk = max([len(prior_markers) if prior_markers is not None else 0] + [i + 1 for i in self._markers])
        if n_mk:
            mk = np.full((n_mk, 2), np.nan)
            if prior_markers is not None:
                mk[: len(prior_markers)] = prior_markers
            for i, xs in self._markers.items():
                if i >= 0:
                    mk[i] = np.mean(xs, axis=0)
            layers["floor_markers"] = mk
        meta = {**self.metadata, "source": "estimator", "estimator": "lidar-lifelong" if self.lifelong else "lidar",
                "prior_keyframes": 0 if self.prior is None else len(self.prior.keyframe_poses),
                "accepted_step": self.accepted_step}
        return MapSnapshot(
            world_id=self.world_id, keyframe_poses=poses.copy(), keyframe_scans=ranges,
            descriptors=range_histogram(ranges, max_range), scan_angles_rad=np.asarray(scans[-1].angles_rad),
            scan_max_range_m=max_range, node_ids=np.arange(len(poses), dtype=np.int64), node_poses=poses.copy(),
            edge_nodes=edges, edge_poses=z, edge_information=info,
            occupancy_logodds=grid.logodds.astype(np.float32), occupancy_origin=grid.origin.copy(),
            occupancy_resolution_m=float(grid.resolution), metadata=meta, layers=layers)

    def _static_layer(self, poses: Array, scans: list[Scan]) -> OccupancyGrid:
        """Every keyframe scan at its estimated pose in a log-odds grid (as ``LidarSLAM.occupancy_grid``) whose
        corner lies on a multiple of the cell size: maps saved on different flights share one cell lattice, so
        their static layers compare cell by cell."""
        res = self.config.save_resolution_m
        mr = self.config.lidar.max_range_m
        pts = [se2.transform_points(p, np.stack([np.cos(s.angles_rad), np.sin(s.angles_rad)], -1)
                                    * np.where(np.isfinite(s.ranges_m), np.minimum(s.ranges_m, mr), 0.0)[:, None])
               for p, s in zip(poses, scans, strict=True)]
        allp = np.vstack([*pts, poses[:, :2]])
        lo = np.floor(allp.min(axis=0) / res - 10) * res
        hi = np.ceil(allp.max(axis=0) / res + 10) * res
        grid = OccupancyGrid((lo[0], lo[1], hi[0], hi[1]), OccupancyConfig(resolution_m=res, free_range_cap_m=0.0))
        for p, s in zip(poses, scans, strict=True):
            grid.update(p, s.ranges_m, s.angles_rad, min(s.max_range_m, mr))
        return grid

    def save_map(self, path: str) -> None:
        """Write :meth:`snapshot` to ``path`` atomically (``MapStore.write``; the path may be the prior's file)."""
        MapStore.write(Path(path), self.snapshot(), created_by="slam2d lidar session",
                       replace_other_world=False)
