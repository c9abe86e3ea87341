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

With ``look_again`` > 0, an object whose NVSM left it ambiguous
(:meth:`Verifier.is_ambiguous`) comes between 1 and 2-4: while nothing is taken for the goal, the
robot walks to a viewpoint that sees what the object's local map lacks
(:func:`~splatsearch.agent.look_again.choose_viewpoint`), turns to face the object, and the
agent's ``capture`` callback adds that frame to the object's observations and runs its NVSM
again (``look_again`` views per object at most, ``look_again_steps`` steps per trip).

With ``confirm_below`` > tau_m (the default since stop 45, with look-again trips only after a
refusal), an entry taken for the goal by a marginal feature match
(e_max in [tau_m, ``confirm_below``), colours undecided) gets one confirm trip of the same kind
before the robot walks to it; the count of the frame taken there (not the running maximum) must
reach tau_m again, or the entry is refuted (``refuted``): a look-alike that passed by a little
cannot end the episode, and e_max, which keeps every run's best, could never take that back.
With ``confirm_by`` "rivals" there is no trip to the marginal match itself: while it is the best
goal candidate, the ambiguous entries get their look-again trips (kind "rival") first, and it
stands once none is left.

A goal that gets no closer for ``goal_patience`` reachable steps, or that no path reaches once
the house is explored, is given up and the next candidate taken. The explorer is asked once per
step (twice in the one step where it reports the house explored and a fallback target is then
planned), and never calls back.
"""

from __future__ import annotations

import numpy as np

from splatsearch.nav.exploration import Decision, ExplorationPlanner, ObjectScore
from splatsearch.nav.grid import wrap_angle
from splatsearch.search.novel_views import camera_pose
from splatsearch.search.objects import ObjectDB, ObjectEntry

from .config import AgentConfig, Strategy
from .look_again import azimuths_of, choose_viewpoint
from .verification import Verifier

#: metres from a look-again viewpoint at which the robot counts as there
LOOK_AGAIN_RADIUS = 0.25
#: the robot faces the object when its bearing is within this (degrees): a 30-degree turn lattice
LOOK_AGAIN_FACING_DEG = 15.0
#: the step status of each kind of trip
_STATUS = {"look": "look_again", "rival": "look_again", "confirm": "confirm"}

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
        observations: the objects' stored observations (their cameras tell the look-again step
            which sides were seen); optional without ``look_again``.

    State: ``explored`` (the explorer found no frontier left), ``given_up`` (entry ids not to be
    chosen again), for display ``target_entry``, ``path_xy`` (P, 2) metres and
    ``last_decision`` (the explorer's latest frontier decision), and for the look-again step
    ``looks`` (entry id -> views begun) and ``look_log`` (one dict per trip: kind "look",
    "rival" or "confirm", entry, start and end step, outcome, the viewpoint and path metres, e_max before and
    after, the captured frame's own count ``count_new`` and, for diagnosis, ``geometry`` (see
    :meth:`_trip_geometry`)), ``confirmed`` (entry ids whose
    marginal match a confirm trip settled or could not check) and ``refuted`` (entry id -> the
    captured frame's count, below tau_m).
    """

    def __init__(self, config: AgentConfig, strategy: Strategy, db: ObjectDB, verifier: Verifier,
                 explorer: ExplorationPlanner, crop_cosine: dict[int, float], observations=None):
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
        self.observations = observations
        self.looks: dict[int, int] = {}
        self.look_log: list[dict] = []
        self._look: dict | None = None  # the trip under way
        self._looked_from: dict[int, list[float]] = {}  # entry id -> azimuths of its look-again viewpoints
        self.confirmed: set[int] = set()
        self.refuted: dict[int, float] = {}

    # -- which entries --------------------------------------------------------------------------
    def identifies_now(self) -> bool:
        """Whether entries can be taken for the goal yet (after exploring, for gaussnav)."""
        return not self.strategy.identify_after_exploring or self.explored

    def goal_candidates(self) -> list[ObjectEntry]:
        """Entries taken for the goal and not given up, most likely first (colours, then e_max)."""
        if not self.identifies_now():
            return []
        out = [e for e in self.db if e.id not in self.given_up and self.verifier.is_goal(e)
               and not self.is_refuted(e)]
        return sorted(out, key=lambda e: (-e.colour_similarity, -e.e_max))

    def is_refuted(self, e: ObjectEntry) -> bool:
        """A confirm trip refuted ``e``'s match (or, with ``refute_radius``, a duplicate's: see
        :meth:`refuted_by`) and its e_max has not since reached ``confirm_below``."""
        return self.refuted_by(e) is not None

    def refuted_by(self, e: ObjectEntry) -> int | None:
        """The id of the refuted entry whose refusal covers ``e``, or None: ``e`` itself when a
        confirm trip refuted it, else (with ``refute_radius`` > 0) the nearest refuted entry of the
        same class whose centroid lies within ``refute_radius`` m of ``e``'s: a duplicate entry of
        the same object must not pass where the refuted one could not. Only while both e_max stay
        below ``confirm_below`` (the level that lifts a refusal)."""
        cb = self.cfg.confirm_below
        if e.e_max >= cb:
            return None
        if e.id in self.refuted:
            return e.id
        r = self.cfg.refute_radius
        if r <= 0 or not self.refuted:
            return None
        best, best_d = None, np.inf
        for rid in self.refuted:
            o = self.db[rid]
            if o.label != e.label or o.e_max >= cb:
                continue
            d = float(np.linalg.norm(o.centroid - e.centroid))
            if d <= r and d < best_d:
                best, best_d = rid, d
        return best

    def needs_confirm(self, e: ObjectEntry) -> bool:
        """``e`` is taken for the goal by a marginal feature match (e_max in [tau_m,
        ``confirm_below``), colours undecided) that no confirm trip has settled yet."""
        cfg = self.cfg
        return (cfg.confirm_below > cfg.tau_m and e.id not in self.given_up and e.id not in self.confirmed
                and not self.is_refuted(e) and self.verifier.is_goal(e) and self.verifier.can_decide(e)
                and e.e_max < cfg.confirm_below)


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
        make the robot turn back and forth. A refuted match counts with its e_max here: the refusal
        only withholds the early stop, and once nothing passed, it is still the best evidence."""
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
    def decide(self, pose: np.ndarray, step: int, verify_all=None, capture=None) -> tuple[str, str]:
        """(action, status) for robot ``pose`` (x, y, yaw) at step index ``step`` (frames seen
        so far). ``verify_all()``: called once the house is explored when the strategy identifies
        only then (it runs the due verification). ``capture(entry_id)``: adds the current frame to
        the entry's observations and runs its NVSM again (the look-again step; without it, or with
        ``look_again`` 0, there is none)."""
        trips = self.cfg.look_again > 0 or self.cfg.confirm_below > self.cfg.tau_m
        if capture is not None and trips and self.strategy.nvsm_during_search:
            out = self._look_again(np.asarray(pose, np.float64), step, capture)
            if out is not None:
                return out
        action, status = self._decide(pose, step, verify_all, after_exploring=False)
        if status == "explored_now":
            action, status = self._decide(pose, step, verify_all, after_exploring=True)
        return action, status

    # -- looking again --------------------------------------------------------------------------
    def _end_look(self, step: int, outcome: str, count_new: float | None = None) -> None:
        lk, self._look = self._look, None
        e = self.db[lk["entry"]]
        if lk["kind"] == "confirm" and outcome != "refuted":
            self.confirmed.add(e.id)  # settled, or it could not be checked: the match stands
        self.look_log.append({"kind": lk["kind"], "entry": e.id, "start": lk["start"], "end": int(step),
                              "outcome": outcome, "xy": [float(v) for v in lk["xy"]],
                              "path_m": round(float(lk["path"]), 2), "e_max_before": float(lk["e_max"]),
                              "e_max_after": float(e.e_max), "count_new": count_new,
                              "geometry": lk.get("geometry")})

    def _viewpoint(self, e: ObjectEntry, D: np.ndarray):
        """The look-again viewpoint of entry ``e`` (``choose_viewpoint``) given the geodesic
        distances ``D`` from the robot, or None."""
        occ = self.explorer.occupancy
        frames = self.observations[e.id] if self.observations is not None else []
        seen = list(azimuths_of([f.viewmat for f in frames], e.centroid)) + self._looked_from.get(e.id, [])
        vh = self.verifier.view_holes.get(e.id)
        return choose_viewpoint(e.centroid, e.extent_radius, occ.spec, occ.occupied, D, seen,
                                view_azimuths=None if vh is None else azimuths_of(vh[0], e.centroid),
                                view_holes=None if vh is None else vh[1], distance=self.cfg.look_again_distance,
                                max_path=self.cfg.look_again_max_path)

    def _trip_geometry(self, e: ObjectEntry, v) -> dict:
        """Where a trip looks from, relative to what was seen (diagnosis only; nothing decides on
        it): the viewpoint's azimuth around ``e`` (deg) and distance (m), the azimuths (deg) and
        distances (m) of the cameras of ``e``'s stored observations and earlier trips, the
        smallest azimuth gap between the viewpoint and those (deg), and the azimuth of the NVSM
        camera that gave ``e``'s e_max (None when a camera crop gave it)."""
        c = np.asarray(e.centroid, np.float64)
        frames = self.observations[e.id] if self.observations is not None else []
        eyes = [camera_pose(np.asarray(f.viewmat, np.float64))[0] for f in frames]
        seen = [float(np.arctan2(p[1] - c[1], p[0] - c[0])) for p in eyes] + self._looked_from.get(e.id, [])
        gap = float(np.min(np.abs(wrap_angle(np.asarray(seen) - v.azimuth)))) if seen else None
        best = None
        if e.best_viewmat is not None:
            p = camera_pose(np.asarray(e.best_viewmat, np.float64))[0]
            best = round(float(np.degrees(np.arctan2(p[1] - c[1], p[0] - c[0]))), 1)
        return {"view_az_deg": round(float(np.degrees(v.azimuth)), 1),
                "view_dist_m": round(float(np.hypot(*(np.asarray(v.xy) - c[:2]))), 2),
                "seen_az_deg": [round(float(np.degrees(a)), 1) for a in seen],
                "seen_dist_m": [round(float(np.hypot(*(p[:2] - c[:2]))), 2) for p in eyes],
                "gap_deg": None if gap is None else round(float(np.degrees(gap)), 1), "best_az_deg": best}

    def _begin(self, kind: str, cands: list[ObjectEntry], pose: np.ndarray, step: int) -> dict | None:
        """Begin a trip of ``kind`` ("look", "rival" or "confirm") to the first of ``cands`` that has a
        viewpoint; the others without one are logged (and, for "look", get no more trips; for
        "confirm", their match stands)."""
        if not cands:
            return None
        D = self.explorer.planner().distance_from(pose[:2])
        for e in cands:
            if kind != "confirm":
                self.looks[e.id] = self.looks.get(e.id, 0) + 1
            v = self._viewpoint(e, D)
            if v is None:
                if kind != "confirm":
                    self.looks[e.id] = self.cfg.look_again  # nowhere to look from: no more trips for it
                else:
                    self.confirmed.add(e.id)
                self.look_log.append({"kind": kind, "entry": e.id, "start": int(step), "end": int(step),
                                      "outcome": "no_viewpoint", "xy": None, "path_m": None,
                                      "e_max_before": float(e.e_max), "e_max_after": float(e.e_max),
                                      "count_new": None})
                continue
            geometry = self._trip_geometry(e, v)
            self._looked_from.setdefault(e.id, []).append(v.azimuth)
            return {"kind": kind, "entry": e.id, "xy": v.xy, "start": int(step), "path": v.path, "e_max": e.e_max,
                    "geometry": geometry}
        return None

    def _start_look(self, pose: np.ndarray, step: int) -> dict | None:
        """Begin a confirm trip to the most likely goal candidate when its marginal match is unsettled
        (with ``confirm_by`` "rivals": a look-again trip to an ambiguous entry instead, or, with
        none left, let the match stand); else, while nothing is taken for the goal (and, with ``look_again_after_refute``, once a
        match was refuted), a look-again trip to the most matched ambiguous entry that has views
        left and a viewpoint."""
        cfg = self.cfg
        gc = self.goal_candidates()
        if gc and self.needs_confirm(gc[0]):
            if cfg.confirm_by == "rivals":
                # the ambiguous entries that could overtake the marginal match get their look first
                lk = self._begin("rival", self._ambiguous_left(), pose, step) if cfg.look_again > 0 else None
                if lk is None:
                    self.confirmed.add(gc[0].id)  # no rival left to look at: the match stands
                return lk
            return self._begin("confirm", gc[:1], pose, step)
        if gc:
            return None
        if cfg.look_again <= 0 or (cfg.look_again_after_refute and not self.refuted):
            return None
        return self._begin("look", self._ambiguous_left(), pose, step)

    def _ambiguous_left(self) -> list[ObjectEntry]:
        """Ambiguous entries with look-again views left, most matched first."""
        cands = [e for e in self.db if e.id not in self.given_up and self.looks.get(e.id, 0) < self.cfg.look_again
                 and self.verifier.is_ambiguous(e)]
        return sorted(cands, key=lambda x: -x.e_max)

    def _look_again(self, pose: np.ndarray, step: int, capture) -> tuple[str, str] | None:
        """The action of a look-again or confirm trip, or None when there is none (a settled goal is
        known, nothing is ambiguous, or no viewpoint is left). Arriving and facing the object, it
        calls ``capture(entry_id)``; a confirm trip then keeps the match iff the captured frame's
        own count (``Verifier.step_counts``) reaches tau_m. Then it goes on with the next trip, if
        any."""
        cfg = self.cfg
        while True:
            lk = self._look
            if lk is not None:
                e = self.db[lk["entry"]]
                if lk["kind"] == "look":
                    if self.goal_candidates():
                        self._end_look(step, "goal_found")
                        continue
                    if e.id in self.given_up or not self.verifier.is_ambiguous(e):
                        self._end_look(step, "decided")
                        continue
                elif lk["kind"] == "rival":
                    gc = self.goal_candidates()
                    if not gc or not self.needs_confirm(gc[0]) or e.id in self.given_up \
                            or not self.verifier.is_ambiguous(e):
                        self._end_look(step, "decided")  # a rival passed, or the match became clear
                        continue
                elif not self.needs_confirm(e):
                    self._end_look(step, "decided")  # e.g. its e_max reached confirm_below on the way
                    continue
            else:
                self._look = lk = self._start_look(pose, step)
                if lk is None:
                    return None
                e = self.db[lk["entry"]]
            if step - lk["start"] >= cfg.look_again_steps:
                self._end_look(step, "timeout")
                continue
            self.target_entry = e.id
            d = self.explorer.act(pose, self._object_scores(), goal_xy=lk["xy"], goal_radius=LOOK_AGAIN_RADIUS)
            plan = d.goal
            self.path_xy = d.goal_path
            if plan.status == "unreachable":
                self._end_look(step, "unreachable")
                continue
            if plan.status in ("reached", "closest"):
                err = bearing_error(pose, e.centroid)
                if abs(err) > np.radians(LOOK_AGAIN_FACING_DEG):
                    return ("turn_left" if err > 0 else "turn_right"), _STATUS[lk["kind"]]
                capture(e.id)
                count = float(self.verifier.step_counts.get(e.id, 0.0))
                if lk["kind"] == "confirm":
                    if count >= cfg.tau_m or e.e_max >= cfg.confirm_below:
                        self._end_look(step, "confirmed", count)
                    else:
                        self.refuted[e.id] = count
                        self._end_look(step, "refuted", count)
                else:
                    self._end_look(step, "captured", count)
                continue
            return plan.action, _STATUS[lk["kind"]]

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
        robot to the frontiers around it as a tau_m match would. A refuted match counts with the
        frame that refuted it."""
        cents, scores = self.db.scores()
        for e in self.db:
            rid = self.refuted_by(e)
            if rid is not None:
                scores[e.id] = min(scores[e.id], self.refuted[rid])
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
