"""Social-navigation scenarios: the four of OLiVia-Nav (thesis Fig. 3) plus a doorway and a crossing.

==============  ==========================================================================================
hallway         narrow hallway (2.6 m), two people walking toward the robot front-on, keeping to their right
blind_corner    L-shaped corridor; a person comes round the corner from the arm the robot turns into,
                hidden by the walls until late
static_groups   open room, two static groups (F-formations of 3) astride the direct line + three walkers
dynamic_groups  open room, two walking groups (3 abreast head-on, 2 crossing) + two individuals
doorway         two rooms joined by a 1 m door; a person comes through it toward the robot
crossing        open space, four people crossing the robot's line from both sides
==============  ==========================================================================================

Every scenario is built from a seed: start positions, speeds and timings are jittered with
``numpy.random.default_rng(seed)``, and the same seed gives the same scenario (and, through
:func:`splatsearch.social.convoi.pedsim.step_key`, the same pedestrian noise). All scenarios share one
grid (16 m x 16 m, 5 cm cells) and one padded size, so the planners and the simulator compile
once for all of them.

World frame: the robot starts near the origin facing +x, z up, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from splatsearch.nav.grid import GridSpec

from .geometry import (
    DistanceField,
    check_capsules,
    distance_field_from_capsules,
    pad_capsules,
)
from .pedsim import PedState, make_state
from .scenario_names import SCENARIOS, TABLE_ONE_SEEDS, THESIS_SCENARIOS  # noqa: F401 - re-exported

GRID = GridSpec((-2.0, -8.0), 0.05, (320, 320))
MAX_PEOPLE = 12
MAX_CAPSULES = 16
WALL = 0.05  # wall half-thickness (m)
PERSON_RADIUS = 0.25
ROBOT_RADIUS = 0.25


@dataclass(frozen=True, eq=False)
class Scenario:
    """One seeded scenario.

    name; seed; capsules: (S, 5) obstacle rows; start: (3,) robot pose (x, y, yaw);
    goal: (2,) m; peds: the initial :class:`PedState`; max_steps: episode cap (steps of dt);
    dt: s; lane_offset: the expert's preferred lateral offset from the global path (m, negative =
    keep right; 0 = none); context: the ground-truth context label (see
    :mod:`splatsearch.social.convoi.context`); groups: lists of person indices walking or standing together.
    """

    name: str
    seed: int
    capsules: np.ndarray
    start: np.ndarray
    goal: np.ndarray
    peds: PedState
    max_steps: int = 400
    dt: float = 0.1
    lane_offset: float = 0.0
    context: str = "an open indoor space"
    groups: tuple[tuple[int, ...], ...] = ()
    description: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def spec(self) -> GridSpec:
        return GRID

    @property
    def n_people(self) -> int:
        return int(np.asarray(self.peds.active).sum())

    def padded_capsules(self) -> tuple[np.ndarray, np.ndarray]:
        """(MAX_CAPSULES, 5) obstacle rows and their (MAX_CAPSULES,) validity."""
        return pad_capsules(self.capsules, MAX_CAPSULES)

    def field(self) -> DistanceField:
        """The static clearance field on :data:`GRID` (cached)."""
        if "field" not in self._cache:
            self._cache["field"] = distance_field_from_capsules(self.capsules, GRID)
        return self._cache["field"]

    def standing_people(self) -> np.ndarray:
        """(k,) indices of people who stand still (their only waypoint is where they start)."""
        pos = np.asarray(self.peds.pos)
        goals = np.asarray(self.peds.goals)[:, 0]
        n = np.asarray(self.peds.n_goals)
        act = np.asarray(self.peds.active)
        return np.flatnonzero(act & (n == 1) & (np.linalg.norm(goals - pos, axis=1) < 0.1))

    def global_path(self, clearance: float = ROBOT_RADIUS + 0.2, spacing: float = 0.1,
                    avoid_standing: float | None = None) -> np.ndarray:
        """(M, 2) shortest path (FMM) from start to goal keeping ``clearance`` m from walls,
        resampled every ``spacing`` m (cached). Walking people are not in it. With
        ``avoid_standing`` (m), standing people are obstacles grown by that much and the inside of
        each standing group is blocked (a route a teleoperator would take)."""
        key = ("path", clearance, spacing, avoid_standing)
        if key not in self._cache:
            from splatsearch.nav.fmm import FMMPlanner

            f = np.asarray(self.field().values)
            if avoid_standing is not None:
                pos = np.asarray(self.peds.pos)
                stand = set(self.standing_people().tolist())
                extra = [[*pos[i], *pos[i], PERSON_RADIUS + avoid_standing] for i in sorted(stand)]
                for g in self.groups:
                    m = [i for i in g if i in stand]
                    extra += [[*pos[a], *pos[b], PERSON_RADIUS] for k, a in enumerate(m) for b in m[k + 1:]]
                if extra:
                    f = np.minimum(f, np.asarray(distance_field_from_capsules(np.asarray(extra, np.float32),
                                                                              GRID).values))
            trav = f > clearance
            planner = FMMPlanner(GRID, trav, robot_radius=0.0, squeeze=None)
            pts = planner.path(self.start[:2], self.goal, radius=0.1)
            pts = np.vstack([self.start[:2][None], pts[1:], self.goal[None]])
            self._cache[key] = resample_polyline(smooth_polyline(pts, 5), spacing)
        return self._cache[key]


def resample_polyline(pts: np.ndarray, spacing: float) -> np.ndarray:
    """(K, 2) points every ``spacing`` metres of arc length along the polyline ``pts`` (N, 2)
    (first and last points kept)."""
    pts = np.asarray(pts, np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if s[-1] <= 0:
        return pts[:1].astype(np.float32)
    n = max(2, int(np.ceil(s[-1] / spacing)) + 1)
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], -1).astype(np.float32)


def smooth_polyline(pts: np.ndarray, k: int) -> np.ndarray:
    """Moving average of width ``2k + 1`` over interior points (ends fixed): removes the grid
    staircase of FMM descent paths."""
    pts = np.asarray(pts, np.float64)
    if len(pts) < 3 or k < 1:
        return pts
    pad = np.vstack([np.repeat(pts[:1], k, 0), pts, np.repeat(pts[-1:], k, 0)])
    ker = np.ones(2 * k + 1) / (2 * k + 1)
    out = np.stack([np.convolve(pad[:, i], ker, "valid") for i in range(2)], -1)
    out[0], out[-1] = pts[0], pts[-1]
    return out


def _wall(x1, y1, x2, y2, r=WALL):
    return [x1, y1, x2, y2, r]


def _box(x0, y0, x1, y1):
    return [_wall(x0, y0, x1, y0), _wall(x1, y0, x1, y1), _wall(x1, y1, x0, y1), _wall(x0, y1, x0, y0)]


def _formation(centre, radius, n, phase):
    a = phase + 2 * np.pi * np.arange(n) / n
    return np.asarray(centre)[None] + radius * np.stack([np.cos(a), np.sin(a)], -1)


#: geometry a scenario accepts (m) with its default and the range training scenes draw it from
GEOMETRY = {
    "hallway": {"width": (2.6, 1.9, 3.2)},
    "blind_corner": {"width": (2.4, 2.1, 2.8)},
    "static_groups": {"spread": (1.0, 0.8, 1.25)},
    "dynamic_groups": {"spread": (0.75, 0.6, 0.95)},
    "doorway": {"door_width": (1.1, 1.02, 1.6)},
    "crossing": {},
}


def training_geometry(name: str, seed: int) -> dict:
    """The geometry of training scene (``name``, ``seed``): each parameter of :data:`GEOMETRY`
    drawn uniformly over its range (door widths 1.02-1.6 m, corridor widths, group spacing),
    from a stream of its own so the scenario's other draws stay those of ``seed``."""
    rng = np.random.default_rng([int(seed), 77, SCENARIOS.index(name)])
    return {k: float(rng.uniform(lo, hi)) for k, (_, lo, hi) in GEOMETRY[name].items()}


def make_scenario(name: str, seed: int = 0, **geometry) -> Scenario:
    """The scenario ``name`` (one of :data:`SCENARIOS`) jittered by ``seed`` (int >= 0), with
    optional ``geometry`` overrides (m; see :data:`GEOMETRY`, e.g. ``door_width=1.3``)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    bad = set(geometry) - set(GEOMETRY[name])
    if bad:
        raise ValueError(f"{name} has no geometry parameter(s) {sorted(bad)}; it takes {sorted(GEOMETRY[name])}")
    geo = {k: float(geometry.get(k, d)) for k, (d, lo, hi) in GEOMETRY[name].items()}
    for k, v in geo.items():
        d, lo, hi = GEOMETRY[name][k]
        if not (0.5 * lo <= v <= 2.0 * hi):
            raise ValueError(f"{name}: {k}={v} m is outside the supported {0.5 * lo:.2f}-{2.0 * hi:.2f} m")
    rng = np.random.default_rng([int(seed), SCENARIOS.index(name)])
    j = lambda s: float(rng.uniform(-s, s))
    scn = globals()[f"_{name}"](int(seed), rng, j, **geo)
    scn._cache["geometry"] = geo
    return scn


def _scn(name, seed, caps, start, goal, pos, goals, v0, group=None, **kw) -> Scenario:
    peds = make_state(pos, goals, v0, group=group, radius=PERSON_RADIUS, max_people=MAX_PEOPLE)
    return Scenario(name, seed, check_capsules(caps), np.asarray(start, np.float32), np.asarray(goal, np.float32),
                    peds, **kw)


def _hallway(seed, rng, j, width=2.6):
    h = width / 2
    caps = [_wall(-1.5, -h, 13.0, -h), _wall(-1.5, h, 13.0, h), _wall(13.0, -h, 13.0, h)]
    y1, y2 = 0.35 + j(0.15), -0.15 + j(0.15)
    pos = [[8.5 + j(0.5), y1], [10.0 + j(0.5), y2]]
    # walking toward -x, their right is +y: they drift to the +y side of the hallway
    goals = [[[-1.8, 0.55 + j(0.1)]], [[-1.8, 0.45 + j(0.1)]]]
    v0 = [1.1 + j(0.15), 1.2 + j(0.15)]
    return _scn("hallway", seed, caps, [0.0, j(0.1), 0.0], [11.5, 0.0], pos, goals, v0, lane_offset=-0.5,
                context="a corridor with people walking towards the robot", max_steps=350,
                description="narrow hallway, two people approaching front-on")


def _blind_corner(seed, rng, j, width=2.4):
    h = width / 2
    caps = [_wall(-1.5, -h, 8.0, -h), _wall(8.0, -h, 8.0, 7.5), _wall(-1.5, h, 8.0 - width, h),
            _wall(8.0 - width, h, 8.0 - width, 7.5)]
    # the person comes down the vertical arm and cuts the inner corner, out of sight until late
    pos = [[6.5 + j(0.2), 7.0 + j(0.3)]]
    goals = [[[6.1 + j(0.1), 0.5 + j(0.1)], [-1.8, 0.3 + j(0.1)]]]
    v0 = [1.1 + j(0.15)]
    return _scn("blind_corner", seed, caps, [0.0, j(0.1), 0.0], [6.8, 6.5], pos, goals, v0, lane_offset=-0.35,
                context="a blind corner in a corridor", max_steps=350,
                description="L-shaped corridor, a person comes round the corner")


def _static_groups(seed, rng, j, spread=1.0):
    caps = _box(-1.5, -5.0, 13.5, 5.0)
    ga = _formation([4.0 + j(0.3), 0.15 + j(0.2)], 0.75 * spread, 3, j(0.5))
    gb = _formation([8.2 + j(0.3), -0.9 + j(0.2)], 0.7 * spread, 3, 0.5 + j(0.5))
    walkers = [[10.0 + j(0.5), 4.2], [12.0 + j(0.5), -3.5 + j(0.3)], [6.0 + j(0.5), -4.4]]
    wgoals = [[[2.0 + j(0.5), -4.2]], [[0.5, 2.5 + j(0.5)]], [[7.5 + j(0.5), 4.4]]]
    pos = np.vstack([ga, gb, walkers])
    goals = [[p] for p in ga] + [[p] for p in gb] + wgoals
    v0 = [0.6] * 6 + [1.0 + j(0.15), 1.1 + j(0.15), 0.9 + j(0.15)]
    group = [0, 0, 0, 1, 1, 1, -1, -1, -1]
    return _scn("static_groups", seed, caps, [0.0, j(0.1), 0.0], [11.5, 0.0], pos, goals, v0, group=group,
                groups=((0, 1, 2), (3, 4, 5)), context="people standing in groups", max_steps=400,
                description="two static groups and three walking people")


def _dynamic_groups(seed, rng, j, spread=0.75):
    caps = _box(-1.5, -5.0, 13.5, 5.0)
    # a group of three walking abreast head-on (met around x = 4 m after ~6 s), a pair crossing
    # where the robot arrives ~10 s in, and two individuals
    y0 = 0.2 + j(0.3)
    x1 = 9.5 + j(0.3)
    g1 = [[x1, y0 - spread], [x1 + j(0.15), y0], [x1 + j(0.15), y0 + spread]]
    g1_goals = [[[-1.0, p[1] + 0.2]] for p in g1]
    x2 = 6.2 + j(0.4)
    g2 = [[x2 - 0.4, -4.4], [x2 + 0.4, -4.4]]
    g2_goals = [[[p[0] + 0.3, 4.4]] for p in g2]
    singles = [[12.5 + j(0.3), 3.0 + j(0.3)], [1.5 + j(0.5), -4.2]]
    s_goals = [[[5.0, -4.2 + j(0.3)]], [[9.0, 4.2 + j(0.3)]]]
    pos = np.vstack([g1, g2, singles])
    goals = g1_goals + g2_goals + s_goals
    v1, v2 = 0.9 + j(0.1), 0.5 + j(0.05)
    v0 = [v1] * 3 + [v2] * 2 + [1.0 + j(0.15), 0.9 + j(0.15)]
    group = [0, 0, 0, 1, 1, -1, -1]
    return _scn("dynamic_groups", seed, caps, [0.0, j(0.1), 0.0], [11.5, 0.0], pos, goals, v0, group=group,
                groups=((0, 1, 2), (3, 4)), context="people walking in an open space", max_steps=400,
                description="two walking groups and two walking people")


def _doorway(seed, rng, j, door_width=1.1):
    dy = j(0.1)
    h = door_width / 2  # wall ends (the clear width is door_width - 2 WALL)
    caps = _box(-1.5, -4.0, 12.5, 4.0) + [_wall(5.0, -4.0, 5.0, dy - h), _wall(5.0, dy + h, 5.0, 4.0)]
    pos = [[8.5 + j(0.4), 1.5 + j(0.3)]]
    goals = [[[5.6, dy + 0.1], [4.2, dy - 0.1], [0.5 + j(0.3), -2.5 + j(0.3)]]]
    v0 = [1.0 + j(0.15)]
    return _scn("doorway", seed, caps, [0.0, j(0.1), 0.0], [10.0, 0.0], pos, goals, v0, lane_offset=0.0,
                context="a doorway", max_steps=400, description="a person comes through a 1.1 m doorway")


def _crossing(seed, rng, j):  # noqa: ARG001
    caps = _box(-1.5, -6.0, 13.5, 6.0)
    pos = [[4.0 + j(0.4), 4.5 + j(0.3)], [6.5 + j(0.4), -5.0 + j(0.3)], [8.5 + j(0.4), 5.3 + j(0.3)],
           [3.0 + j(0.4), -5.5 + j(0.3)]]
    goals = [[[4.5 + j(0.3), -5.3]], [[6.0 + j(0.3), 5.3]], [[8.0 + j(0.3), -5.3]], [[3.5 + j(0.3), 5.3]]]
    v0 = [1.0 + j(0.15), 1.1 + j(0.15), 1.0 + j(0.15), 0.9 + j(0.15)]
    return _scn("crossing", seed, caps, [0.0, j(0.1), 0.0], [11.5, 0.0], pos, goals, v0,
                context="people walking in an open space", max_steps=400,
                description="four people crossing the robot's line")
