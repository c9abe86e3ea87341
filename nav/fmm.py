"""Fast Marching planner on a traversability grid (scikit-fmm does the solving).

One FMM solve from the robot gives the geodesic distance to every cell, hence to every frontier
(:meth:`FMMPlanner.distance_from`). One solve from a goal region gives a distance field that the
robot descends, either as the next discrete action (``move_forward`` 0.25 m, ``turn_left`` /
``turn_right`` 30 deg, ``stop``) or as a continuous look-ahead waypoint.

Unknown space: the planner only sees the ``traversable`` mask it is given. The exploration planner
passes :meth:`OccupancyGrid.traversable` with ``unknown_is_free=False``, so plans stay in space
the robot has seen free (frontiers are on its edge anyway); pass ``unknown_is_free=True`` there for
optimistic plans through unseen space.

An unreachable goal raises :class:`Unreachable` (or is reported by ``Plan.status``); distances
are ``inf`` where unreachable, never NaN. A goal that stays reachable but that no discrete move
brings closer is reported as status "blocked", so a caller can give it up instead of looping.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from .grid import GridSpec, disk, known_bbox, wrap_angle
from .occupancy import FREE, OCCUPIED

ACTIONS = ("stop", "move_forward", "turn_left", "turn_right")
FORWARD_STEP = 0.25
TURN_DEG = 30.0


class Unreachable(RuntimeError):
    """The goal cannot be reached from the robot through traversable cells."""

    def __init__(self, message: str, goal_xy=None):
        super().__init__(message)
        self.goal_xy = None if goal_xy is None else np.asarray(goal_xy, np.float64)


def geodesic_distance(traversable: np.ndarray, sources: np.ndarray, cell_size: float) -> np.ndarray:
    """Geodesic distance (m) through ``traversable`` cells to the nearest ``sources`` cell.

    traversable, sources: (H, W) bool. Returns (H, W) float64: 0 on traversable sources, the FMM
    distance on cells connected to them, inf everywhere else (obstacles, unreachable islands).
    The solve runs on the bounding box of the traversable cells only.
    """
    traversable = np.asarray(traversable, bool)
    sources = np.asarray(sources, bool)
    if traversable.shape != sources.shape or traversable.ndim != 2:
        raise ValueError(f"traversable {traversable.shape} and sources {sources.shape} must be equal 2-D shapes")
    if not cell_size > 0:
        raise ValueError(f"cell_size must be > 0, got {cell_size}")
    out = np.full(traversable.shape, np.inf)
    src = sources & traversable
    if not src.any():
        return out
    bb = known_bbox(traversable, pad=1)
    free, tgt = traversable[bb], src[bb]
    # FMM fronts move along the axes (4-neighbour stencil): keep only the 4-connected pieces that
    # hold a source, everything else is unreachable
    lab, _ = ndimage.label(free)
    comp = np.isin(lab, np.unique(lab[tgt]))
    phi = np.ma.MaskedArray(np.where(tgt, -1.0, 1.0), mask=~comp)
    sub = np.full(free.shape, np.inf)
    import skfmm  # compiled; imported here so the grid and dataset code load without it

    try:
        d = skfmm.distance(phi, dx=cell_size)
        # the zero level set lies half a cell outside the sources: shift so sources read 0 and a
        # neighbour reads one cell
        vals = np.ma.filled(d, np.inf).astype(np.float64)
        sub = np.where(tgt, 0.0, np.where(comp, np.maximum(vals + 0.5 * cell_size, 0.0), np.inf))
    except ValueError:  # no zero contour: the sources fill their component
        sub = np.where(tgt, 0.0, np.inf)
    sub[~np.isfinite(sub)] = np.inf
    out[bb] = sub
    return out


@dataclass
class Plan:
    """Result of one planning query.

    status: "reached" (robot within the goal region), "moving" (the action brings it closer),
    "squeezing" (the same, but only with the reduced clearance, see ``FMMPlanner.squeeze``),
    "closest" (within one step of the region and no discrete action gets closer: the action is
    "stop"), "unreachable", or "blocked" (reachable, but no discrete move gets closer from here:
    the action turns toward the path; a caller that sees this repeat should give up the goal).
    distance: geodesic metres from the robot to the goal region (inf if unreachable).
    waypoint: (2,) world xy look-ahead point on the path (None unless moving/blocked).
    """

    action: str
    status: str
    distance: float
    waypoint: np.ndarray | None = None


class FMMPlanner:
    """FMM planner over a traversability grid.

    Args:
        spec: grid placement.
        traversable: (H, W) bool, where the robot centre may be (obstacles already inflated).
        blocked: (H, W) bool, raw obstacles; the robot footprint is cleared around the robot
            (it stands there, so those cells are fine for it) except for blocked cells.
        robot_radius: metres, the footprint cleared around the robot.
        forward_step, turn_deg: the discrete action space.
        turn_cost: metres charged per turn when comparing headings; it only breaks ties toward
            fewer turns, the order of headings is set by the distance field.
        free: (H, W) bool, where the robot may be ignoring clearance (e.g. known-free cells);
            with ``blocked`` it enables the squeeze fallback.
        squeeze: when no discrete move with the full clearance gets closer, or the goal cannot be
            reached with it (a passage barely wider than the robot leaves a strip of one or two
            cells that the 30-degree heading lattice cannot follow, or a gap that cell rounding
            closed), plan once more keeping only ``squeeze * robot_radius`` from obstacles; such
            moves report status "squeezing". None disables it. ``distance_from`` and the other
            queries always use the full clearance; ``squeezed()`` gives the reduced one.
    """

    def __init__(self, spec: GridSpec, traversable: np.ndarray, blocked: np.ndarray | None = None, *,
                 free: np.ndarray | None = None, robot_radius: float = 0.17, forward_step: float = FORWARD_STEP,
                 turn_deg: float = TURN_DEG, turn_cost: float = 0.02, squeeze: float | None = 0.5):
        traversable = np.asarray(traversable, bool)
        if traversable.shape != spec.shape:
            raise ValueError(f"traversable shape {traversable.shape} does not match the grid {spec.shape}")
        blocked = np.zeros(spec.shape, bool) if blocked is None else np.asarray(blocked, bool)
        if blocked.shape != spec.shape:
            raise ValueError(f"blocked shape {blocked.shape} does not match the grid {spec.shape}")
        if forward_step <= 0 or not 0 < turn_deg <= 180 or robot_radius < 0:
            raise ValueError("need forward_step > 0, 0 < turn_deg <= 180 and robot_radius >= 0")
        if squeeze is not None and not 0 <= squeeze < 1:
            raise ValueError(f"squeeze must be in [0, 1) or None, got {squeeze}")
        if free is not None:
            free = np.asarray(free, bool)
            if free.shape != spec.shape:
                raise ValueError(f"free shape {free.shape} does not match the grid {spec.shape}")
        self.free = free
        self.squeeze = squeeze if free is not None else None
        self._squeeze: FMMPlanner | None = None
        self.spec = spec
        self.traversable = traversable
        self.blocked = blocked
        self.robot_radius = float(robot_radius)
        self.forward_step = float(forward_step)
        self.turn = float(np.radians(turn_deg))
        self.turn_cost = float(turn_cost)
        self._mask_cache: tuple | None = None
        self._goal_cache: dict = {}

    @classmethod
    def from_occupancy(cls, occupancy, unknown_is_free: bool = False, **kw) -> FMMPlanner:
        """Planner over an :class:`~splatsearch.nav.occupancy.OccupancyGrid` (see
        ``OccupancyGrid.traversable`` for ``unknown_is_free``)."""
        occ = occupancy
        free = (occ.state != OCCUPIED) if unknown_is_free else (occ.state == FREE)
        return cls(occ.spec, occ.traversable(unknown_is_free), occ.occupied, free=free,
                   robot_radius=occ.robot_radius, **kw)

    def squeezed(self) -> FMMPlanner | None:
        """The planner with the reduced clearance (None when the fallback is off)."""
        if self.squeeze is None:
            return None
        if self._squeeze is None:
            r = self.squeeze * self.robot_radius
            k = disk(r / self.spec.cell_size).astype(np.uint8)
            near = cv2.dilate(self.blocked.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
            self._squeeze = FMMPlanner(self.spec, self.free & ~near, self.blocked, robot_radius=self.robot_radius,
                                       forward_step=self.forward_step, turn_deg=np.degrees(self.turn),
                                       turn_cost=self.turn_cost, squeeze=None)
        return self._squeeze

    # -- fields ---------------------------------------------------------------------------
    def mask_for(self, xy) -> np.ndarray:
        """Traversable mask with the robot footprint at ``xy`` cleared (blocked cells excepted)."""
        rc = tuple(self.spec.world_to_cell(np.asarray(xy, np.float64)[:2]))
        if self._mask_cache is not None and self._mask_cache[0] == rc:
            return self._mask_cache[1]
        m = self.traversable.copy()
        rows, cols, disc = self.spec.cells_within(xy, self.robot_radius)
        sub = m[rows, cols]
        sub |= disc & ~self.blocked[rows, cols]
        if self.spec.in_bounds(rc):  # the robot is standing on its own cell, whatever the map says
            m[rc] = True
        self._mask_cache = (rc, m)
        return m

    def distance_from(self, xy) -> np.ndarray:
        """(H, W) geodesic metres from the robot at world ``xy`` to every cell (inf if unreachable)."""
        xy = self._check_xy(xy)
        m = self.mask_for(xy)
        src = np.zeros(self.spec.shape, bool)
        rc = self.spec.world_to_cell(xy)
        if self.spec.in_bounds(rc):
            src[rc[0], rc[1]] = True
        return geodesic_distance(m, src, self.spec.cell_size)

    def goal_region(self, goal_xy, radius: float, mask: np.ndarray) -> np.ndarray:
        """(H, W) bool: cells of ``mask`` within ``radius`` m of ``goal_xy`` (the goal's own cell
        when the radius is below a cell)."""
        out = np.zeros(self.spec.shape, bool)
        rows, cols, disc = self.spec.cells_within(goal_xy, radius)
        out[rows, cols] = disc & mask[rows, cols]
        return out

    def distance_to(self, goal_xy, radius: float = 0.0, robot_xy=None) -> np.ndarray:
        """(H, W) geodesic metres to the goal region (traversable cells within ``radius`` of
        ``goal_xy``); ``robot_xy`` clears the robot footprint first."""
        goal_xy = self._check_xy(goal_xy)
        m = self.mask_for(robot_xy) if robot_xy is not None else self.traversable
        key = (tuple(np.round(goal_xy, 6)), float(radius), id(m))
        hit = self._goal_cache.get(key)
        if hit is not None and hit[0] is m:
            return hit[1]
        d = geodesic_distance(m, self.goal_region(goal_xy, radius, m), self.spec.cell_size)
        self._goal_cache = {key: (m, d)}
        return d

    # -- queries --------------------------------------------------------------------------
    def plan(self, pose, goal_xy, radius: float = 0.5, lookahead: float = 0.75) -> Plan:
        """Plan one step from ``pose`` (x, y, yaw) toward the goal region (traversable cells within
        ``radius`` m of ``goal_xy``); never raises for an unreachable goal (see ``Plan.status``).

        Every heading ``yaw + k * 30 deg`` whose forward step stays in the planning mask is scored by
        the goal distance at its end (plus a small per-turn cost); the best one is either straight
        ahead (``move_forward``) or a turn toward it. The squeeze fallback (see the class) runs
        only when the full clearance offers no step that gets closer.
        """
        pose = self._check_pose(pose)
        if radius < 0:
            raise ValueError(f"radius must be >= 0, got {radius}")
        xy = pose[:2]
        goal_xy = self._check_xy(goal_xy)
        rc = self.spec.world_to_cell(xy)
        if not self.spec.in_bounds(rc):
            return Plan("stop", "unreachable", np.inf)
        mask = self.mask_for(xy)
        D = self.distance_to(goal_xy, radius, robot_xy=xy)
        d0 = float(D[rc[0], rc[1]])
        if d0 == 0.0:
            return Plan("stop", "reached", d0)
        wp = None
        if np.isfinite(d0):
            wp = self._lookahead(xy, D, mask, lookahead)
            best = self._best_heading(pose, D, mask)
            if best is not None and best[1] < d0 - 1e-9:
                return Plan(self._turn_or_go(best[0]), "moving", d0, wp)
            if best is not None and d0 <= radius + self.forward_step:
                return Plan("stop", "closest", d0)
        sq = self.squeezed()
        d2 = np.inf
        if sq is not None:
            m2 = sq.mask_for(xy)
            D2 = sq.distance_to(goal_xy, radius, robot_xy=xy)
            d2 = float(D2[rc[0], rc[1]])
            if d2 == 0.0:
                return Plan("stop", "reached", d2)
            if np.isfinite(d2):
                if wp is None:
                    wp = self._lookahead(xy, D2, m2, lookahead)
                b2 = self._best_heading(pose, D2, m2)
                if b2 is not None and b2[1] < d2 - 1e-9:
                    return Plan(self._turn_or_go(b2[0]), "squeezing", min(d0, d2), wp)
        if wp is None:
            return Plan("stop", "unreachable", np.inf)
        # no discrete move gets closer: rotate toward the path and let the caller notice if this
        # repeats (the exploration planner gives up on the target after a while)
        a = np.arctan2(wp[1] - xy[1], wp[0] - xy[0]) - pose[2]
        a = wrap_angle(a)
        return Plan("turn_left" if a >= 0 else "turn_right", "blocked", min(d0, d2), wp)

    def _best_heading(self, pose: np.ndarray, D: np.ndarray, mask: np.ndarray) -> tuple[int, float] | None:
        """(k, D at the end of the step) of the best heading ``yaw + k * turn`` whose forward step is
        free in ``mask``, ranking by D plus the turn cost; None if no step is free."""
        xy = pose[:2]
        best_k, best_cost, best_d = None, np.inf, np.inf
        n_head = round(2 * np.pi / self.turn)
        for k in range(-((n_head - 1) // 2), n_head // 2 + 1):
            h = pose[2] + k * self.turn
            end = xy + self.forward_step * np.array([np.cos(h), np.sin(h)])
            if not self._segment_free(xy, end, mask):
                continue
            erc = self.spec.world_to_cell(end)
            d = float(D[erc[0], erc[1]])
            if d + abs(k) * self.turn_cost < best_cost - 1e-9:
                best_k, best_cost, best_d = k, d + abs(k) * self.turn_cost, d
        return None if best_k is None else (best_k, best_d)

    @staticmethod
    def _turn_or_go(k: int) -> str:
        return "move_forward" if k == 0 else ("turn_left" if k > 0 else "turn_right")

    def next_action(self, pose, goal_xy, radius: float = 0.5) -> str:
        """One of :data:`ACTIONS` bringing the robot at ``pose`` toward the goal region; "stop" once
        inside it (or when no discrete action gets closer). Raises :class:`Unreachable`."""
        p = self.plan(pose, goal_xy, radius)
        if p.status == "unreachable":
            raise Unreachable(f"goal {np.round(goal_xy, 3).tolist()} is unreachable from "
                              f"{np.round(np.asarray(pose)[:2], 3).tolist()}", goal_xy)
        return p.action

    def path(self, xy, goal_xy, radius: float = 0.0) -> np.ndarray:
        """(N, 2) world xy polyline of cell centres from the robot to the goal region, by steepest
        descent on the goal's distance field. Raises :class:`Unreachable`."""
        xy = self._check_xy(xy)
        D = self.distance_to(goal_xy, radius, robot_xy=xy)
        rc = self.spec.world_to_cell(xy)
        if not self.spec.in_bounds(rc) or not np.isfinite(D[rc[0], rc[1]]):
            raise Unreachable(f"goal {np.round(goal_xy, 3).tolist()} is unreachable", goal_xy)
        return self.spec.cell_to_world(self._descend(rc, D, np.inf))

    def waypoint(self, pose, goal_xy, radius: float = 0.0, lookahead: float = 0.75) -> np.ndarray:
        """(2,) world xy: the farthest point of the path, up to ``lookahead`` m along it, that the
        robot sees in a straight free line; the continuous counterpart of :meth:`next_action`.
        Returns the robot position once it is in the goal region. Raises :class:`Unreachable`."""
        pose = self._check_pose(pose)
        xy = pose[:2]
        D = self.distance_to(goal_xy, radius, robot_xy=xy)
        rc = self.spec.world_to_cell(xy)
        if not self.spec.in_bounds(rc) or not np.isfinite(D[rc[0], rc[1]]):
            raise Unreachable(f"goal {np.round(goal_xy, 3).tolist()} is unreachable", goal_xy)
        return self._lookahead(xy, D, self.mask_for(xy), lookahead)

    # -- helpers --------------------------------------------------------------------------
    def _descend(self, rc, D: np.ndarray, max_len: float) -> np.ndarray:
        H, W = D.shape
        r, c = int(rc[0]), int(rc[1])
        out = [(r, c)]
        length = 0.0
        cs = self.spec.cell_size
        nbrs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
        for _ in range(H * W):
            if D[r, c] == 0.0 or length >= max_len:
                break
            # steepest slope, not largest drop: a diagonal step drops more just by being longer,
            # which would bend straight paths into 45-degree zig-zags
            best, slope = None, 0.0
            for dr, dc in nbrs:
                rr, cc = r + dr, c + dc
                if 0 <= rr < H and 0 <= cc < W and D[rr, cc] < D[r, c]:
                    s = (D[r, c] - D[rr, cc]) / (1.4142135623730951 if dr and dc else 1.0)
                    if s > slope:
                        best, slope = (rr, cc), s
            if best is None:
                break
            length += cs * np.hypot(best[0] - r, best[1] - c)
            r, c = best
            out.append((r, c))
        return np.asarray(out, np.int64)

    def _lookahead(self, xy, D: np.ndarray, mask: np.ndarray, lookahead: float) -> np.ndarray:
        rc = self.spec.world_to_cell(xy)
        cells = self._descend(rc, D, lookahead)
        pts = self.spec.cell_to_world(cells)
        for p in pts[::-1]:
            if self._segment_free(xy, p, mask):
                return p
        return pts[min(1, len(pts) - 1)]

    def _segment_free(self, a, b, mask: np.ndarray) -> bool:
        n = max(2, int(np.ceil(np.hypot(*(np.asarray(b) - a)) / (0.5 * self.spec.cell_size))) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        rc = self.spec.world_to_cell(np.asarray(a)[None] * (1 - t) + np.asarray(b)[None] * t)
        if not np.all(self.spec.in_bounds(rc)):
            return False
        return bool(mask[rc[:, 0], rc[:, 1]].all())

    @staticmethod
    def _check_xy(xy) -> np.ndarray:
        a = np.asarray(xy, np.float64).reshape(-1)
        if a.size < 2 or not np.all(np.isfinite(a[:2])):
            raise ValueError(f"expected a finite world point (x, y), got {xy!r}")
        return a[:2]

    @staticmethod
    def _check_pose(pose) -> np.ndarray:
        p = np.asarray(pose, np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"pose must be finite (x, y, yaw), got {pose!r}")
        return p
