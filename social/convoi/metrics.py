"""Trajectory and reference-path metrics in JAX (thesis Tables I-II, CoNVOI Tables I-II).

Trajectories are (N, 2) world points in metres (a pose array (N, 3) is cut to x, y). The jitted
kernels work on static shapes: the public functions pad every trajectory to a power-of-two
length by repeating its last point, which changes none of the values below (a repeated point adds
no length, no new distance and no new Fréchet coupling), so a whole evaluation compiles a few
times instead of once per episode length.

==============================  ====================================================================
:func:`mse`                     mean squared Euclidean distance (m²) between the two trajectories
                                resampled to ``n`` points evenly spaced in arc length
:func:`hausdorff`               symmetric Hausdorff distance (m)
:func:`frechet`                 discrete Fréchet distance (m) (Eiter & Mannila 1994)
:func:`psv_duration`            personal-space violation: seconds during which the robot is closer
                                than ``zone`` (default 0.25 m) to a person; one value per zone
:func:`path_length`             arc length (m)
:func:`normalized_length`       path length / straight-line start-goal distance (≈ 1 is direct)
:func:`mean_velocity`           path length / duration (m/s)
:func:`min_distance_to_people`  smallest robot-person distance (m)
:func:`collision_count`         number of collision onsets (robot-person overlaps and wall contacts)
:func:`success`                 reached the goal without any collision
:func:`reference_path_error`    distance (m) between the mean points of two reference paths
:func:`cosine_similarity`       cosine of the angle between the robot-to-mean-point directions
:func:`path_unacceptable`       a reference path (from the robot) crosses an obstacle, a person or
                                the gap between two members of a group
:func:`fraction_unacceptable`   share of unacceptable paths (CoNVOI reports it in [0, 1])
==============================  ====================================================================

Distances to people are centre to centre unless radii are given, in which case they are edge to
edge (``robot_radius`` + ``person_radius`` subtracted), which is how the thesis' 0.25 m personal
space reads for a robot and a person who are not points.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .geometry import F32, DistanceField, field_lookup, pad_rows, point_segment_distance


def _xy(a, name: str) -> np.ndarray:
    a = np.asarray(a, np.float32)
    if a.ndim != 2 or a.shape[1] < 2 or len(a) < 1:
        raise ValueError(f"{name} must be (N, 2) or (N, 3) with N >= 1, got shape {a.shape}")
    a = a[:, :2]
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf")
    return a


def _bucket(n: int, minimum: int = 32) -> int:
    return max(minimum, 1 << int(np.ceil(np.log2(max(n, 1)))))


def _pad(a: np.ndarray, n: int | None = None) -> jax.Array:
    n = _bucket(len(a)) if n is None else n
    if len(a) < n:
        a = np.concatenate([a, np.repeat(a[-1:], n - len(a), 0)])
    return jnp.asarray(a)


# -- kernels ----------------------------------------------------------------------------------

@jax.jit
def _pairwise(a, b):
    return jnp.linalg.norm(a[:, None] - b[None], axis=-1)


@jax.jit
def _hausdorff(a, b):
    d = _pairwise(a, b)
    return jnp.maximum(jnp.max(jnp.min(d, 1)), jnp.max(jnp.min(d, 0)))


@jax.jit
def _frechet(a, b):
    # dynamic programme over anti-diagonals k = i + j: every cell of a diagonal depends only on
    # the two previous diagonals, so one scan step updates a whole diagonal at once
    d = _pairwise(a, b)
    n, m = d.shape
    i = jnp.arange(n)
    inf = jnp.asarray(jnp.inf, d.dtype)

    def diag(k):
        j = k - i
        ok = (j >= 0) & (j < m)
        return jnp.where(ok, d[i, jnp.clip(j, 0, m - 1)], inf), ok

    def body(carry, k):
        prev2, prev1 = carry  # diagonals k-2, k-1, indexed by i
        dk, ok = diag(k)
        up = prev1  # (i, k-1-i): same i on diagonal k-1
        left = jnp.concatenate([jnp.full((1,), inf), prev1[:-1]])  # (i-1, k-i)
        corner = jnp.concatenate([jnp.full((1,), inf), prev2[:-1]])  # (i-1, k-1-i)
        best = jnp.minimum(jnp.minimum(up, left), corner)
        cur = jnp.where(ok, jnp.maximum(dk, best), inf)
        return (prev1, cur), None

    first = jnp.where(i == 0, d[0, 0], inf)
    (_, last), _ = jax.lax.scan(body, (jnp.full((n,), inf), first), jnp.arange(1, n + m - 1))
    return jnp.where(n + m - 1 > 1, last[n - 1], d[0, 0])


@partial(jax.jit, static_argnums=1)
def _resample(a, n: int):
    seg = jnp.linalg.norm(jnp.diff(a, axis=0), axis=1)
    s = jnp.concatenate([jnp.zeros(1, a.dtype), jnp.cumsum(seg)])
    q = jnp.linspace(0.0, 1.0, n, dtype=a.dtype) * s[-1]
    # searchsorted keeps the first of repeated arc lengths, so padded duplicates are harmless
    k = jnp.clip(jnp.searchsorted(s, q, side="right") - 1, 0, a.shape[0] - 2)
    t = jnp.where(s[k + 1] > s[k], (q - s[k]) / jnp.where(s[k + 1] > s[k], s[k + 1] - s[k], 1.0), 0.0)
    return a[k] + t[:, None] * (a[k + 1] - a[k])


@jax.jit
def _length(a):
    return jnp.sum(jnp.linalg.norm(jnp.diff(a, axis=0), axis=1))


# -- trajectory metrics ---------------------------------------------------------------------

def resample(traj, n: int = 100) -> np.ndarray:
    """(n, 2) points evenly spaced in arc length along ``traj`` (N, 2), ends included."""
    a = _xy(traj, "traj")
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    if len(a) == 1:
        return np.repeat(a, n, 0)
    return np.asarray(_resample(_pad(a), n))


def mse(traj, reference, n: int = 100) -> float:
    """Mean squared distance (m²) between ``traj`` and ``reference`` resampled to ``n`` points
    each by arc length (the thesis' positional error)."""
    a, b = resample(traj, n), resample(reference, n)
    return float(jnp.mean(jnp.sum((jnp.asarray(a) - jnp.asarray(b)) ** 2, -1)))


def hausdorff(traj, reference) -> float:
    """Symmetric Hausdorff distance (m) between two point sequences (N, 2) and (M, 2)."""
    return float(_hausdorff(_pad(_xy(traj, "traj")), _pad(_xy(reference, "reference"))))


def frechet(traj, reference) -> float:
    """Discrete Fréchet distance (m) between two polylines (N, 2) and (M, 2) (any lengths)."""
    return float(_frechet(_pad(_xy(traj, "traj")), _pad(_xy(reference, "reference"))))


def path_length(traj) -> float:
    """Arc length (m) of ``traj`` (N, 2)."""
    return float(_length(_pad(_xy(traj, "traj"))))


def normalized_length(traj, start=None, goal=None) -> float:
    """Path length / straight-line distance from ``start`` to ``goal`` (default: the
    trajectory's first and last points). Raises if they coincide."""
    a = _xy(traj, "traj")
    s = a[0] if start is None else np.asarray(start, np.float32)[:2]
    g = a[-1] if goal is None else np.asarray(goal, np.float32)[:2]
    d = float(np.linalg.norm(g - s))
    if d <= 1e-9:
        raise ValueError("start and goal coincide: the normalised length is undefined")
    return path_length(a) / d


def mean_velocity(traj, dt: float) -> float:
    """Mean linear speed (m/s): path length over the duration (N - 1) * ``dt``."""
    a = _xy(traj, "traj")
    if dt <= 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    if len(a) < 2:
        return 0.0
    return path_length(a) / ((len(a) - 1) * dt)


@jax.jit
def _gaps(robot, people, valid, offset):
    d = jnp.linalg.norm(people - robot[:, None], axis=-1) - offset
    return jnp.min(jnp.where(valid, d, jnp.inf), 1)


def _people_inputs(robot, people, valid):
    r = _xy(robot, "robot")
    p = np.asarray(people, np.float32)
    if p.ndim != 3 or p.shape[0] != len(r) or p.shape[2] != 2:
        raise ValueError(f"people must be (T, P, 2) with T = {len(r)}, got shape {p.shape}")
    if valid is None:
        v = np.ones(p.shape[:2], bool)
    else:
        v = np.asarray(valid, bool)
        if v.ndim == 1:
            v = np.broadcast_to(v, p.shape[:2])
        if v.shape != p.shape[:2]:
            raise ValueError(f"valid must be (P,) or (T, P), got {v.shape}")
    return r, p, v


def people_gaps(robot, people, valid=None, robot_radius: float = 0.0, person_radius: float = 0.0) -> np.ndarray:
    """(T,) distance (m) from the robot to the nearest valid person at each step (inf if none);
    edge to edge when radii are given. robot: (T, 2); people: (T, P, 2); valid: (P,) or (T, P)."""
    r, p, v = _people_inputs(robot, people, valid)
    T = len(r)
    n = _bucket(T)
    rp = np.concatenate([r, np.repeat(r[-1:], n - T, 0)])
    pp = np.concatenate([p, np.repeat(p[-1:], n - T, 0)])
    vp = np.concatenate([v, np.zeros((n - T, v.shape[1]), bool)])
    return np.asarray(_gaps(jnp.asarray(rp), jnp.asarray(pp), jnp.asarray(vp), robot_radius + person_radius))[:T]


def psv_duration(robot, people, dt: float, zone=0.25, valid=None, robot_radius: float = 0.0,
                 person_radius: float = 0.0):
    """Personal-space violation duration (s): time the robot spends closer than ``zone`` m to any
    person (thesis Table I: < 0.25 m). ``zone`` may be a sequence of zones (e.g. Hall's 0.45,
    1.2, 3.6 m); then one duration per zone (np.ndarray). Each step counts ``dt`` seconds."""
    g = people_gaps(robot, people, valid, robot_radius, person_radius)
    z = np.asarray(zone, np.float64)
    if np.any(z <= 0):
        raise ValueError("zones must be > 0")
    out = (g[None] < z.reshape(-1, 1)).sum(1) * float(dt)
    return float(out[0]) if z.ndim == 0 else out


def min_distance_to_people(robot, people, valid=None, robot_radius: float = 0.0, person_radius: float = 0.0) -> float:
    """Smallest robot-person distance (m) over the episode (inf with nobody)."""
    return float(np.min(people_gaps(robot, people, valid, robot_radius, person_radius)))


def collision_count(robot, people, valid=None, robot_radius: float = 0.25, person_radius: float = 0.25,
                    field: DistanceField | None = None) -> int:
    """Number of collision *onsets*: steps where the robot starts overlapping a person (edge gap
    < 0) or, with ``field``, a static obstacle (clearance < robot_radius)."""
    g = people_gaps(robot, people, valid, robot_radius, person_radius)
    hit = g < 0
    if field is not None:
        c = np.asarray(field_lookup(field, jnp.asarray(_xy(robot, "robot"))))
        hit = hit | (c < robot_radius)
    onsets = hit & ~np.r_[False, hit[:-1]]
    return int(onsets.sum())


def success(reached: bool, collisions: int) -> bool:
    """Success: the goal was reached and nothing was hit on the way."""
    return bool(reached) and int(collisions) == 0


# -- reference-path metrics (CoNVOI Table I) --------------------------------------------------

def reference_path_error(path, reference) -> float:
    """Distance (m) between the mean points of two reference paths (K, 2) and (L, 2)."""
    a, b = _xy(path, "path"), _xy(reference, "reference")
    return float(jnp.linalg.norm(jnp.mean(jnp.asarray(a), 0) - jnp.mean(jnp.asarray(b), 0)))


def cosine_similarity(path, reference, origin=(0.0, 0.0)) -> float:
    """Cosine of the angle between the directions from ``origin`` (the robot, default the
    robot-frame origin) to each path's mean point; 0 if either direction is null."""
    o = jnp.asarray(np.asarray(origin, np.float32)[:2])
    u = jnp.mean(jnp.asarray(_xy(path, "path")), 0) - o
    v = jnp.mean(jnp.asarray(_xy(reference, "reference")), 0) - o
    nu, nv = jnp.linalg.norm(u), jnp.linalg.norm(v)
    return float(jnp.where((nu > 0) & (nv > 0), jnp.dot(u, v) / jnp.maximum(nu * nv, 1e-12), 0.0))


@partial(jax.jit, static_argnames="samples")
def _unacceptable(pts, valid, field, clearance, people, people_valid, person_gap, pairs, pairs_valid, samples: int):
    # the polyline origin -> p1 -> p2 ... through the valid points, densely sampled
    pts = jnp.where(valid[:, None], pts, jnp.nan)

    # each segment starts at the previous valid point (the origin for the first one)
    def carry_last(last, p):
        return jnp.where(jnp.isnan(p[0]), last, p), last

    _, starts = jax.lax.scan(carry_last, jnp.zeros(2, pts.dtype), pts)
    t = jnp.linspace(0.0, 1.0, samples, dtype=pts.dtype)
    seg = starts[:, None] + t[None, :, None] * (pts - starts)[:, None]  # (K, S, 2)
    ok = valid[:, None] & jnp.ones((1, samples), bool)
    c = field_lookup(field, jnp.nan_to_num(seg))
    bad_static = jnp.any(ok & (c < clearance))
    d = jnp.linalg.norm(jnp.nan_to_num(seg)[:, :, None] - people[None, None], axis=-1)
    bad_people = jnp.any(ok[..., None] & people_valid[None, None] & (d < person_gap))
    a, b = people[pairs[:, 0]], people[pairs[:, 1]]
    dg, _ = point_segment_distance(jnp.nan_to_num(seg)[:, :, None], a[None, None], b[None, None])
    bad_group = jnp.any(ok[..., None] & pairs_valid[None, None] & (dg < 0.5 * clearance + 0.05))
    return bad_static | bad_people | bad_group


def path_unacceptable(path, field: DistanceField, *, clearance: float = 0.25, people=None, person_gap: float = 0.5,
                      group_pairs=None, samples: int = 16) -> bool:
    """Whether the reference path ``path`` (K, 2) — walked from the origin of the frame of
    ``field`` (the robot) through its points in order — is unacceptable: it passes closer than
    ``clearance`` to an obstacle, closer than ``person_gap`` to a person centre ``people`` (P, 2),
    or between two members of a group (``group_pairs`` (G, 2) indices into ``people``)."""
    pts = _xy(path, "path")
    pp, pv = pad_rows(pts, _bucket(len(pts), 8))
    ppl, plv = pad_rows(people, 16, truncate=True)
    prs, prv = pad_rows(group_pairs, 16, np.int32, truncate=True)
    return bool(_unacceptable(jnp.asarray(pp), jnp.asarray(pv), field, float(clearance), jnp.asarray(ppl),
                              jnp.asarray(plv), float(person_gap), jnp.asarray(prs), jnp.asarray(prv), samples))


def fraction_unacceptable(flags) -> float:
    """Share (in [0, 1]) of unacceptable reference paths; 0 for an empty list."""
    f = np.asarray(flags, bool).reshape(-1)
    return float(jnp.mean(jnp.asarray(f, F32))) if f.size else 0.0


# -- SEANavBench-style social metrics (Tsoi et al., SEAN 2.0) ---------------------------------

#: Hall's proxemic zones (m, edge to edge between the robot's and a person's discs)
INTIMATE_ZONE = 0.45
PERSONAL_ZONE = 1.2


def path_irregularity(robot) -> float:
    """Rotation beyond what facing the goal needs, per metre (rad/m): (Σ|Δyaw| - |yaw_end -
    yaw_start|) / path length, over ``robot`` poses (T, 3) (yaw unwrapped). 0 for a straight or
    single-turn path; larger for weaving."""
    r = np.asarray(robot, np.float64)
    if r.ndim != 2 or r.shape[1] < 3:
        raise ValueError(f"robot must be (T, 3) poses, got {r.shape}")
    if len(r) < 2:
        return 0.0
    yaw = np.unwrap(r[:, 2])
    total = float(np.sum(np.abs(np.diff(yaw))))
    need = abs(float(yaw[-1] - yaw[0]))
    length = float(np.sum(np.linalg.norm(np.diff(r[:, :2], axis=0), axis=1)))
    return max(total - need, 0.0) / max(length, 1e-6)


def time_not_moving(robot, dt: float, speed: float = 0.05) -> float:
    """Seconds the robot moved slower than ``speed`` m/s (SEANavBench's "time not moving")."""
    r = _xy(robot, "robot")
    if len(r) < 2:
        return 0.0
    v = np.linalg.norm(np.diff(r, axis=0), axis=1) / float(dt)
    return float(np.sum(v < speed) * float(dt))


def social_metrics(robot, people, active, dt: float, reached: bool, robot_radius: float = 0.25,
                   person_radius: float = 0.25) -> dict:
    """SEANavBench-style metrics of one episode: ``completed`` (goal reached, 0/1),
    ``irregularity`` (rad/m, :func:`path_irregularity`), ``not_moving_s`` (s), ``personal_s`` and
    ``intimate_s`` (s within Hall's personal 1.2 m / intimate 0.45 m zones, edge to edge),
    ``min_dist`` (m, edge to edge; inf with nobody). robot: (T, 3) poses; people: (T, P, 2);
    active: (P,) bool."""
    robot = np.asarray(robot)
    zones = psv_duration(robot[:, :2], people, dt, (PERSONAL_ZONE, INTIMATE_ZONE), active, robot_radius, person_radius)
    return {"completed": float(bool(reached)), "irregularity": path_irregularity(robot),
            "not_moving_s": time_not_moving(robot[:, :2], dt), "personal_s": float(zones[0]),
            "intimate_s": float(zones[1]),
            "min_dist": min_distance_to_people(robot[:, :2], people, active, robot_radius, person_radius)}
