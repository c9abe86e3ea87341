"""The perceived-person part of D_T's retrieval key (stop 45, issue 28; beyond the thesis).

The thesis retrieves E_T by image-to-text similarity alone. On the doorway a head-on meeting and
a pass look alike to F_I while the person is still 5-8 m away (E_I cosine >= 0.99 between them),
so an LLU update's view entries cannot tell them apart. The robot's LiDAR already measures the
people (the planner's selection uses them), so a view entry may also be keyed by the state of
the nearest person the robot saw there, relative to the robot:

    s = (range r [m], bearing b [rad, + left], closing speed c [m/s, + approaching],
         lateral offset y [m, robot frame, + left])

With ``OliviaConfig.person_key`` on, a view entry j with person key s_j is ranked for a view
with person state s by ``cos(E_I, key_j) - person_weight * d2(s, s_j)`` and passes the gate only
when ``d2 <= person_gate`` (besides ``view_gate`` on the image cosine), where
``d2 = sum(((s - s_j) / PERSON_SCALE)²)`` is dimensionless. The offline caption entries (not
view entries) keep the image-only ranking; a view entry where nobody was seen ahead matches only
a view where nobody is seen ahead (d2 0), never a perceived person (d2 inf): see
:func:`splatsearch.social.olivia.planner.person_penalty`.
"""

from __future__ import annotations

import numpy as np

PERSON_DIM = 4
# per-component scales of d2 (m, rad, m/s, m): one unit of d2 is a difference of about 1.5 m in
# range, 20° in bearing, 0.5 m/s in closing speed or 0.5 m across
PERSON_SCALE = np.array([1.5, 0.35, 0.5, 0.5], np.float32)
NO_PERSON = np.full(PERSON_DIM, np.nan, np.float32)  # nobody seen ahead: the entry has no person key


def person_state(pose: np.ndarray, people: np.ndarray, people_vel: np.ndarray) -> np.ndarray:
    """(PERSON_DIM,) float32 state of the nearest person ahead (bearing within ±90°) among the
    people the robot perceives, ``people`` (P, 2) world [m] moving at ``people_vel`` (P, 2)
    [m/s], seen from ``pose`` (3,) = (x, y, heading) world: (range m, bearing rad, closing speed
    m/s, lateral offset m). :data:`NO_PERSON` (NaN) when nobody is ahead."""
    people = np.asarray(people, np.float64).reshape(-1, 2)
    vel = np.asarray(people_vel, np.float64).reshape(-1, 2)
    if len(people) == 0:
        return NO_PERSON.copy()
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rel = people - np.asarray(pose[:2], np.float64)
    fwd, lat = rel @ np.array([c, s]), rel @ np.array([-s, c])
    ahead = fwd > 0
    if not np.any(ahead):
        return NO_PERSON.copy()
    rng = np.hypot(fwd, lat)
    i = int(np.argmin(np.where(ahead, rng, np.inf)))
    # closing speed: the person's own velocity toward the robot (the robot's motion is its own)
    closing = -float(vel[i] @ rel[i]) / max(float(rng[i]), 1e-6)
    return np.array([rng[i], np.arctan2(lat[i], fwd[i]), closing, lat[i]], np.float32)


def person_distance2(s: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """(M,) dimensionless squared distance of the state ``s`` (PERSON_DIM,) to the person keys
    ``keys`` (M, PERSON_DIM) under :data:`PERSON_SCALE`; +inf where either is NaN (no person)."""
    d = (np.asarray(keys, np.float32) - np.asarray(s, np.float32)[None]) / PERSON_SCALE
    d2 = np.sum(d * d, -1)
    return np.where(np.isfinite(d2), d2, np.inf)
