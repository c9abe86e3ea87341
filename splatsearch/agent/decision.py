"""The decision: where to go next, given what perception and verification know (thesis 4.2.6).

:class:`SearchPolicy` is a small state machine over the object DB. Each step it picks a target:

1. an object taken for the goal (:meth:`Verifier.is_goal`): walk to it (FMM) and stop within
   ``stop_margin`` of its extent;
2. else an object whose colours look like the goal's from too few viewpoints: walk up to it and
   turn toward it for ``verify_steps`` steps to see it again (``verifying``);
3. else no target: the explorer's eq 19/20 frontier;
4. once the explorer reports the house explored and nothing is the goal: the goal-class object
   with the most evidence (colours, then e_max, then the crop cosine), chosen again every step
   with some hysteresis, since the way there shows the other objects again.

A goal that gets no closer for ``goal_patience`` reachable steps, or that no path reaches once
the house is explored, is given up and the next candidate taken. The explorer is asked once per
step (twice in the one step where it reports the house explored and a fallback target is then
planned), and never calls back.
"""

from __future__ import annotations

import numpy as np

from splatsearch.nav.exploration import Decision, ExplorationPlanner, ObjectScore
from splatsearch.nav.grid import wrap_angle
from splatsearch.search.objects import ObjectDB, ObjectEntry

from .config import AgentConfig, Strategy
from .verification import Verifier

#: hysteresis of the end-of-exploration fallback: another entry replaces the current one only
#: when its colour similarity is higher by more than this, or when it is about as similar and has
#: at least ``FALLBACK_MATCH_MARGIN`` more matches (camera-image scale)
FALLBACK_COLOUR_MARGIN = 0.05
FALLBACK_MATCH_MARGIN = 2.0


class SearchPolicy:
    """Target choice and the action toward it.

    Args:
        config, strategy: :class:`AgentConfig` and its :class:`Strategy`.
        db: the object DB (read; verification writes it). verifier: judges entries and, for a
            strategy that identifies after exploring, runs their NVSM then (``verify_all``).
        explorer: the :class:`ExplorationPlanner`, asked for the action of each step.
        crop_cosine: entry id -> best crop cosine (the fallback's last tie-break).

    State: ``explored`` (the explorer found no frontier left), ``given_up`` (entry ids not to be
    chosen again), and for display ``target_entry``, ``path_xy`` (P, 2) metres and
    ``last_decision`` (the explorer's latest frontier decision).
    """

    def __init__(self, config: AgentConfig, strategy: Strategy, db: ObjectDB, verifier: Verifier,
                 explorer: ExplorationPlanner, crop_cosine: dict[int, float]):
        self.cfg, self.strategy = config, strategy
        self.db, self.verifier, self.explorer = db, verifier, explorer
        self.crop_cosine = crop_cosine
        self.explored = False
        self.given_up: set[int] = set()
        self.target_entry: int | None = None
        self.path_xy: np.ndarray = np.zeros((0, 2))
        self.last_decision: Decision | None = None
        self._fallback: int | None = None
        self._verify: tuple[int, int] | None = None  # (entry id, step the verification began)
        self._progress: list | None = None  # [entry id, best distance m, steps without progress]

    # -- which entries --------------------------------------------------------------------------
    def identifies_now(self) -> bool:
        """Whether entries can be taken for the goal yet (after exploring, for gaussnav)."""
        return not self.strategy.identify_after_exploring or self.explored

    def goal_candidates(self) -> list[ObjectEntry]:
        """Entries taken for the goal and not given up, most likely first (colours, then e_max)."""
        if not self.identifies_now():
            return []
        out = [e for e in self.db if e.id not in self.given_up and self.verifier.is_goal(e)]
        return sorted(out, key=lambda e: (-e.colour_similarity, -e.e_max))

    def promising(self) -> list[ObjectEntry]:
        """Entries whose colours reach tau_a from too few viewpoints to confirm them, most similar
        first: the agent walks up to them to see them again."""
        if not self.identifies_now():
            return []
        out = [e for e in self.db if e.id not in self.given_up and self.verifier.looks_promising(e)]
        return sorted(out, key=lambda e: -e.colour_similarity)

    def choose_fallback(self) -> ObjectEntry | None:
        """Once everything is explored and nothing is the goal: the entry with the best evidence
        (colour similarity, then e_max, then the crop cosine), or None. The current choice is kept
        unless another entry beats it by ``FALLBACK_COLOUR_MARGIN`` in colour similarity or, at
        about the same similarity, by ``FALLBACK_MATCH_MARGIN`` matches, so that near-ties do not
        make the robot turn back and forth."""
        cands = [e for e in self.db if e.id not in self.given_up]
        if not cands:
            self._fallback = None
            return None
        best = max(cands, key=lambda e: (e.colour_similarity, e.e_max, self.crop_cosine.get(e.id, -1.0)))
        cur = next((e for e in cands if e.id == self._fallback), None)
        if cur is not None and best.id != cur.id:
            d = best.colour_similarity - cur.colour_similarity
            switch = d > FALLBACK_COLOUR_MARGIN or (
                d >= -FALLBACK_COLOUR_MARGIN and best.e_max >= cur.e_max + FALLBACK_MATCH_MARGIN)
            if not switch:
                best = cur
        self._fallback = best.id
        return best

    def goal_stalled(self, entry_id: int, distance: float) -> bool:
        """True when the geodesic distance (m) to entry ``entry_id`` has not dropped by 0.1 m in
        ``goal_patience`` calls; a new entry starts the count afresh."""
        if self._progress is None or self._progress[0] != entry_id:
            self._progress = [entry_id, np.inf, 0]
        if distance < self._progress[1] - 0.1:
            self._progress[1:] = [distance, 0]
            return False
        self._progress[2] += 1
        return self._progress[2] > self.cfg.goal_patience

    # -- one step -------------------------------------------------------------------------------
    def decide(self, pose: np.ndarray, step: int, verify_all=None) -> tuple[str, str]:
        """(action, status) for robot ``pose`` (x, y, yaw) at step index ``step`` (frames seen
        so far). ``verify_all()``: called once the house is explored when the strategy identifies
        only then (it runs the due verification)."""
        action, status = self._decide(pose, step, verify_all, after_exploring=False)
        if status == "explored_now":
            action, status = self._decide(pose, step, verify_all, after_exploring=True)
        return action, status

    def _target(self, verify_all) -> tuple[ObjectEntry | None, bool]:
        matched = self.goal_candidates()
        if self.explored and not matched:
            if self.strategy.identify_after_exploring and verify_all is not None:
                verify_all()
                matched = self.goal_candidates()
            if not matched:
                # everything is explored and nothing passed tau_m: the goal-class object with the
                # most evidence is still a better bet than stopping where the robot is
                best = self.choose_fallback()
                if best is not None:
                    matched = [best]
        if matched:
            return matched[0], False
        promising = self.promising()
        return (promising[0], True) if promising else (None, False)

    def _decide(self, pose, step: int, verify_all, *, after_exploring: bool) -> tuple[str, str]:
        e, verifying = self._target(verify_all)
        if e is None:
            if after_exploring:
                return "stop", "explored"
            d = self.explorer.act(pose, self._object_scores())
            return self._follow_frontier(pose, d, "exploring")
        self.target_entry = e.id
        radius = e.extent_radius + self.cfg.stop_margin
        d = self.explorer.act(pose, self._object_scores(), goal_xy=e.centroid[:2], goal_radius=radius,
                              explore_if_unreachable=not (after_exploring or self.explored))
        plan = d.goal
        self.path_xy = d.goal_path
        if plan.status in ("reached", "closest"):
            if verifying:
                return self._look_at(pose, e, step)
            return "stop", "goal_reached"
        if np.isfinite(plan.distance) and self.goal_stalled(e.id, plan.distance):
            self.given_up.add(e.id)  # no progress for a long while: try the next candidate
            return "turn_left", "stuck_goal"
        if plan.status == "unreachable":
            if after_exploring or self.explored:
                self.given_up.add(e.id)  # no way to it on the map: try the next candidate
                return "turn_left", "unreachable_goal"
            return self._follow_frontier(pose, d, "exploring_to_goal")  # the way is not mapped yet
        return plan.action, "to_candidate" if verifying else "to_goal"

    def _follow_frontier(self, pose, d: Decision, label: str) -> tuple[str, str]:
        self.last_decision = d
        if d.target is not None:
            self.path_xy = np.asarray([pose[:2], d.target.waypoint_xy])
        if d.status == "explored":
            self.explored = True
            return "stop", "explored_now"
        return d.action, label if d.status == "exploring" else d.status

    def _object_scores(self) -> list[ObjectScore]:
        """eq 20's objects in match units: an object whose colours look like the goal's draws the
        robot to the frontiers around it as a tau_m match would."""
        cents, scores = self.db.scores()
        if self.verifier.colour_cue:
            sim = np.array([max(e.colour_similarity, 0.0) for e in self.db])
            if len(sim):
                scores = np.maximum(scores, self.cfg.tau_m * sim / max(self.cfg.tau_a, 1e-6))
        return [ObjectScore(c[:2], s) for c, s in zip(cents, scores)]

    def _look_at(self, pose, e: ObjectEntry, step: int) -> tuple[str, str]:
        """Next to an unconfirmed candidate: turn toward it so the next frames see it, and give it
        up after ``verify_steps`` steps there without confirming it."""
        if self._verify is None or self._verify[0] != e.id:
            self._verify = (e.id, step)
        err = bearing_error(pose, e.centroid)
        if step - self._verify[1] >= self.cfg.verify_steps:
            self.given_up.add(e.id)
            return "turn_left", "not_the_goal"
        if abs(err) > np.radians(20):
            return ("turn_left" if err > 0 else "turn_right"), "verifying"
        # facing it: wait for the next frames by looking left and right of it in turn
        return ("turn_left" if (step - self._verify[1]) % 2 else "turn_right"), "verifying"


def bearing_error(pose, xy) -> float:
    """Turn (rad, in [-pi, pi), positive = left) from robot ``pose`` (x, y, yaw) to face world
    point ``xy`` (its first two coordinates, metres)."""
    dx, dy = xy[0] - pose[0], xy[1] - pose[1]
    return float(wrap_angle(np.arctan2(dy, dx) - pose[2]))
