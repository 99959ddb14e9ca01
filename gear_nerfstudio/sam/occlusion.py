"""Occluding edges of a mask on a rendered depth map (issue 26): how much of a mask's outline lies in front of what
surrounds it. Tracking's click check reads it (`tracking.click`), and the built-in SAM stand-in joins the parts of an
object by it (`builtin_backend`)."""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import ndimage

EDGE_JUMP = 0.1
"""Relative inverse-depth step, beyond the surface's own continuation, that counts as an occluding edge."""
EDGE_OFFSETS = (1, 2, 3)
"""Cells from a mask's edge at which `in_front_share` compares the two sides."""


def _shifted(values: np.ndarray, rows: int, cols: int, fill) -> np.ndarray:
    """out[r, c] = values[r + rows, c + cols], `fill` where that lies outside the grid."""
    height, width = values.shape
    out = np.full_like(values, fill)
    out[max(0, -rows) : min(height, height - rows), max(0, -cols) : min(width, width - cols)] = values[
        max(0, rows) : min(height, height + rows), max(0, cols) : min(width, width + cols)
    ]
    return out


def in_front_share(cells: np.ndarray, depth: np.ndarray) -> Optional[float]:
    """Share of a mask's edge along which the mask lies in front of what surrounds it (an occluding edge).

    `cells` (rows, cols) is the mask on a grid of cells and `depth` (rows, cols) the rendered depth at their
    centres. Each cell inside the mask with a 4-neighbour outside it (within the image) is one step of the
    edge. The surface inside is continued across the edge: the inverse depth of a plane is linear in image
    coordinates, so it is extrapolated from the two inside cells nearest the edge (a wall or a floor seen at
    a grazing angle continues as predicted; a surface behind an object does not). The step is occluding
    when the outside cell is further than both that prediction and the inside cell by more than EDGE_JUMP
    (relative). Masks are decoded on a coarse grid and are often a cell or two too large or too small, so
    the same test is also made 2 and 3 cells away on both sides, and any one of them counts. The depth is
    first median-filtered over 3 x 3 cells: that removes a NeRF's isolated stray depths (rays that slip
    through a thin surface) and keeps its step edges in place; only objects under 3 cells across (less
    than 3/64 of the image on SAM's grid) vanish with it. None when the mask has no edge inside the image
    (empty, or everything).
    """
    return occluding_share(cells, filtered_disparity(depth))


def filtered_disparity(depth: np.ndarray) -> np.ndarray:
    """Inverse depth (rows, cols) after the 3 x 3 median of `in_front_share`."""
    depth = ndimage.median_filter(np.asarray(depth, dtype=np.float64), size=3, mode="nearest")
    return 1.0 / np.maximum(depth, 1e-9)


def occluding_share(cells: np.ndarray, disparity: np.ndarray) -> Optional[float]:
    """`in_front_share` on a `filtered_disparity` map (made once for many masks on one view)."""
    cells = np.asarray(cells, dtype=bool)
    steps = occluding = 0
    for rows, cols in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        edge = cells & _shifted(~cells, rows, cols, False)
        found = np.zeros_like(edge)
        for k in EDGE_OFFSETS:
            outside = _shifted(~cells, k * rows, k * cols, False)
            beyond = _shifted(disparity, k * rows, k * cols, np.nan)
            near_in = _shifted(cells, -(k - 1) * rows, -(k - 1) * cols, False)
            first = _shifted(disparity, -(k - 1) * rows, -(k - 1) * cols, np.nan)
            far_in = _shifted(cells, -k * rows, -k * cols, False)
            second = _shifted(disparity, -k * rows, -k * cols, np.nan)
            predicted = first + (first - second) * (2 * k - 1)  # 2k - 1 cells from `first` to `beyond`
            with np.errstate(invalid="ignore"):
                jump = (beyond < predicted * (1.0 - EDGE_JUMP)) & (beyond < first * (1.0 - EDGE_JUMP))
            found |= edge & outside & near_in & far_in & jump
        steps += int(edge.sum())
        occluding += int(found.sum())
    return None if steps == 0 else occluding / steps
