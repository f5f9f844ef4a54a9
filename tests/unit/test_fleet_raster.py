"""The joint graph's map-tile rasters draw the newest keyframe per place, so their work follows the mapped area."""

from __future__ import annotations

import numpy as np

from slam2d.fleet.joint import JointGraph


def test_raster_draws_the_newest_keyframe_per_place() -> None:
    """Ten passes over one spot facing east, one facing north, one 3 m away: three places, the newest of each."""
    g = JointGraph()
    g.poses = np.array([[1.2, 1.3, 0.01 * k] for k in range(10)] + [[1.4, 1.1, np.pi / 2], [4.2, 1.3, 0.0]])
    keep = g._newest_per_place(np.arange(len(g.poses)))
    assert keep.tolist() == [9, 10, 11]
