"""OLiVia-Nav's plan selection costs: what the planner subtracts from the networks' scores of the
K plans before it picks one (:func:`selection_scores`, used by
:func:`~splatsearch.social.olivia.planner.run_olivia_episode`).

Everything here reads only what the robot observes: its pose, the plan it follows, and the
people's positions and velocities from its two LiDAR sweeps.

People walking head-on toward the robot (:func:`oncoming_mask`, the walker's 25° cone) are
treated apart in two ways, because a head-on meeting is where a person and the robot both make
way:

- **Yielding is not held back by the commitment.** The consistency cost keeps the robot from
  switching sides plan after plan. While someone comes at it head-on it does not charge the part
  of a plan's deviation that lies to the right of the followed plan (right-hand traffic: the
  walker steps right and lets the person by), so the robot can step aside; moving back left
  still costs.
- **Their drift across the robot's line is transient.** A person walking toward the robot and
  drifting sideways does so to pass something (a door post, the robot itself) and straightens
  out; a constant-velocity forecast carries that drift on for the whole 4 s horizon and puts the
  person into the very space the robot would yield to. For them the safety cost's forecast keeps
  the velocity along the person-robot line and lets the part across it decay with time
  constant ``cross_tau``. Everybody else (standing, crossing, walking away) stays at constant
  velocity.

The forecasts (and the opt-in one where people make way for the robot) are in
:mod:`~splatsearch.social.olivia.forecast`.
"""

from __future__ import annotations

import numpy as np

from ..convoi.scenarios import PERSON_RADIUS, ROBOT_RADIUS
from .features import FUTURE_STRIDE
from .forecast import forecast_people, plan_times  # noqa: F401 - forecast_people re-exported

WALL_MARGIN = 0.05  # m: the clearance a plan keeps from the map (the NC cuts corners by about this)
ONCOMING_CONE = 0.44  # rad (25°): the walker's `oncoming_cone`
ONCOMING_SPEED = 0.3  # m/s: slower people are not walking at the robot
ONCOMING_RADIUS = 4.0  # m: farther people have time to change their way (the LLU buffer's tag)
ROBOT_SPEED = 0.6  # m/s: the robot's top speed (the follower's and the walker's limit)


def consistency_cost(trajs_world: np.ndarray, prev_world: np.ndarray | None, elapsed: float,
                     min_length: float = 0.6, free_right: np.ndarray | None = None) -> np.ndarray:
    """(K,) mean squared distance (m²) of each candidate plan ``trajs_world`` (K, horizon, 2)
    (world, poses every FUTURE_STRIDE steps from now) from the plan being followed,
    ``prev_world`` (1 + horizon, 2) (its start pose, then its poses), made ``elapsed`` s ago and
    read at the same instants (held at its end). Zeros without a previous plan, and when it
    was a stop (under ``min_length`` m): waiting commits to nothing, and holding to it would
    keep the robot waiting. ``free_right`` (2,) unit world vector (the robot's right): the part
    of a deviation along it (to the right) is not charged (used while someone comes head-on)."""
    K, H = trajs_world.shape[:2]
    if prev_world is None or np.sum(np.linalg.norm(np.diff(prev_world, axis=0), axis=1)) < min_length:
        return np.zeros(K)
    step = FUTURE_STRIDE * 0.1
    tp = np.arange(len(prev_world)) * step
    tq = np.minimum(elapsed + step * np.arange(1, H + 1), tp[-1])
    ref = np.stack([np.interp(tq, tp, prev_world[:, 0]), np.interp(tq, tp, prev_world[:, 1])], -1)
    d = trajs_world - ref[None]
    sq = np.sum(d ** 2, -1)
    if free_right is not None:
        sq = sq - np.clip(d @ np.asarray(free_right, np.float64), 0.0, None) ** 2
    return np.mean(sq, -1)


def oncoming_mask(pose: np.ndarray, people: np.ndarray, people_vel: np.ndarray, cone: float = ONCOMING_CONE,
                  radius: float = ONCOMING_RADIUS, min_speed: float = ONCOMING_SPEED,
                  meet_time: float = 0.0, robot_speed: float = ROBOT_SPEED) -> np.ndarray:
    """(P,) bool: which of the people seen, ``people`` (P, 2) world moving at ``people_vel``
    (P, 2) m/s, are ahead of the robot at ``pose`` (3,) (x, y, yaw) (within 60° of its heading
    and ``radius`` m) and walk toward it within ``cone`` rad of head-on, faster than
    ``min_speed`` m/s (closing on it). With ``meet_time`` > 0 (s) the distance is instead
    ``meet_time x`` (their speed toward the robot + ``robot_speed``): close enough to meet it
    within that time (a plan's horizon)."""
    people = np.asarray(people, np.float64).reshape(-1, 2)
    vel = np.asarray(people_vel, np.float64).reshape(-1, 2)
    if len(people) == 0:
        return np.zeros(0, bool)
    heading = np.array([np.cos(pose[2]), np.sin(pose[2])])
    rel = people - np.asarray(pose[:2], np.float64)
    dist = np.linalg.norm(rel, axis=-1)
    speed = np.linalg.norm(vel, axis=-1)
    ahead = rel @ heading > 0.5 * dist
    to_robot = -rel / np.maximum(dist[:, None], 1e-6)
    cos_to = np.sum(vel * to_robot, -1) / np.maximum(speed, 1e-6)
    if meet_time > 0:
        radius = meet_time * (speed * np.clip(cos_to, 0.0, None) + robot_speed)
    return ahead & (dist < radius) & (speed > min_speed) & (cos_to > np.cos(cone))


def oncoming_count(pose: np.ndarray, people: np.ndarray, people_vel: np.ndarray, cone: float = ONCOMING_CONE,
                   radius: float = ONCOMING_RADIUS, min_speed: float = ONCOMING_SPEED) -> int:
    """How many people :func:`oncoming_mask` finds: the situations where the walker steps aside.
    Only what the robot observes, so a deployed robot can tag its own views this way."""
    return int(np.sum(oncoming_mask(pose, people, people_vel, cone, radius, min_speed)))


def safety_cost(trajs_world: np.ndarray, people: np.ndarray, people_vel: np.ndarray, margin: float,
                pose: np.ndarray | None = None, oncoming: np.ndarray | None = None,
                cross_tau: float = 0.0, people_react: float = 0.0) -> np.ndarray:
    """(K,) intrusion of each plan ``trajs_world`` (K, horizon, 2) into the space of the people
    seen, ``people`` (P, 2) world moving at ``people_vel`` (P, 2) m/s, predicted by
    :func:`~splatsearch.social.olivia.forecast.forecast_people` (constant velocity unless
    ``cross_tau`` > 0 and ``oncoming``, or ``people_react`` > 0): the
    sum over the plan's poses of ``max(0, margin - edge gap)²`` (m²), nearer poses weighing
    more (1 down to 0.5)."""
    K, H = trajs_world.shape[:2]
    if len(people) == 0:
        return np.zeros(K)
    pred = forecast_people(people, people_vel, H, pose, oncoming, cross_tau, people_react)  # (H, P, 2)
    gap = np.linalg.norm(trajs_world[:, :, None] - pred[None], axis=-1) - (ROBOT_RADIUS + PERSON_RADIUS)
    w = np.linspace(1.0, 0.5, H)[None, :]
    return np.sum(w * np.max(np.clip(margin - gap, 0.0, None), -1) ** 2, -1)


def side_cost(trajs_world: np.ndarray, people: np.ndarray, people_vel: np.ndarray, cone: float = ONCOMING_CONE,
              near: float = 1.0) -> np.ndarray:
    """(K,) how many of the people seen, ``people`` (P, 2) world moving at ``people_vel`` (P, 2)
    m/s (constant velocity), walk head-on toward plan ``trajs_world`` (K, horizon, 2) (within
    ``cone`` rad of its heading, faster than 0.3 m/s) and go by on its right within ``near`` m
    (edge to edge) at the closest approach: right-hand traffic passes them on the left."""
    K, H = trajs_world.shape[:2]
    if len(people) == 0:
        return np.zeros(K)
    pred = people[None] + plan_times(H)[:, None, None] * people_vel[None]  # (H, P, 2)
    # the plan's direction of travel (first to last pose), not its pose-to-pose heading, which
    # turns away from the person while stepping aside
    chord = trajs_world[:, -1] - trajs_world[:, 0]
    chord = chord / np.maximum(np.linalg.norm(chord, axis=-1, keepdims=True), 1e-6)
    head = np.broadcast_to(chord[:, None], trajs_world.shape)  # (K, H, 2)
    rel = pred[None] - trajs_world[:, :, None]  # (K, H, P, 2)
    dist = np.linalg.norm(rel, axis=-1)
    i = np.argmin(dist, axis=1)  # (K, P) closest approach
    take = lambda a: np.take_along_axis(a, i[:, None, :], 1)[:, 0]  # noqa: E731
    cross = take(head[:, :, None, 0] * rel[..., 1] - head[:, :, None, 1] * rel[..., 0])  # > 0: on the left
    speed = np.linalg.norm(people_vel, axis=-1)
    along = take(np.sum(head[:, :, None, :] * people_vel[None, None], -1))
    oncoming = (along < -np.cos(cone) * speed[None]) & (speed[None] > ONCOMING_SPEED)
    gap = take(dist) - (ROBOT_RADIUS + PERSON_RADIUS)
    return np.sum(oncoming & (cross < 0) & (gap < near), -1).astype(np.float64)


def selection_scores(logits: np.ndarray, cand: np.ndarray, pose: np.ndarray, prev_world: np.ndarray | None,
                     elapsed: float, people: np.ndarray, people_vel: np.ndarray, clearance: np.ndarray | None,
                     cfg) -> dict:
    """The selection's score of each of the K plans and its parts.

    logits (K,): the networks' log-scores; cand (K, horizon, 2) world: the plans; pose (3,):
    the robot's; prev_world (1 + horizon, 2) or None: the plan being followed, made ``elapsed``
    s ago; people (P, 2), people_vel (P, 2) m/s: the people in line of sight; clearance
    (K, horizon) m or None: the map's clearance at the plans' poses; cfg: an
    :class:`~splatsearch.social.olivia.planner.OliviaConfig` (``consistency``, ``safety``,
    ``safety_margin``, ``pass_right``, ``oncoming_yield``, ``cross_tau``, ``people_react``, ``oncoming_time``).

    Returns ``{"score": (K,), "consistency", "safety", "side", "map": (K,) penalties already
    weighted, "oncoming": number of head-on people}``; the plan picked is ``argmax(score)``."""
    K = len(logits)
    people = np.asarray(people, np.float64).reshape(-1, 2)
    people_vel = np.asarray(people_vel, np.float64).reshape(-1, 2)
    # head-on: anyone who can meet the robot within a plan's horizon
    on = oncoming_mask(pose, people, people_vel, meet_time=cfg.oncoming_time)
    zero = np.zeros(K)
    parts = {"consistency": zero, "safety": zero, "side": zero, "map": zero, "oncoming": int(np.sum(on))}
    if cfg.consistency > 0 and prev_world is not None:
        # a plan is a commitment: switching sides on every cycle walks into what both avoid
        right = np.array([np.sin(pose[2]), -np.cos(pose[2])])
        free = right if (cfg.oncoming_yield and np.any(on)) else None
        parts["consistency"] = cfg.consistency * consistency_cost(cand, prev_world, elapsed, free_right=free)
    if cfg.safety > 0:
        parts["safety"] = cfg.safety * safety_cost(cand, people, people_vel, cfg.safety_margin, pose, on,
                                                   cfg.cross_tau, cfg.people_react)
        if cfg.pass_right > 0:
            parts["side"] = cfg.pass_right * side_cost(cand, people, people_vel)
        if clearance is not None:
            # a plan through a door post is refused move by move, forever
            parts["map"] = cfg.safety * np.sum(np.clip(ROBOT_RADIUS + WALL_MARGIN - clearance, 0.0, None) ** 2, -1) * 100.0
    parts["score"] = (np.asarray(logits, np.float64) - parts["consistency"] - parts["safety"] - parts["side"]
                      - parts["map"])
    return parts
