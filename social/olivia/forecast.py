"""Where the people the robot sees will be over a plan's horizon: the forecast the plan
selection's safety cost (:func:`~splatsearch.social.olivia.selection.safety_cost`) charges plans
against.

Only what the robot observes goes in: the people's positions and velocities from its two LiDAR
sweeps, and its own pose. Three forecasts, composed:

- **Constant velocity** (the default).
- **Head-on drift decays** (``cross_tau`` > 0, for the people :func:`oncoming_mask` finds): the
  velocity along the line to the robot stays, the part across it decays with time constant
  ``cross_tau`` s. A person drifting sideways while walking at the robot does so to pass
  something and straightens out.
- **People react to the robot** (:func:`reactive_forecast`, gain ``people_react`` > 0): a person
  ahead of the robot moves sideways away from its line of travel until they keep the walker's
  intimate berth from it, the way the social-force walker and the simulated pedestrians make
  way. With constant velocity a person who walks straight at the robot blocks every plan that
  passes them, although they will step aside.
"""

from __future__ import annotations

import numpy as np

from ..convoi.scenarios import PERSON_RADIUS, ROBOT_RADIUS
from .features import FUTURE_STRIDE

#: m, centre to centre: the lateral distance from the robot's line of travel a person who makes
#: way keeps (robot and person radii + the walker's intimate zone, 0.45 m edge to edge)
REACT_BERTH = ROBOT_RADIUS + PERSON_RADIUS + 0.45


def plan_times(H: int) -> np.ndarray:
    """(H,) s: the instants of a plan's poses (every FUTURE_STRIDE sim steps of 0.1 s)."""
    return FUTURE_STRIDE * 0.1 * np.arange(1, H + 1)


def constant_velocity(people: np.ndarray, people_vel: np.ndarray, H: int) -> np.ndarray:
    """(H, P, 2) world: ``people`` (P, 2) m moving on at ``people_vel`` (P, 2) m/s."""
    people = np.asarray(people, np.float64).reshape(-1, 2)
    vel = np.asarray(people_vel, np.float64).reshape(-1, 2)
    return people[None] + plan_times(H)[:, None, None] * vel[None]


def reactive_forecast(people: np.ndarray, people_vel: np.ndarray, H: int, pose: np.ndarray,
                      gain: float, berth: float = REACT_BERTH) -> np.ndarray:
    """(H, P, 2) world: constant velocity plus each person's reaction to the robot at ``pose``
    (3,) (x, y, yaw). A person ahead of the robot (in front of the line through it across its
    heading) whose lateral offset ``l`` from its line of travel is below ``berth`` m moves to
    ``sign(l) x berth`` (the robot's left when exactly on the line: right-hand traffic), a
    first-order approach with rate ``gain`` (1/s): offset ``(berth sign(l) - l)(1 - exp(-gain
    t))`` along the robot's left normal. ``gain`` 0 is constant velocity."""
    if not gain >= 0:
        raise ValueError(f"gain must be >= 0 (1/s), got {gain!r}")
    pred = constant_velocity(people, people_vel, H)
    if gain == 0 or pred.shape[1] == 0:
        return pred
    people = np.asarray(people, np.float64).reshape(-1, 2)
    heading = np.array([np.cos(pose[2]), np.sin(pose[2])])
    left = np.array([-heading[1], heading[0]])
    rel = people - np.asarray(pose[:2], np.float64)
    ahead = rel @ heading > 0
    lat = rel @ left
    side = np.where(lat >= 0, 1.0, -1.0)
    shift = np.where(ahead & (np.abs(lat) < berth), side * berth - lat, 0.0)  # (P,) m
    ramp = 1.0 - np.exp(-gain * plan_times(H))  # (H,)
    return pred + ramp[:, None, None] * shift[None, :, None] * left[None, None]


def forecast_people(people: np.ndarray, people_vel: np.ndarray, H: int, pose: np.ndarray | None = None,
                    oncoming: np.ndarray | None = None, cross_tau: float = 0.0,
                    people_react: float = 0.0) -> np.ndarray:
    """(H, P, 2) the people's predicted centres at the plan's instants (every FUTURE_STRIDE
    steps). Constant velocity, except: for the ``oncoming`` (P,) bool people when ``cross_tau``
    > 0, their velocity along the line to the robot at ``pose`` stays and the part across it
    decays with time constant ``cross_tau`` s (it moves them at most ``speed_across x
    cross_tau`` m sideways); with ``people_react`` > 0 (1/s, needs ``pose``) everyone ahead
    also makes way (:func:`reactive_forecast`)."""
    people = np.asarray(people, np.float64).reshape(-1, 2)
    vel = np.asarray(people_vel, np.float64).reshape(-1, 2)
    t = plan_times(H)[:, None, None]
    pred = constant_velocity(people, vel, H)
    if cross_tau > 0 and oncoming is not None and np.any(oncoming) and pose is not None:
        rel = np.asarray(pose[:2], np.float64) - people
        u = rel / np.maximum(np.linalg.norm(rel, axis=-1, keepdims=True), 1e-6)  # toward the robot
        along = np.sum(vel * u, -1, keepdims=True) * u
        across = vel - along
        decayed = people[None] + t * along[None] + cross_tau * (1 - np.exp(-t / cross_tau)) * across[None]
        pred = np.where(np.asarray(oncoming, bool)[None, :, None], decayed, pred)
    if people_react > 0 and pose is not None:
        pred = pred + reactive_forecast(people, vel, H, pose, people_react) - constant_velocity(people, vel, H)
    return pred
