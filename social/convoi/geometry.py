"""2-D geometry shared by the social-navigation layer: frames, capsule obstacles, distance fields.

Frames. World: x, y in metres, z up, yaw counter-clockwise from +x. Robot (CoNVOI III-A): x
forward, y left. A pose is ``(x, y, yaw)``.

Obstacles are *capsules*: a core segment ``(x1, y1, x2, y2)`` grown by a radius ``r`` (row
``(x1, y1, x2, y2, r)``). A wall is a long thin capsule, a pillar a zero-length one. The same
rows drive the pedestrian simulator (wall forces, hard collisions), perception (line of sight)
and the planners (a :class:`DistanceField` rasterised from them).

Grids follow :mod:`splatsearch.nav.grid`: ``grid[row, col]`` covers
``x in [ox + col*c, ox + (col+1)*c)``, ``y in [oy + row*c, oy + (row+1)*c)``; values live at the
cell centres (+0.5).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from splatsearch.nav.grid import GridSpec

F32 = jnp.float32


def world_to_robot(points_xy, pose):
    """(..., 2) world points -> (..., 2) robot frame (x forward, y left) of ``pose`` (3,) (x, y, yaw)."""
    xp = jnp if isinstance(points_xy, jax.Array) or isinstance(pose, jax.Array) else np
    d = points_xy - pose[:2]
    c, s = xp.cos(pose[2]), xp.sin(pose[2])
    return xp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def robot_to_world(points_xy, pose):
    """(..., 2) robot-frame points -> (..., 2) world points for ``pose`` (3,) (x, y, yaw)."""
    xp = jnp if isinstance(points_xy, jax.Array) or isinstance(pose, jax.Array) else np
    c, s = xp.cos(pose[2]), xp.sin(pose[2])
    x, y = points_xy[..., 0], points_xy[..., 1]
    return xp.stack([pose[0] + c * x - s * y, pose[1] + s * x + c * y], -1)


# ---------------------------------------------------------------------------------------------
# capsules
# ---------------------------------------------------------------------------------------------

def check_capsules(capsules) -> np.ndarray:
    """Validate obstacle rows: (S, 5) float32 ``(x1, y1, x2, y2, radius)``, radius >= 0."""
    c = np.asarray(capsules, np.float32)
    if c.ndim != 2 or c.shape[1] != 5:
        raise ValueError(f"capsules must be (S, 5) rows (x1, y1, x2, y2, radius), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("capsules contain NaN or Inf")
    if np.any(c[:, 4] < 0):
        raise ValueError("capsule radii must be >= 0")
    return c


def pad_rows(rows, n: int, dtype=np.float32, *, width: int = 2, what: str = "rows",
             truncate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Pad ``rows`` (M, width) (or None / empty) to (n, width) zeros of ``dtype`` with a validity
    mask (n,), so that jitted code sees one shape. More than ``n`` rows raise a ValueError naming
    ``what``, or are cut to the first ``n`` with ``truncate``."""
    out = np.zeros((n, width), dtype)
    valid = np.zeros(n, bool)
    if rows is None or len(rows) == 0:
        return out, valid
    r = np.asarray(rows, dtype).reshape(-1, width)
    if len(r) > n:
        if not truncate:
            raise ValueError(f"{len(r)} {what} exceed the padded size {n}")
        r = r[:n]
    out[: len(r)] = r
    valid[: len(r)] = True
    return out, valid


def pad_capsules(capsules, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pad (S, 5) capsules to (n, 5) with a validity mask (n,) so that every scenario shares one
    compiled shape. Raises if S > n."""
    c = check_capsules(capsules)
    if len(c) > n:
        raise ValueError(f"{len(c)} capsules do not fit the padded size {n}")
    out = np.zeros((n, 5), np.float32)
    out[: len(c)] = c
    valid = np.zeros(n, bool)
    valid[: len(c)] = True
    return out, valid


def point_segment_distance(p, a, b):
    """Distance (m) from points ``p`` (..., 2) to segments ``a``-``b`` (..., 2) (broadcasting),
    plus the closest point (..., 2). Zero-length segments are points."""
    ab = b - a
    denom = jnp.maximum(jnp.sum(ab * ab, -1), 1e-12)
    t = jnp.clip(jnp.sum((p - a) * ab, -1) / denom, 0.0, 1.0)
    q = a + t[..., None] * ab
    return jnp.linalg.norm(p - q, axis=-1), q


def capsule_distance(p, capsules, valid=None):
    """Signed clearance (m) of points ``p`` (..., 2) to the nearest capsule surface, and the unit
    direction (..., 2) pointing from that surface to the point (the push-out direction).

    capsules: (S, 5); valid: optional (S,) bool. With no valid capsule the clearance is +1e6.
    """
    a = capsules[:, 0:2]
    b = capsules[:, 2:4]
    r = capsules[:, 4]
    pe = p[..., None, :]
    d, q = point_segment_distance(pe, a, b)  # (..., S)
    surf = d - r
    if valid is not None:
        surf = jnp.where(valid, surf, 1e6)
    k = jnp.argmin(surf, -1)
    best = jnp.take_along_axis(surf, k[..., None], -1)[..., 0]
    qk = jnp.take_along_axis(q, k[..., None, None], -2)[..., 0, :]
    diff = p - qk
    n = diff / jnp.maximum(jnp.linalg.norm(diff, axis=-1, keepdims=True), 1e-9)
    return best, n


def _cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def segment_segment_distance(p1, p2, q1, q2):
    """Distance (m) between segments p1-p2 and q1-q2 (all (..., 2), broadcasting); 0 when they cross."""
    d1 = p2 - p1
    d2 = q2 - q1
    o1 = _cross(d1, q1 - p1)
    o2 = _cross(d1, q2 - p1)
    o3 = _cross(d2, p1 - q1)
    o4 = _cross(d2, p2 - q1)
    crosses = (o1 * o2 < 0) & (o3 * o4 < 0)
    m = jnp.minimum(jnp.minimum(point_segment_distance(p1, q1, q2)[0], point_segment_distance(p2, q1, q2)[0]),
                    jnp.minimum(point_segment_distance(q1, p1, p2)[0], point_segment_distance(q2, p1, p2)[0]))
    return jnp.where(crosses, 0.0, m)


def line_of_sight(a, b, capsules, valid=None, shrink: float = 0.0):
    """Whether the straight line a-b ((..., 2) each) misses every capsule (grown by ``-shrink``).

    Used for perception (can the robot see a person?). Returns (...) bool.
    """
    p1 = a[..., None, :]
    p2 = b[..., None, :]
    d = segment_segment_distance(p1, p2, capsules[:, 0:2], capsules[:, 2:4]) - (capsules[:, 4] - shrink)
    hit = d < 0
    if valid is not None:
        hit = hit & valid
    return ~jnp.any(hit, -1)


# ---------------------------------------------------------------------------------------------
# distance fields
# ---------------------------------------------------------------------------------------------

class DistanceField(NamedTuple):
    """Clearance map: metres from each cell centre to the nearest obstacle surface (<= 0 inside).

    values: (H, W) float32; origin: (2,) float32 world x, y of cell (0, 0)'s corner; cell: ()
    float32 cell size in metres. A pytree: pass it straight into jitted functions.
    """

    values: jax.Array
    origin: jax.Array
    cell: jax.Array

    @property
    def spec(self) -> GridSpec:
        """The :class:`GridSpec` of this field."""
        o = np.asarray(self.origin, np.float64)
        return GridSpec((float(o[0]), float(o[1])), float(self.cell), tuple(int(s) for s in self.values.shape))


def distance_field_from_capsules(capsules, spec: GridSpec, chunk: int = 65536) -> DistanceField:
    """Exact clearance field of capsule obstacles on the cells of ``spec``.

    capsules: (S, 5) rows (x1, y1, x2, y2, radius) in metres. Cells farther than any obstacle
    read the true distance; with no obstacle at all every cell reads 1e6.
    """
    caps = check_capsules(capsules)
    H, W = spec.shape
    rc = np.stack(np.meshgrid(np.arange(H), np.arange(W), indexing="ij"), -1).reshape(-1, 2)
    xy = spec.cell_to_world(rc).astype(np.float32)
    if len(caps) == 0:
        vals = np.full(H * W, 1e6, np.float32)
    else:
        a, b, r = caps[:, :2], caps[:, 2:4], caps[:, 4]
        out = []
        for s in range(0, len(xy), chunk):
            p = xy[s:s + chunk, None, :]
            ab = b - a
            t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-12), 0, 1)
            d = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1) - r
            out.append(d.min(1))
        vals = np.concatenate(out).astype(np.float32)
    return DistanceField(jnp.asarray(vals.reshape(H, W)), jnp.asarray(spec.origin_xy, F32),
                         jnp.asarray(spec.cell_size, F32))


def distance_field_from_occupancy(occupied: np.ndarray, spec: GridSpec) -> DistanceField:
    """Clearance field of an occupancy grid (H, W) bool (True = obstacle), e.g. the nav layer's
    ``OccupancyGrid.occupied``. Distances are Euclidean from cell centre to the nearest occupied
    cell's edge (OpenCV's exact L2 transform minus half a cell); occupied cells read -c/2."""
    occ = np.asarray(occupied, bool)
    if occ.shape != spec.shape:
        raise ValueError(f"occupancy shape {occ.shape} does not match the grid {spec.shape}")
    if not occ.any():
        vals = np.full(occ.shape, 1e6, np.float32)
    else:
        d = cv2.distanceTransform((~occ).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        vals = np.where(occ, -0.5, d - 0.5).astype(np.float32) * spec.cell_size
    return DistanceField(jnp.asarray(vals), jnp.asarray(spec.origin_xy, F32), jnp.asarray(spec.cell_size, F32))


def field_lookup(field: DistanceField, xy):
    """Bilinear clearance (m) at world points ``xy`` (..., 2). Points outside the grid read
    -1 (unknown space is treated as blocked, so planners never leave the map)."""
    H, W = field.values.shape
    g = (xy - field.origin) / field.cell - 0.5  # continuous (col, row) of cell centres
    c, r = g[..., 0], g[..., 1]
    inside = (c >= -0.5) & (c <= W - 0.5) & (r >= -0.5) & (r <= H - 0.5)
    c = jnp.clip(c, 0.0, W - 1.0)
    r = jnp.clip(r, 0.0, H - 1.0)
    c0 = jnp.clip(jnp.floor(c).astype(jnp.int32), 0, W - 2)
    r0 = jnp.clip(jnp.floor(r).astype(jnp.int32), 0, H - 2)
    fc = c - c0
    fr = r - r0
    v = field.values
    val = ((1 - fr) * ((1 - fc) * v[r0, c0] + fc * v[r0, c0 + 1])
           + fr * ((1 - fc) * v[r0 + 1, c0] + fc * v[r0 + 1, c0 + 1]))
    return jnp.where(inside, val, -1.0)


def occupancy_from_field(field: DistanceField, inflate: float = 0.0) -> np.ndarray:
    """(H, W) bool: cells whose clearance is below ``inflate`` metres (obstacles grown by it)."""
    return np.asarray(field.values) < inflate
