"""The robot's route around the standing people it has perceived.

The TPN's goal features and the route fallback read a global route. Walls alone give the shortest
path, which in the static-groups scene runs through an F-formation. The walker's route keeps 0.8 m
from standing people and never crosses a group, but it reads who stands where from the scene,
which the robot does not perceive. :class:`PerceivedRoute` builds that route from what the robot
perceives: people in line of sight within sensing range (the mask the caller passes), standing =
measured speed over the two LiDAR sweeps below ``STAND_SPEED`` (for someone the robot has seen
walking: at every plan for ``STAND_TIME``, since a walker who stops to let the robot by walks on),
grouped by
:func:`~splatsearch.social.convoi.perception.detect_groups`. A person stays in the set after
leaving view (the robot remembers where it saw them standing) and leaves it when seen walking. The
global re-route (one FMM solve, from the scene's start like the walls-only route) runs only when
that set changes.
"""

from __future__ import annotations

import numpy as np

from ..convoi.geometry import distance_field_from_capsules
from ..convoi.perception import detect_groups
from ..convoi.scenarios import GRID, PERSON_RADIUS, Scenario, resample_polyline, smooth_polyline

# people standing in a group shift their weight at 0.1-0.2 m/s; someone who stops for a moment
# to let the robot by is not a standing person to route around
STAND_SPEED = 0.3  # m/s: measured slower than this over the sweep interval = not walking
STAND_TIME = 1.0  # s: someone seen walking who is then seen still for this long = standing again


def route_around(scn: Scenario, standing: np.ndarray, berth: float, start: np.ndarray | None = None,
                 clearance: float = 0.45, spacing: float = 0.1) -> np.ndarray | None:
    """(M, 2) world route from ``start`` (2,) m (default: the scene's start) to its goal keeping ``clearance`` m from walls and
    ``berth`` m (edge) from each standing person at ``standing`` (k, 2) m, never through the
    inside of a group of them (members within 1.6 m of each other are joined by a blocked segment).
    None when no such route exists (the caller keeps the walls-only route)."""
    from splatsearch.nav.fmm import FMMPlanner, Unreachable

    standing = np.asarray(standing, np.float64).reshape(-1, 2)
    f = np.asarray(scn.field().values)
    if len(standing):
        extra = [[*p, *p, PERSON_RADIUS + berth] for p in standing]
        labels = detect_groups(standing, np.zeros_like(standing))
        for g in sorted(set(labels[labels >= 0].tolist())):
            m = standing[labels == g]
            extra += [[*a, *b, PERSON_RADIUS] for k, a in enumerate(m) for b in m[k + 1:]]
        f = np.minimum(f, np.asarray(distance_field_from_capsules(np.asarray(extra, np.float32), GRID).values))
    trav = f > clearance
    start = np.asarray(scn.start[:2] if start is None else start, np.float64)
    try:
        pts = FMMPlanner(GRID, trav, robot_radius=0.0, squeeze=None).path(start, scn.goal, radius=0.1)
    except (Unreachable, ValueError):
        return None
    pts = np.vstack([start[None], pts[1:], np.asarray(scn.goal, np.float64)[None]])
    return resample_polyline(smooth_polyline(pts, 5), spacing)


class PerceivedRoute:
    """The route of one episode, updated from perception at each plan.

    ``berth`` (m): clearance from perceived standing people (0: the walls-only route throughout)."""

    def __init__(self, scn: Scenario, berth: float):
        self.scn = scn
        self.berth = float(berth)
        self.walls = scn.global_path()
        self.path = self.walls
        self.standing: dict[int, np.ndarray] = {}  # person index -> where they were seen standing
        self.slow_since: dict[int, float] = {}  # person index -> since when (s) seen not walking
        self.walked: set[int] = set()  # people seen walking at some plan
        self.replans = 0

    def update(self, pos: np.ndarray, vel: np.ndarray, seen: np.ndarray, now: float,
               measured: bool = True) -> np.ndarray:
        """The route (M, 2) after this plan's perception at time ``now`` (s): people at ``pos``
        (P, 2) m with measured ``vel`` (P, 2) m/s, ``seen`` (P,) bool. The route runs from the
        scene's start (the goal features project the robot onto it); when none exists the
        previous one is kept.
        ``measured`` False (no second sweep yet): speeds are unknown, nobody is classed."""
        if self.berth <= 0 or not measured:
            return self.path
        speed = np.linalg.norm(np.asarray(vel, np.float64), axis=1)
        before = set(self.standing)
        seen = np.asarray(seen, bool)
        for i in range(len(seen)):
            if not seen[i]:
                self.slow_since.pop(i, None)  # out of view: the next sighting starts the clock again
            elif speed[i] < STAND_SPEED:
                since = self.slow_since.setdefault(i, float(now))
                if i not in self.walked or now - since >= STAND_TIME - 1e-6:
                    self.standing.setdefault(i, np.asarray(pos[i], np.float64).copy())
            else:
                self.walked.add(i)
                self.slow_since.pop(i, None)
                self.standing.pop(i, None)
        if set(self.standing) != before:
            pts = np.stack([self.standing[i] for i in sorted(self.standing)]) if self.standing else np.zeros((0, 2))
            if not len(pts):
                self.path = self.walls
            else:
                # from the scene's start, as the walls-only path: rooted at the robot, a route
                # carried a sidestep along as the new lateral reference (dev seeds: the robot no
                # longer drifted back to the lane after passing people, hallway and dynamic groups).
                # People closing every way through: keep the route in use (the robot waits or
                # squeezes by as trained)
                route = route_around(self.scn, pts, self.berth)
                self.path = self.path if route is None else route
            self.replans += 1
        return self.path
