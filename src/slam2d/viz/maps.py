"""Map images: occupancy grids as PNG (optionally with the trajectory drawn in)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import ArrayLike

from slam2d.maps.occupancy import OccupancyGrid


def save_occupancy_png(grid: OccupancyGrid, path: str | Path, trajectory: ArrayLike | None = None) -> Path:
    """Write the grid as a greyscale PNG, one pixel per cell, north up (occupied black, free white, unknown grey).

    With ``trajectory`` (N,2+) the path is drawn in red, one pixel wide. Returns the path.
    """
    path = Path(path)
    img = np.repeat(grid.image()[..., None], 3, axis=2)
    if trajectory is not None:
        xy = np.asarray(trajectory, dtype=np.float64)[:, :2]
        # dense resampling so the drawn path has no gaps between poses
        seg = np.hypot(*np.diff(xy, axis=0).T)
        n = np.maximum(np.ceil(seg / (0.5 * grid.resolution)).astype(int), 1)
        t = np.concatenate([np.linspace(0, 1, k, endpoint=False) for k in n]) if len(n) else np.zeros(0)
        i0 = np.repeat(np.arange(len(n)), n)
        pts = xy[i0] + t[:, None] * (xy[i0 + 1] - xy[i0]) if len(n) else xy
        flat, inside = grid.cell_index(pts)
        r, c = np.unravel_index(flat[inside], grid.shape)
        img[r, c] = (220, 30, 30)
    plt.imsave(path, img[::-1], format="png")
    return path
