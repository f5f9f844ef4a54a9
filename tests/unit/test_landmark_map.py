"""Landmark map: fusion math, the k-sightings persistence rule, and forklifts kept out of the map (warehouse)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from slam2d.maps.landmarks import LandmarkMap, PersistenceConfig, PersistentLandmarkMapper
from slam2d.maps.occupancy import OccupancyConfig, OccupancyGrid, rasterize_segments
from slam2d.models.sensors import SensorConfig
from slam2d.sim import simulate


def test_fusion_equals_batch_information_mean(rng: np.random.Generator) -> None:
    m = LandmarkMap(PersistenceConfig(min_sightings=3))
    covs = np.array([np.diag(rng.uniform(0.01, 0.1, 2)) for _ in range(6)])
    z = np.array([1.0, 2.0]) + rng.normal(0, 0.05, (6, 2))
    m.add(z[0], covs[0], step=0)
    for t in range(1, 6):
        m.fuse([0], z[t:t + 1], covs[t:t + 1], step=t)
    info = np.linalg.inv(covs)
    p = np.linalg.inv(info.sum(axis=0))
    mean = p @ np.einsum("kij,kj->i", info, z)
    assert np.allclose(m.means[0], mean) and np.allclose(m.covs[0], p)
    # the running-sum consistency chi-square equals the direct weighted residual sum of squares
    d = z - mean
    assert np.isclose(m.consistency_chi2()[0], np.einsum("ki,kij,kj->", d, info, d))
    assert m.counts[0] == 6 and m.confirmed[0]


def test_k_sightings_rule_and_pruning() -> None:
    cfg = PersistenceConfig(min_sightings=4, max_unseen_steps=3)
    m = LandmarkMap(cfg)
    c = np.eye(2)[None] * 0.01
    m.add([[0.0, 0.0], [5.0, 5.0]], np.repeat(c, 2, axis=0), step=0)
    for t in range(1, 3):
        m.fuse([0], [[0.01 * t, 0.0]], c, step=t)
    assert m.counts[0] == 3 and not m.confirmed[0]
    assert len(m.estimate_view()[2]) == 0
    m.fuse([0], [[0.0, 0.01]], c, step=3)
    assert m.confirmed[0]
    dropped = m.prune(step=4)  # landmark 1 (seen once at step 0) is stale; 0 is confirmed and stays
    assert dropped == 1 and m.ids.tolist() == [0]
    means, covs, ids = m.estimate_view()
    assert ids.tolist() == [0] and means.shape == (1, 2) and covs.shape == (1, 2, 2)
    with pytest.raises(ValueError, match="min_sightings"):
        PersistenceConfig(min_sightings=0)
    with pytest.raises(ValueError, match="at most one"):
        m.fuse([0, 0], [[0, 0], [0, 0]], np.repeat(c, 2, axis=0), step=5)


def test_a_moving_point_is_flagged_dynamic_a_static_one_is_not(rng: np.random.Generator) -> None:
    cfg = PersistenceConfig(min_sightings=10)
    sigma = 0.15
    c = np.eye(2)[None] * sigma**2
    flagged = {"static": 0, "moving": 0}
    for _trial in range(50):
        for kind, v in (("static", 0.0), ("moving", 0.16)):  # the forklift: one sigma of drift per step
            m = LandmarkMap(cfg)
            z0 = np.array([3.0, 4.0])
            m.add(z0 + rng.normal(0, sigma, 2), c, step=0)
            for t in range(1, 10):
                m.fuse([0], (z0 + [v * t, 0.0] + rng.normal(0, sigma, 2))[None], c, step=t)
            flagged[kind] += int(m.dynamic[0])
            assert m.confirmed[0] != m.dynamic[0]
    assert flagged["moving"] >= 48 and flagged["static"] <= 3, flagged


@pytest.mark.slow
def test_warehouse_forklifts_do_not_become_landmarks_and_fade_from_the_grid() -> None:
    log = simulate("warehouse", seed=1)
    assert log.true_poses is not None and log.true_landmarks is not None and log.walls is not None
    sensor = SensorConfig(**log.metadata["sensor"])
    k = 10
    mapper = PersistentLandmarkMapper(sensor, PersistenceConfig(min_sightings=k))
    naive = PersistentLandmarkMapper(sensor, PersistenceConfig(min_sightings=1))
    for t in range(1, log.num_steps + 1):
        z = log.observations_at(t).z
        mapper.observe(log.true_poses[t], z, t)
        naive.observe(log.true_poses[t], z, t)
    assert (log.obs_id == -2).sum() > 300  # the forklifts were seen a lot

    def far_from_true(means: np.ndarray) -> int:
        d = np.min(np.hypot(*(means[:, None] - log.true_landmarks[None]).transpose(2, 0, 1)), axis=1)
        return int((d > 0.5).sum())

    means, _, _ = mapper.map.estimate_view()
    assert far_from_true(naive.map.estimate_view()[0]) > 50  # without the rule the forklift tracks are "landmarks"
    assert far_from_true(means) == 0
    # every post seen at least k times is in the map
    seen, cnt = np.unique(log.obs_id[log.obs_id >= 0], return_counts=True)
    posts = log.true_landmarks[seen[cnt >= k]]
    d = np.min(np.hypot(*(posts[:, None] - means[None]).transpose(2, 0, 1)), axis=1)
    assert len(posts) > 40 and np.all(d < 0.3)

    # grid decay: the lidar also sees the forklifts; their traces fade with decay and stay without it
    off_wall = {}
    for decay in (0.0, 0.02):
        g = OccupancyGrid((-0.55, -0.55, 40.5, 30.5), OccupancyConfig(resolution_m=0.1, decay_per_update=decay))
        g.integrate(log.true_poses[log.scan_step], log.scan_ranges_m, log.scan_angles_rad, log.scan_max_range_m)
        near_wall = binary_dilation(rasterize_segments(g, log.walls), np.ones((5, 5), dtype=bool))
        off_wall[decay] = int((g.occupied() & ~near_wall).sum())
    assert off_wall[0.0] > 40 and off_wall[0.02] * 5 < off_wall[0.0], off_wall
