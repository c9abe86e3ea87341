"""What the robot perceives: visible people, groups among them, and its local occupancy map.

* :func:`visible_people` (JAX): people within range whose line of sight from the robot misses
  every wall (a blind corner hides people until it does not).
* :func:`detect_groups`: people closer than ``link`` metres to each other with similar velocities,
  linked transitively (single-linkage); a cheap stand-in for a group detector.
* :func:`local_occupancy`: CoNVOI's n x n robot-centric occupancy map O_t (III-A): the static
  clearance field and the detected people, obstacles inflated by the robot radius, as a grid in
  the robot frame (x forward along columns, y left along rows; robot at the centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from splatsearch.nav.grid import GridSpec

from .geometry import DistanceField, line_of_sight


@jax.jit
def visible_people(pose, pos, active, capsules, capsules_valid, max_range=8.0):
    """(P,) bool: active people within ``max_range`` m of the robot ``pose`` (3,) whose centre
    the robot sees in a straight line past the capsule obstacles. pos: (P, 2)."""
    d = jnp.linalg.norm(pos - pose[:2], axis=-1)
    los = line_of_sight(jnp.broadcast_to(pose[:2], pos.shape), pos, capsules, capsules_valid)
    return active & (d <= max_range) & los


def detect_groups(pos: np.ndarray, vel: np.ndarray, link: float = 1.6, max_dv: float = 0.4) -> np.ndarray:
    """(n,) int group labels (-1 = alone) of people at pos (n, 2) m moving at vel (n, 2) m/s:
    pairs within ``link`` m whose velocities differ by less than ``max_dv`` m/s are joined."""
    pos = np.asarray(pos, np.float64).reshape(-1, 2)
    vel = np.asarray(vel, np.float64).reshape(-1, 2)
    n = len(pos)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for k in range(i + 1, n):
            if np.linalg.norm(pos[i] - pos[k]) < link and np.linalg.norm(vel[i] - vel[k]) < max_dv:
                parent[find(i)] = find(k)
    roots = [find(i) for i in range(n)]
    labels = np.full(n, -1, np.int64)
    next_id = 0
    for r in sorted(set(roots)):
        members = [i for i in range(n) if roots[i] == r]
        if len(members) > 1:
            labels[members] = next_id
            next_id += 1
    return labels


def group_pairs(labels: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """(G, 2) int pairs of people (indices into ``index``, default 0..n-1) in the same group."""
    labels = np.asarray(labels)
    idx = np.arange(len(labels)) if index is None else np.asarray(index)
    out = []
    for g in sorted(set(labels[labels >= 0].tolist())):
        m = idx[labels == g]
        out += [(int(a), int(b)) for k, a in enumerate(m) for b in m[k + 1:]]
    return np.asarray(out, np.int64).reshape(-1, 2)


@dataclass(frozen=True)
class LocalMap:
    """Robot-centric occupancy O_t: ``occupied`` (n, n) bool in the robot frame (grid rows along
    +y (left), columns along +x (forward), robot at the centre), obstacles inflated by
    ``inflate`` m; ``spec`` places it in the robot frame; ``clearance`` (n, n) metres to the
    nearest obstacle (static or person), before inflation."""

    occupied: np.ndarray
    clearance: np.ndarray
    spec: GridSpec
    inflate: float

    def free_at(self, xy_robot) -> np.ndarray:
        """(...,) bool: robot-frame points (..., 2) inside the map and not occupied."""
        rc = self.spec.world_to_cell(np.asarray(xy_robot, np.float64))
        ok = self.spec.in_bounds(rc)
        ok = np.asarray(ok)
        out = np.zeros(ok.shape, bool)
        r = np.clip(rc[..., 0], 0, self.spec.shape[0] - 1)
        c = np.clip(rc[..., 1], 0, self.spec.shape[1] - 1)
        out[...] = ok & ~self.occupied[r, c]
        return out

    def clearance_at(self, xy_robot) -> np.ndarray:
        """(...,) clearance (m) at robot-frame points (0 outside the map)."""
        rc = self.spec.world_to_cell(np.asarray(xy_robot, np.float64))
        ok = np.asarray(self.spec.in_bounds(rc))
        r = np.clip(rc[..., 0], 0, self.spec.shape[0] - 1)
        c = np.clip(rc[..., 1], 0, self.spec.shape[1] - 1)
        return np.where(ok, self.clearance[r, c], 0.0)


#: module-level cache: (n, cell) -> (GridSpec, (n, n, 2) cell centres in the robot frame). The
#: grids depend only on their size, so they are built once per process; a few entries at most.
_CELL_CACHE: dict = {}


def _robot_cells(n: int, cell: float) -> tuple[GridSpec, np.ndarray]:
    key = (n, cell)
    if key not in _CELL_CACHE:
        spec = GridSpec.centered((0.0, 0.0), (n, n), cell)
        rc = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1)
        _CELL_CACHE[key] = (spec, spec.cell_to_world(rc).astype(np.float32))
    return _CELL_CACHE[key]


def local_maps(field: DistanceField, pose, people_xy=None, *, n: int = 200, cell: float = 0.05,
               inflate: float = 0.25, person_radius: float = 0.25) -> tuple[LocalMap, LocalMap]:
    """CoNVOI's O_t twice: without people (the static layout) and with the detected ``people_xy``
    (k, 2) world centres; an ``n`` x ``n`` grid of ``cell`` m around the robot at ``pose`` (3,)
    sampled from the world clearance ``field`` (nearest cell; outside the field reads 0)."""
    if n < 4 or cell <= 0:
        raise ValueError(f"need n >= 4 and cell > 0, got {n}, {cell}")
    spec, rob = _robot_cells(n, cell)
    pose = np.asarray(pose, np.float64)
    c, s = np.float32(np.cos(pose[2])), np.float32(np.sin(pose[2]))
    wx = pose[0] + c * rob[..., 0] - s * rob[..., 1]
    wy = pose[1] + s * rob[..., 0] + c * rob[..., 1]
    fs = field.spec
    vals = np.asarray(field.values)
    col = np.floor((wx - fs.origin_xy[0]) / fs.cell_size).astype(np.int64)
    row = np.floor((wy - fs.origin_xy[1]) / fs.cell_size).astype(np.int64)
    inside = (row >= 0) & (row < fs.shape[0]) & (col >= 0) & (col < fs.shape[1])
    static = np.where(inside, vals[np.clip(row, 0, fs.shape[0] - 1), np.clip(col, 0, fs.shape[1] - 1)],
                      0.0).astype(np.float32)
    full = static
    if people_xy is not None and len(people_xy):
        d2 = np.full(static.shape, np.inf, np.float32)
        for p in np.asarray(people_xy, np.float64).reshape(-1, 2):
            d2 = np.minimum(d2, (wx - np.float32(p[0])) ** 2 + (wy - np.float32(p[1])) ** 2)
        full = np.minimum(static, np.sqrt(d2) - np.float32(person_radius))
    return (LocalMap(static < inflate, static, spec, float(inflate)),
            LocalMap(full < inflate, full, spec, float(inflate)))


def local_occupancy(field: DistanceField, pose, people_xy=None, *, n: int = 200, cell: float = 0.05,
                    inflate: float = 0.25, person_radius: float = 0.25) -> LocalMap:
    """CoNVOI's O_t: an ``n`` x ``n`` grid of ``cell`` m around the robot at ``pose`` (3,) from the
    world clearance ``field`` and the detected ``people_xy`` (k, 2) world centres."""
    return local_maps(field, pose, people_xy, n=n, cell=cell, inflate=inflate, person_radius=person_radius)[1]
