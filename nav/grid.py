"""Grid geometry shared by every map of the navigation layer.

Convention (identical to :mod:`splatsearch.sim.navgrid`): ``grid[row, col]`` covers the world
square ``x in [ox + col*c, ox + (col+1)*c)``, ``y in [oy + row*c, oy + (row+1)*c)`` with
``origin_xy = (ox, oy)`` and ``cell_size = c`` metres; cell centres sit at +0.5. Rows follow +y
and columns follow +x, so an image view of a grid is mirrored vertically relative to a map
plotted with y up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_CELL_SIZE = 0.05
DEFAULT_SHAPE = (1000, 1000)


@dataclass(frozen=True)
class GridSpec:
    """Placement of a 2-D grid in the world.

    origin_xy: (2,) world x, y (m) of the corner of cell (0, 0); cell_size: metres per cell;
    shape: (rows, cols).
    """

    origin_xy: tuple[float, float]
    cell_size: float = DEFAULT_CELL_SIZE
    shape: tuple[int, int] = DEFAULT_SHAPE

    def __post_init__(self):
        o = np.asarray(self.origin_xy, np.float64).reshape(-1)
        if o.shape != (2,) or not np.all(np.isfinite(o)):
            raise ValueError(f"origin_xy must be two finite numbers, got {self.origin_xy!r}")
        if not np.isfinite(self.cell_size) or self.cell_size <= 0:
            raise ValueError(f"cell_size must be a positive number of metres, got {self.cell_size!r}")
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 2 or min(shape) <= 0:
            raise ValueError(f"shape must be two positive ints (rows, cols), got {self.shape!r}")
        object.__setattr__(self, "origin_xy", (float(o[0]), float(o[1])))
        object.__setattr__(self, "cell_size", float(self.cell_size))
        object.__setattr__(self, "shape", shape)

    @classmethod
    def centered(cls, center_xy, shape: tuple[int, int] = DEFAULT_SHAPE,
                 cell_size: float = DEFAULT_CELL_SIZE) -> GridSpec:
        """A grid of ``shape`` cells whose centre is at world ``center_xy`` (m)."""
        c = np.asarray(center_xy, np.float64).reshape(-1)[:2]
        rows, cols = int(shape[0]), int(shape[1])
        return cls((float(c[0] - 0.5 * cols * cell_size), float(c[1] - 0.5 * rows * cell_size)), cell_size,
                   (rows, cols))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in metres."""
        ox, oy = self.origin_xy
        return ox, oy, ox + self.shape[1] * self.cell_size, oy + self.shape[0] * self.cell_size

    def world_to_cell(self, xy) -> np.ndarray:
        """(..., 2) world x, y in metres -> (..., 2) int64 (row, col); may be out of bounds."""
        xy = np.asarray(xy, np.float64)
        col = np.floor((xy[..., 0] - self.origin_xy[0]) / self.cell_size)
        row = np.floor((xy[..., 1] - self.origin_xy[1]) / self.cell_size)
        return np.stack([row, col], -1).astype(np.int64)

    def cell_to_world(self, rc) -> np.ndarray:
        """(..., 2) (row, col) -> (..., 2) float64 world x, y of the cell centres."""
        rc = np.asarray(rc, np.float64)
        return np.stack([self.origin_xy[0] + (rc[..., 1] + 0.5) * self.cell_size,
                         self.origin_xy[1] + (rc[..., 0] + 0.5) * self.cell_size], -1)

    def in_bounds(self, rc) -> np.ndarray | bool:
        """Whether (..., 2) (row, col) lies inside the grid (bool array, or bool for one cell)."""
        rc = np.asarray(rc)
        ok = (rc[..., 0] >= 0) & (rc[..., 0] < self.shape[0]) & (rc[..., 1] >= 0) & (rc[..., 1] < self.shape[1])
        return bool(ok) if ok.ndim == 0 else ok

    def cells_within(self, xy, radius: float) -> tuple[slice, slice, np.ndarray]:
        """Cells whose centres lie within ``radius`` m of world ``xy``.

        Returns (row slice, col slice, mask) where ``mask`` (h, w) bool covers the clipped window
        ``grid[rows, cols]``; the window is empty when the disc is entirely outside the grid.
        """
        if radius < 0:
            raise ValueError(f"radius must be >= 0, got {radius}")
        c = self.cell_size
        x, y = float(xy[0]), float(xy[1])
        r = int(np.ceil(radius / c)) + 1
        rc = self.world_to_cell([x, y])
        r0, r1 = max(0, rc[0] - r), min(self.shape[0], rc[0] + r + 1)
        c0, c1 = max(0, rc[1] - r), min(self.shape[1], rc[1] + r + 1)
        if r0 >= r1 or c0 >= c1:
            return slice(0, 0), slice(0, 0), np.zeros((0, 0), bool)
        ys = self.origin_xy[1] + (np.arange(r0, r1) + 0.5) * c
        xs = self.origin_xy[0] + (np.arange(c0, c1) + 0.5) * c
        mask = (ys[:, None] - y) ** 2 + (xs[None, :] - x) ** 2 <= radius ** 2 + 1e-12
        if not mask.any() and self.in_bounds(rc):  # a tiny radius still means "the point's cell"
            mask[rc[0] - r0, rc[1] - c0] = True
        return slice(r0, r1), slice(c0, c1), mask


def wrap_angle(a):
    """Angle(s) in radians wrapped to [-pi, pi); works on floats, numpy and JAX arrays."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def disk(radius_cells: float) -> np.ndarray:
    """(2k+1, 2k+1) bool structuring element of cell centres within ``radius_cells`` of the middle."""
    k = int(np.floor(max(radius_cells, 0.0)))
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    return xx * xx + yy * yy <= radius_cells * radius_cells + 1e-9


def known_bbox(known: np.ndarray, pad: int = 1) -> tuple[slice, slice] | None:
    """Bounding box of the True cells of ``known`` (H, W), padded by ``pad`` cells and clipped to the
    grid, as (row slice, col slice); None when nothing is known."""
    rows = np.flatnonzero(known.any(1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(known.any(0))
    H, W = known.shape
    return (slice(max(0, rows[0] - pad), min(H, rows[-1] + pad + 1)),
            slice(max(0, cols[0] - pad), min(W, cols[-1] + pad + 1)))
