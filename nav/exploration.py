"""Exploration planner: which frontier next (thesis eq 19-20) and the action that heads there.

eq 19: ``f* = argmax_f  alpha * d_t(f) + beta * E_t(f) + delta * V_t(f)`` with
  * ``d_t(f)``: normalised inverse geodesic distance, ``min_f' D(f') / D(f)`` (1 for the nearest
    frontier, toward 0 for far ones);
  * ``E_t(f)`` (eq 20): ``(1/C) max_i e_max_i / (tau_m ||f - mu_i||)`` over the objects the feature
    matcher scored; ``C`` defaults to the largest raw value over the frontiers, so E is in [0, 1];
  * ``V_t(f)``: the value map's mean (or median / max) within ``r_val`` of the frontier waypoint,
    min-max normalised over the frontiers by default (embedding cosines sit in a narrow band).

:class:`ExplorationPlanner` ties the occupancy grid, frontiers, value map and FMM planner together:
``observe`` once per frame (with the action the robot took to get there), then ``act`` once for
the next discrete action: toward the best frontier, or toward a goal region the caller names (the
FMM planner over the current map is built once per ``act``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .encoders import ImageEncoder, cosine
from .fmm import FMMPlanner, Plan
from .frontiers import MIN_POCKET_AREA, Frontier, attach_distances, extract_frontiers
from .grid import GridSpec, wrap_angle
from .occupancy import OCCUPIED, UNKNOWN, OccupancyGrid
from .value_map import R_VAL, ValueMap


@dataclass
class ObjectScore:
    """A candidate object for eq 20: centroid ``xy`` (world metres; a 3-D centroid is fine, only
    x, y are used) and its best feature-match count ``e_max``."""

    xy: np.ndarray
    e_max: float


def inverse_distance_score(distances) -> np.ndarray:
    """d_t(f) of eq 19: (N,) geodesic metres -> (N,) in [0, 1]: ``min(D) / D``; 0 for inf.
    Distances below 1 cm count as 1 cm (the robot is on the frontier)."""
    d = np.asarray(distances, np.float64).reshape(-1)
    if np.any(np.isnan(d)) or np.any(d < 0):
        raise ValueError("distances must be >= 0 and not NaN")
    out = np.zeros(len(d))
    fin = np.isfinite(d)
    if fin.any():
        dd = np.maximum(d[fin], 0.01)
        out[fin] = dd.min() / dd
    return out


def object_score(frontier_xy, objects: list[ObjectScore], tau_m: float = 1.0, C: float | None = None,
                 min_distance: float = 0.1) -> np.ndarray:
    """E_t(f) of eq 20 for (N, 2) frontier points -> (N,) float64.

    ``max_i e_max_i / (tau_m * ||f - mu_i||)`` divided by ``C``; ``C=None`` uses the largest value
    over the frontiers (so the best frontier scores 1). Distances are clamped to ``min_distance``
    m. Zeros when there are no objects.
    """
    f = np.asarray(frontier_xy, np.float64).reshape(-1, 2)
    if tau_m <= 0:
        raise ValueError(f"tau_m must be > 0, got {tau_m}")
    if C is not None and C <= 0:
        raise ValueError(f"C must be > 0, got {C}")
    if not len(objects) or not len(f):
        return np.zeros(len(f))
    mu = np.stack([np.asarray(o.xy, np.float64).reshape(-1)[:2] for o in objects])
    e = np.array([float(o.e_max) for o in objects])
    dist = np.maximum(np.linalg.norm(f[:, None, :] - mu[None], axis=-1), min_distance)
    raw = (e[None] / (tau_m * dist)).max(1)
    c = raw.max() if C is None else C
    return raw / c if c > 0 else np.zeros(len(f))


def normalise(values, mode: str = "minmax") -> np.ndarray:
    """Scale frontier values for eq 19: "minmax" to [0, 1] over the frontiers (all 0 if they are
    equal), "none" to leave them."""
    v = np.asarray(values, np.float64).reshape(-1)
    if mode == "none":
        return v
    if mode != "minmax":
        raise ValueError(f"mode must be 'minmax' or 'none', got {mode!r}")
    if not len(v):
        return v
    span = v.max() - v.min()
    return (v - v.min()) / span if span > 1e-12 else np.zeros_like(v)


def utility(d, E, V, alpha: float = 1.0, beta: float = 0.0, delta: float = 0.0) -> np.ndarray:
    """eq 19's bracket: ``alpha * d + beta * E + delta * V`` (all (N,))."""
    d, E, V = (np.asarray(a, np.float64).reshape(-1) for a in (d, E, V))
    if not len(d) == len(E) == len(V):
        raise ValueError(f"d, E and V must have equal length, got {len(d)}, {len(E)}, {len(V)}")
    return alpha * d + beta * E + delta * V


@dataclass
class ExplorationConfig:
    """Weights of eq 19 and the knobs of the exploration loop.

    alpha, beta, delta: eq 19 weights. tau_m, C: eq 20 (``C=None``: normalise by the max).
    r_val, value_reduce, value_norm: frontier value (eq text; "mean" per the thesis).
    min_pocket_area (m^2), min_frontier_cells, reach_tolerance (m): frontier extraction.
    arrive_radius: m from the waypoint at which a frontier counts as visited.
    initial_turns: turns in place before the first move (12 x 30 deg = a full look around).
    stuck_steps: steps without getting 0.1 m closer before the target is blacklisted. Also: steps
        in which the robot stays within 0.5 m of one spot while exploring before the frontier it
        is heading for is blacklisted, whichever targets it switched between meanwhile.
    max_look_turns: turns spent facing a frontier's unknown side on arrival before blacklisting it.
    blacklist_radius: frontiers whose waypoint lies this close to a blacklisted one are skipped.
    switch_margin: utility a new frontier must win by to replace the current target.
    unknown_is_free: plan through unknown cells (optimistic) instead of seen-free ones only.
    """

    alpha: float = 1.0
    beta: float = 0.0
    delta: float = 0.0
    tau_m: float = 1.0
    C: float | None = None
    r_val: float = R_VAL
    value_reduce: str = "mean"
    value_norm: str = "minmax"
    min_pocket_area: float = MIN_POCKET_AREA
    min_frontier_cells: int | None = None
    reach_tolerance: float = 0.25
    arrive_radius: float = 0.5
    initial_turns: int = 12
    stuck_steps: int = 25
    max_look_turns: int = 6
    blacklist_radius: float = 0.5
    switch_margin: float = 0.05
    unknown_is_free: bool = False

    def __post_init__(self):
        if min(self.alpha, self.beta, self.delta) < 0:
            raise ValueError("alpha, beta and delta must be >= 0")
        if self.value_reduce not in ("mean", "median", "max"):
            raise ValueError(f"value_reduce must be 'mean', 'median' or 'max', got {self.value_reduce!r}")
        if self.value_norm not in ("minmax", "none"):
            raise ValueError(f"value_norm must be 'minmax' or 'none', got {self.value_norm!r}")
        if self.arrive_radius < self.reach_tolerance:
            raise ValueError("arrive_radius must be >= reach_tolerance (the waypoint may sit that far "
                             "from the nearest cell the robot can stand on)")


@dataclass
class Decision:
    """What :meth:`ExplorationPlanner.act` chose: ``action`` (one of the discrete actions),
    ``status`` ("look_around", "exploring", "looking", "explored", "blocked", or "goal" when
    ``action`` heads for the caller's goal region), the target frontier, and all reachable
    frontiers scored this step (their ``info`` holds d, E, V and utility). With a goal region:
    ``goal`` is the FMM :class:`~splatsearch.nav.fmm.Plan` toward it and ``goal_path`` its path
    (P, 2) world metres (empty when there is none)."""

    action: str
    status: str
    target: Frontier | None = None
    frontiers: list[Frontier] = field(default_factory=list)
    goal: Plan | None = None
    goal_path: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


class ExplorationPlanner:
    """Frontier exploration with the eq 19 utility, over an occupancy grid and a value map.

    Args:
        spec: grid placement (default 1000 x 1000 cells of 5 cm around the start, see
            :meth:`GridSpec.centered`).
        config: :class:`ExplorationConfig`.
        occupancy: an :class:`OccupancyGrid` on ``spec`` (built with defaults if None).
        value_map: a :class:`ValueMap` on ``spec`` (built with defaults if None).
        encoder: :class:`ImageEncoder` for eq 11; needed only if a goal image is set.
        forward_step, turn_deg: the robot's discrete action space.
    """

    def __init__(self, spec: GridSpec, config: ExplorationConfig | None = None, *,
                 occupancy: OccupancyGrid | None = None, value_map: ValueMap | None = None,
                 encoder: ImageEncoder | None = None, forward_step: float = 0.25, turn_deg: float = 30.0):
        self.spec = spec
        self.config = config or ExplorationConfig()
        self.occupancy = occupancy if occupancy is not None else OccupancyGrid(spec)
        self.value_map = value_map if value_map is not None else ValueMap(spec)
        if self.occupancy.spec != spec or self.value_map.spec != spec:
            raise ValueError("occupancy grid and value map must use the planner's GridSpec")
        self.encoder = encoder
        self.forward_step = float(forward_step)
        self.turn_deg = float(turn_deg)
        self.goal_embedding: np.ndarray | None = None
        self.blacklist: list[np.ndarray] = []
        self.last_value: float | None = None
        self._turns_left = int(self.config.initial_turns)
        self._target: Frontier | None = None
        self._best_dist = np.inf
        self._since_progress = 0
        self._look_turns = 0
        self._optimistic_planner: FMMPlanner | None = None
        self._anchor_xy: np.ndarray | None = None
        self._still_steps = 0
        self._last_action: str | None = None
        self._last_pose: np.ndarray | None = None

    # -- sensing --------------------------------------------------------------------------
    def set_goal_image(self, rgb: np.ndarray) -> None:
        """Embed the goal image (eq 11's e_g); needs an encoder."""
        if self.encoder is None:
            raise ValueError("set_goal_image needs an encoder (e.g. ColorTextureEncoder())")
        self.goal_embedding = np.asarray(self.encoder.embed(rgb), np.float32)

    def observe(self, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, pose, rgb: np.ndarray | None = None,
                action: str | None = None):
        """Fuse one frame: depth (H, W) m, viewmat (4, 4) world-to-camera, K (3, 3), robot pose
        (x, y, yaw), and optionally rgb (H, W, 3) for the value map (used once a goal image is
        set). ``action``: the action the robot took to arrive here (None: the one :meth:`act`
        returned last); a ``move_forward`` that went nowhere marks the obstacle the camera missed.
        Returns the frame's :class:`FovFootprint`."""
        pose = np.asarray(pose, np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be finite (x, y, yaw), got {pose!r}")
        if action is not None:
            self._last_action = str(action)
        occ = self.occupancy
        if (self._last_action == "move_forward" and self._last_pose is not None
                and np.hypot(*(pose[:2] - self._last_pose[:2])) < 0.2 * self.forward_step):
            self.mark_blocked_ahead(pose)
        fp = occ.update(depth, viewmat, K)
        occ.mark_footprint(pose[:2])
        if rgb is not None and self.goal_embedding is not None and self.encoder is not None:
            self.last_value = cosine(self.encoder.embed(rgb), self.goal_embedding)
            self.value_map.update(self.last_value, fp)
        self._last_pose = pose.copy()
        return fp

    def observe_obs(self, obs, K: np.ndarray):
        """:meth:`observe` for a simulator ``Observation`` (frame.depth, frame.rgb, viewmat, pose)."""
        return self.observe(obs.frame.depth, obs.viewmat, K, obs.pose, obs.frame.rgb)

    def mark_blocked_ahead(self, pose) -> None:
        """Put an obstacle cell just beyond the robot's rim, straight ahead of ``pose``.

        :meth:`observe` calls this when a ``move_forward`` went nowhere: the robot met something the
        camera missed (too low or too close to see), and without it the plan would repeat.
        """
        pose = np.asarray(pose, np.float64).reshape(-1)
        d = self.occupancy.robot_radius + self.spec.cell_size
        p = pose[:2] + d * np.array([np.cos(pose[2]), np.sin(pose[2])])
        rc = self.spec.world_to_cell(p)
        if self.spec.in_bounds(rc):
            self.occupancy.state[rc[0], rc[1]] = OCCUPIED

    # -- deciding -------------------------------------------------------------------------
    def planner(self) -> FMMPlanner:
        """FMM planner over the current map (the robot footprint is cleared per query)."""
        return FMMPlanner.from_occupancy(self.occupancy, self.config.unknown_is_free,
                                         forward_step=self.forward_step, turn_deg=self.turn_deg)

    def frontiers(self, pose, objects: list[ObjectScore] = (), planner: FMMPlanner | None = None) -> list[Frontier]:
        """Reachable, non-blacklisted frontiers with eq 19 terms in ``info`` (d, E, V, utility),
        best first."""
        cfg = self.config
        pose = np.asarray(pose, np.float64).reshape(-1)
        planner = planner or self.planner()
        D = planner.distance_from(pose[:2])
        fs = extract_frontiers(self.occupancy.state, self.spec, min_cells=cfg.min_frontier_cells,
                               min_pocket_area=cfg.min_pocket_area)
        kept = attach_distances(fs, D, self.spec, cfg.reach_tolerance)
        sq = planner.squeezed()
        if sq is not None and len(kept) < len(fs):
            # frontiers only reachable through a passage the full clearance closes (the planner
            # squeezes through it with half the clearance)
            ids = {id(f) for f in kept}
            rest = [f for f in fs if id(f) not in ids]
            extra = attach_distances(rest, sq.distance_from(pose[:2]), self.spec, cfg.reach_tolerance)
            for f in extra:
                f.info["squeeze"] = True
            kept += extra
        self._optimistic_planner = None
        if not kept and fs and not cfg.unknown_is_free:
            # nothing reachable over seen-free space, yet frontiers remain: a doorway seen at a
            # grazing angle leaves a free strip narrower than the robot. Plan through unknown
            # cells to get close enough to see it, rather than declaring the house explored
            opt = FMMPlanner.from_occupancy(self.occupancy, True, forward_step=self.forward_step,
                                            turn_deg=self.turn_deg)
            kept = attach_distances(fs, opt.distance_from(pose[:2]), self.spec, cfg.reach_tolerance)
            for f in kept:
                f.info["optimistic"] = True
            self._optimistic_planner = opt
        fs = [f for f in kept if not self._blacklisted(f.waypoint_xy)]
        if not fs:
            return []
        wps = np.stack([f.waypoint_xy for f in fs])
        d = inverse_distance_score([f.distance for f in fs])
        E = object_score(wps, list(objects), cfg.tau_m, cfg.C) if cfg.beta > 0 else np.zeros(len(fs))
        if cfg.delta > 0:
            V = normalise(self.value_map.scores(wps, cfg.r_val, cfg.value_reduce), cfg.value_norm)
        else:
            V = np.zeros(len(fs))
        u = utility(d, E, V, cfg.alpha, cfg.beta, cfg.delta)
        for f, di, ei, vi, ui in zip(fs, d, E, V, u):
            f.info.update(d=float(di), E=float(ei), V=float(vi), utility=float(ui))
        order = np.argsort(-u, kind="stable")
        return [fs[i] for i in order]

    def act(self, pose, objects: list[ObjectScore] = (), *, goal_xy=None, goal_radius: float = 0.0,
            explore_if_unreachable: bool = False) -> Decision:
        """Next discrete action from robot ``pose`` (x, y, yaw); ``objects`` feed eq 20.

        Without ``goal_xy``: toward the best frontier (eq 19). With ``goal_xy`` (2,) metres: the
        FMM plan toward the free cells within ``goal_radius`` m of it (``Decision.goal``, status
        "goal"); when no path reaches it and ``explore_if_unreachable``, the frontier decision of
        this step instead (still carrying ``goal``), since the way may not be mapped yet.
        """
        pose = np.asarray(pose, np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be finite (x, y, yaw), got {pose!r}")
        planner = self.planner()
        if goal_xy is None:
            return self._explore(pose, objects, planner)
        plan = planner.plan(pose, goal_xy, goal_radius)
        try:
            path = planner.path(pose[:2], goal_xy, goal_radius)
        except Exception:  # noqa: BLE001 - the path is for display only
            path = np.zeros((0, 2))
        if plan.status == "unreachable" and explore_if_unreachable:
            d = self._explore(pose, objects, planner)
            d.goal, d.goal_path = plan, path
            return d
        return self._done(Decision(plan.action, "goal", goal=plan, goal_path=path))

    def _explore(self, pose: np.ndarray, objects, planner: FMMPlanner) -> Decision:
        if self._turns_left > 0:
            self._turns_left -= 1
            return self._done(Decision("turn_left", "look_around"))
        cfg = self.config
        # two frontiers whose utilities swap as the robot turns (the value map changes with its
        # heading) would reset a per-target progress count at every switch and leave the robot
        # turning on one spot: count the steps spent on one spot instead
        if self._anchor_xy is None or np.hypot(*(pose[:2] - self._anchor_xy)) > 0.5:
            self._anchor_xy, self._still_steps = pose[:2].copy(), 0
        else:
            self._still_steps += 1
        if self._still_steps > cfg.stuck_steps + cfg.max_look_turns and self._target is not None:
            self._ban(self._target)
            self._still_steps = 0
        fs = self.frontiers(pose, objects, planner)
        for _ in range(8):  # a few re-selections after blacklisting, then give up for this step
            fs = [f for f in fs if not self._blacklisted(f.waypoint_xy)]
            if not fs:
                self._target = None
                return self._done(Decision("stop", "explored"))
            target = self._select(fs)
            pl = self._optimistic_planner if target.info.get("optimistic") and self._optimistic_planner else planner
            plan = pl.plan(pose, target.waypoint_xy, cfg.arrive_radius)
            if plan.status in ("reached", "closest"):
                # arrived, but the frontier is still there: the unknown side may be out of view
                # (the robot arrives facing along its path), so turn to face it before giving up
                a = self._look_angle(pose, target)
                if a is not None and abs(a) > 0.5 * np.radians(self.turn_deg) and self._look_turns < cfg.max_look_turns:
                    self._look_turns += 1
                    return self._done(Decision("turn_left" if a > 0 else "turn_right", "looking", target, fs))
            if plan.status in ("reached", "closest", "unreachable"):
                # the frontier survived a visit (or cannot be approached): never pick it again
                self._ban(target)
                continue
            if plan.distance < self._best_dist - 0.1:
                self._best_dist, self._since_progress = plan.distance, 0
            else:
                self._since_progress += 1
            if self._since_progress > cfg.stuck_steps:
                self._ban(target)
                continue
            status = "blocked" if plan.status == "blocked" else "exploring"  # moving or squeezing
            return self._done(Decision(plan.action, status, target, fs))
        return self._done(Decision("turn_left", "blocked", None, []))

    def _look_angle(self, pose: np.ndarray, f: Frontier) -> float | None:
        """Heading change (rad) that faces the unknown cells near frontier ``f``; None if none."""
        rows, cols, disc = self.spec.cells_within(f.waypoint_xy, 1.5)
        unk = disc & (self.occupancy.state[rows, cols] == UNKNOWN)
        if not unk.any():
            return None
        rc = np.argwhere(unk).mean(0) + [rows.start, cols.start]
        c = self.spec.cell_to_world(rc)
        a = np.arctan2(c[1] - pose[1], c[0] - pose[0]) - pose[2]
        return float(wrap_angle(a))

    def _select(self, fs: list[Frontier]) -> Frontier:
        best = fs[0]
        cur = self._target
        if cur is not None:
            near = [f for f in fs if np.hypot(*(f.waypoint_xy - cur.waypoint_xy)) <= 1.0]
            if near:
                keep = max(near, key=lambda f: f.info["utility"])
                if keep.info["utility"] >= best.info["utility"] - self.config.switch_margin:
                    best = keep
        if cur is None or np.hypot(*(best.waypoint_xy - cur.waypoint_xy)) > 1.0:
            self._best_dist, self._since_progress, self._look_turns = np.inf, 0, 0
        self._target = best
        return best

    def _ban(self, f: Frontier) -> None:
        self.blacklist.append(np.asarray(f.waypoint_xy, np.float64).copy())
        self._target = None
        self._best_dist, self._since_progress, self._look_turns = np.inf, 0, 0

    def _blacklisted(self, xy) -> bool:
        r = self.config.blacklist_radius
        return any(np.hypot(*(xy - b)) <= r for b in self.blacklist)

    def _done(self, d: Decision) -> Decision:
        self._last_action = d.action
        return d


def coverage(occupancy: OccupancyGrid, navigable: np.ndarray, cell_to_world) -> float:
    """Fraction of ground-truth navigable cells that the map knows (free or occupied).

    navigable: (h, w) bool ground-truth mask on any grid; cell_to_world: that grid's (..., 2)
    (row, col) -> world xy function (e.g. ``NavGrid.cell_to_world``).
    """
    rc = np.argwhere(np.asarray(navigable, bool))
    if not len(rc):
        raise ValueError("the ground-truth mask has no navigable cell")
    ours = occupancy.spec.world_to_cell(cell_to_world(rc))
    inside = occupancy.spec.in_bounds(ours)
    known = np.zeros(len(rc), bool)
    known[inside] = occupancy.state[ours[inside, 0], ours[inside, 1]] != UNKNOWN
    return float(known.mean())
