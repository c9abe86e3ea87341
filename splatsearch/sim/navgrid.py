"""Ground-truth navigable grid of a house and FMM geodesic distances (scikit-fmm).

The grid convention is :class:`splatsearch.nav.grid.GridSpec`'s: ``grid[row, col]`` covers
``x in [ox + col*c, ox + (col+1)*c)``, ``y in [oy + row*c, oy + (row+1)*c)``; cell centres are
at +0.5. Cell conversions and the FMM solver are the nav layer's, so ground truth and the
robot's own maps can never disagree on them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import warp as wp
from scipy import ndimage

from splatsearch.nav.fmm import geodesic_distance as _nav_geodesic
from splatsearch.nav.grid import GridSpec

from .house import House

AGENT_RADIUS = 0.17
AGENT_HEIGHT = 1.5
OBSTACLE_MIN_Z = 0.1


@dataclass
class NavGrid:
    """navigable (H, W) bool: the robot centre may be there (obstacles inflated by the radius,
    largest connected floor region); floor (H, W) bool; obstacle (H, W) bool (not inflated)."""

    navigable: np.ndarray
    floor: np.ndarray
    obstacle: np.ndarray
    origin_xy: np.ndarray
    cell_size: float
    agent_radius: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.navigable.shape

    @functools.cached_property
    def spec(self) -> GridSpec:
        """The grid's placement as a :class:`splatsearch.nav.grid.GridSpec` (same convention)."""
        return GridSpec(tuple(self.origin_xy), self.cell_size, self.shape)

    def world_to_cell(self, xy) -> np.ndarray:
        """(..., 2) world x, y in metres -> (..., 2) int (row, col); may be out of bounds."""
        return self.spec.world_to_cell(xy)

    def cell_to_world(self, rc) -> np.ndarray:
        """(..., 2) (row, col) -> (..., 2) world x, y of the cell centres."""
        return self.spec.cell_to_world(rc)

    def in_bounds(self, rc) -> bool:
        r, c = int(rc[0]), int(rc[1])
        return 0 <= r < self.shape[0] and 0 <= c < self.shape[1]

    def is_navigable(self, xy) -> bool:
        rc = self.world_to_cell(xy)
        return self.in_bounds(rc) and bool(self.navigable[rc[0], rc[1]])

    def geodesic_from(self, targets: np.ndarray) -> np.ndarray:
        """FMM geodesic distance (metres) over navigable cells to the nearest target cell.

        targets: (H, W) bool. Returns (H, W) float64; 0 on targets, inf where unreachable.
        """
        return geodesic_distance(self.navigable, targets, self.cell_size)


def geodesic_distance(free: np.ndarray, targets: np.ndarray, cell_size: float) -> np.ndarray:
    """Geodesic distance (m) through ``free`` cells to ``targets`` (scikit-fmm); inf if unreachable.

    The simulator and the robot's planner share one solver: :func:`splatsearch.nav.fmm.geodesic_distance`.
    """
    return _nav_geodesic(free, targets, cell_size)


def _clip_band(tri: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a triangle (3, 3) to lo <= z <= hi; returns (k, 3)."""
    poly = [p for p in tri]
    for sign, bound in ((1, lo), (-1, hi)):
        out = []
        n = len(poly)
        for i in range(n):
            a, b = poly[i], poly[(i + 1) % n]
            ina, inb = sign * (a[2] - bound) >= 0, sign * (b[2] - bound) >= 0
            if ina:
                out.append(a)
            if ina != inb:
                t = (bound - a[2]) / (b[2] - a[2])
                out.append(a + t * (b - a))
        poly = out
        if not poly:
            break
    return np.asarray(poly).reshape(-1, 3)


def build_navgrid(house: House, cell_size: float = 0.05, agent_radius: float = AGENT_RADIUS,
                  agent_height: float = AGENT_HEIGHT, margin: float = 0.5, mesh: wp.Mesh | None = None) -> NavGrid:
    """Rasterise the house's geometry into a navigable grid.

    Obstacles are triangles (clipped to the band ``OBSTACLE_MIN_Z .. agent_height``) projected
    onto the floor; floor is where a downward ray from 0.3 m hits a surface below 5 cm. Works for
    any mesh in the house format, not only generated houses. ``mesh``: the house's ``wp.Mesh`` if
    one exists already (e.g. ``HouseRenderer.mesh``), to avoid building a second BVH.
    """
    if cell_size <= 0 or agent_radius < 0:
        raise ValueError("cell_size must be > 0 and agent_radius >= 0")
    lo, hi = house.bounds
    origin = np.array([lo[0] - margin, lo[1] - margin])
    W = int(np.ceil((hi[0] - lo[0] + 2 * margin) / cell_size))
    H = int(np.ceil((hi[1] - lo[1] + 2 * margin) / cell_size))
    obstacle = np.zeros((H, W), np.uint8)
    V = house.vertices.astype(np.float64)
    tris = V[house.faces]
    zmin, zmax = tris[:, :, 2].min(1), tris[:, :, 2].max(1)
    band = (zmax >= OBSTACLE_MIN_Z) & (zmin <= agent_height)
    scale = 1.0 / cell_size
    shift = 4  # sub-pixel bits for cv2 drawing
    for tri in tris[band]:
        poly = _clip_band(tri, OBSTACLE_MIN_Z, agent_height)
        if len(poly) < 2:
            continue
        pts = np.round(((poly[:, :2] - origin) * scale - 0.5) * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(obstacle, [pts], 1, lineType=cv2.LINE_8, shift=shift)
        cv2.polylines(obstacle, [pts], True, 1, lineType=cv2.LINE_8, shift=shift)
    obstacle = obstacle.astype(bool)
    floor = _floor_mask(house, origin, cell_size, (H, W), mesh)
    dist = ndimage.distance_transform_edt(~obstacle) * cell_size
    nav = floor & ~obstacle & (dist > agent_radius)
    lab, n = ndimage.label(nav)
    if n > 1:
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        nav = lab == int(np.argmax(sizes))
    return NavGrid(nav, floor, obstacle, origin, float(cell_size), float(agent_radius))


@wp.kernel(enable_backward=False)
def _down_kernel(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), hit_z: wp.array(dtype=float)):
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, pts[i], wp.vec3(0.0, 0.0, -1.0), 1.0)
    hit_z[i] = 1.0e9
    if q.result:
        hit_z[i] = pts[i][2] - q.t


def _floor_mask(house: House, origin, cell_size, shape, mesh: wp.Mesh | None) -> np.ndarray:
    H, W = shape
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    xs = origin[0] + (cols + 0.5) * cell_size
    ys = origin[1] + (rows + 0.5) * cell_size
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.3)], -1).astype(np.float32)
    if mesh is None:
        mesh = wp.Mesh(points=wp.array(house.vertices.astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(house.faces.astype(np.int32).ravel(), dtype=wp.int32))
    hit_z = wp.zeros(len(pts), dtype=float, device=mesh.device)
    wp.launch(_down_kernel, dim=len(pts), inputs=[mesh.id, wp.array(pts, dtype=wp.vec3, device=mesh.device)],
              outputs=[hit_z], device=mesh.device)
    return hit_z.numpy().reshape(H, W) < 0.05
