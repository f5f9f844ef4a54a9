"""An occupancy grid over absurd bounds (a diverged pose at 1e300 m) is refused with a short message."""

from __future__ import annotations

import pytest

from slam2d.maps.occupancy import OccupancyGrid


@pytest.mark.parametrize("bounds", [(0.0, 0.0, 1e300, 1.0), (-1e200, -1e200, 1e200, 1e200), (0.0, 0.0, 1e5, 1e5)])
def test_a_grid_too_large_is_refused_in_a_short_message(bounds: tuple[float, float, float, float]) -> None:
    with pytest.raises(ValueError, match="too large") as e:
        OccupancyGrid(bounds)
    assert len(str(e.value)) < 200, str(e.value)


def test_the_size_limit_counts_whole_cells() -> None:
    assert OccupancyGrid((0.0, 0.0, 10.0, 5.0)).shape == (50, 100)
    OccupancyGrid((0.0, 0.0, 500.0, 1000.0))  # 5000 x 10000 cells: exactly the limit
    with pytest.raises(ValueError, match="too large"):
        OccupancyGrid((0.0, 0.0, 500.01, 1000.0))  # 5001 columns
