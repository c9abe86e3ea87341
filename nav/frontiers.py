"""Frontiers: free cells next to unknown space, grouped into connected components.

Unknown pockets smaller than ``min_pocket_area`` (1.5 m^2, as in VLFM) count as known, so the
shadow behind a chair leg or the gap under a bed does not attract the robot. Each frontier keeps
its cells and a waypoint, the frontier cell nearest to the component's centroid (its midpoint; for
a straight frontier this is the middle cell). :func:`attach_distances` then keeps only frontiers
the robot can reach and measures their geodesic distance with one FMM field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from .grid import GridSpec, disk, known_bbox
from .occupancy import FREE, OCCUPIED, UNKNOWN

MIN_POCKET_AREA = 1.5  # m^2, VLFM
MIN_FRONTIER_LENGTH = 0.25  # m
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
_EIGHT = np.ones((3, 3), bool)


@dataclass
class Frontier:
    """One frontier. cells: (n, 2) int64 (row, col); waypoint_rc: (2,) int64; waypoint_xy: (2,)
    world metres; distance: geodesic metres from the robot (inf until :func:`attach_distances`);
    approach_rc: the reachable cell the distance was measured at."""

    cells: np.ndarray
    waypoint_rc: np.ndarray
    waypoint_xy: np.ndarray
    distance: float = float("inf")
    approach_rc: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return len(self.cells)


def significant_unknown(state: np.ndarray, cell_size: float, min_pocket_area: float = MIN_POCKET_AREA) -> np.ndarray:
    """(H, W) bool: unknown cells that belong to an unknown region of at least ``min_pocket_area``
    m^2 (4-connected). Regions that reach the edge of the known area are always kept: they continue
    into the unexplored rest of the map."""
    state = np.asarray(state)
    unknown = state == UNKNOWN
    out = unknown.copy()
    bb = known_bbox(~unknown, pad=1)
    if bb is None or min_pocket_area <= 0:
        return out
    sub = unknown[bb]
    lab, n = ndimage.label(sub)
    if n == 0:
        return out
    sizes = np.bincount(lab.ravel(), minlength=n + 1).astype(np.float64)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    sizes[border] = np.inf
    small = sizes * cell_size ** 2 < min_pocket_area
    small[0] = False
    out[bb] = sub & ~small[lab]
    return out


def frontier_cells(state: np.ndarray, cell_size: float, min_pocket_area: float = MIN_POCKET_AREA,
                   wall_clearance: int = 1) -> np.ndarray:
    """(H, W) bool: free cells 4-adjacent to a significant unknown cell and more than
    ``wall_clearance`` cells (8-neighbourhood) from an occupied cell.

    The clearance drops the spurious frontiers along walls seen at grazing angles, whose sampled
    points leave one- or two-cell holes that open onto the unknown space behind the wall; a real
    opening (a doorway) keeps its middle cells.
    """
    state = np.asarray(state)
    if state.ndim != 2:
        raise ValueError(f"state must be a 2-D grid, got shape {state.shape}")
    unk = significant_unknown(state, cell_size, min_pocket_area)
    out = np.zeros(state.shape, bool)
    bb = known_bbox(state != UNKNOWN, pad=1)
    if bb is None:
        return out
    near = cv2.dilate(unk[bb].astype(np.uint8), _CROSS, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    out[bb] = near & (state[bb] == FREE)
    if wall_clearance > 0:
        k = np.ones((2 * wall_clearance + 1,) * 2, np.uint8)
        wall = cv2.dilate((state[bb] == OCCUPIED).astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT,
                          borderValue=0) > 0
        out[bb] &= ~wall
    return out


def extract_frontiers(state: np.ndarray, spec: GridSpec, *, min_cells: int | None = None,
                      min_pocket_area: float = MIN_POCKET_AREA, wall_clearance: int = 1) -> list[Frontier]:
    """Frontiers of an occupancy ``state`` (H, W) uint8 (UNKNOWN/FREE/OCCUPIED) on ``spec``.

    Frontier cells are grouped 8-connected; groups smaller than ``min_cells`` (default: 0.25 m
    worth of cells) are dropped; ``wall_clearance`` as in :func:`frontier_cells`. Returned in no particular order, distances unset.
    """
    state = np.asarray(state)
    if state.shape != spec.shape:
        raise ValueError(f"state shape {state.shape} does not match the grid {spec.shape}")
    if min_cells is None:
        min_cells = max(1, int(np.ceil(MIN_FRONTIER_LENGTH / spec.cell_size)))
    fc = frontier_cells(state, spec.cell_size, min_pocket_area, wall_clearance)
    bb = known_bbox(fc, pad=0)
    if bb is None:
        return []
    lab, _ = ndimage.label(fc[bb], structure=_EIGHT)
    off = np.array([bb[0].start, bb[1].start])
    objs = ndimage.find_objects(lab)
    out = []
    for i, sl in enumerate(objs, start=1):
        cells = np.argwhere(lab[sl] == i) + [sl[0].start, sl[1].start] + off
        if len(cells) < min_cells:
            continue
        mid = cells[np.argmin(((cells - cells.mean(0)) ** 2).sum(1))]
        out.append(Frontier(cells, mid, spec.cell_to_world(mid)))
    return out


def attach_distances(frontiers: list[Frontier], dist: np.ndarray, spec: GridSpec,
                     tolerance: float = 0.25) -> list[Frontier]:
    """Keep the frontiers the robot can reach and set their geodesic distance.

    dist: (H, W) geodesic metres from the robot (inf where unreachable), e.g.
    :meth:`FMMPlanner.distance_from`. A frontier cell counts as reachable if a reachable cell lies
    within ``tolerance`` m of it (frontier cells often sit inside the inflated band along walls,
    where the robot centre may not go but from where it can see across). The waypoint becomes the
    reachable frontier cell nearest to the centroid, and ``distance`` its relaxed geodesic distance
    (reachable cell's distance + the straight hop). Returns a new list; frontiers are updated in place.
    """
    dist = np.asarray(dist)
    if dist.shape != spec.shape:
        raise ValueError(f"dist shape {dist.shape} does not match the grid {spec.shape}")
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    if not frontiers:
        return []
    c = spec.cell_size
    k = int(np.floor(tolerance / c))
    offs = np.argwhere(disk(tolerance / c)) - k
    hop = np.hypot(offs[:, 0], offs[:, 1]) * c
    H, W = spec.shape
    kept = []
    for f in frontiers:
        cand = f.cells[:, None, :] + offs[None]  # (n, m, 2)
        rr = np.clip(cand[..., 0], 0, H - 1)
        cc = np.clip(cand[..., 1], 0, W - 1)
        inside = (cand[..., 0] >= 0) & (cand[..., 0] < H) & (cand[..., 1] >= 0) & (cand[..., 1] < W)
        d = np.where(inside, dist[rr, cc] + hop[None], np.inf)
        j = np.argmin(d, 1)
        best = d[np.arange(len(d)), j]
        ok = np.isfinite(best)
        if not ok.any():
            continue
        cells = f.cells[ok]
        i = int(np.argmin(((cells - f.cells.mean(0)) ** 2).sum(1)))
        sel = np.flatnonzero(ok)[i]
        f.waypoint_rc = f.cells[sel]
        f.waypoint_xy = spec.cell_to_world(f.waypoint_rc)
        f.distance = float(best[sel])
        f.approach_rc = cand[sel, j[sel]]
        kept.append(f)
    return kept
