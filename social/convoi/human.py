"""A human-like reference walker: the reference of OLiVia-Nav's Tables I-II (``"human"``).

It stands in for a person teleoperating the robot who sees the whole scene and knows where
everyone is going. Unlike the DWA-with-critics expert (``"expert"``, kept as a named
alternative), which scores 3-s arcs of constant (v, ω), it plans *along the whole route*:

* **Route**: the scene's shortest path around the walls and around standing groups (never through
  an F-formation), shifted into the walking lane the scenario asks for (keep right), smoothed.
* **Speed profile**: like a walker it slows for corners, v(s) <= sqrt(a_lat / κ(s)), and starts
  braking early enough for them (v² <= v_c² + 2 a_dec Δs).
* **Candidates** (every control step): lateral shifts of the route (``offsets``, blended in over
  ``shift_length`` m, the way people drift aside to pass) x speed factors including standing
  still, each rolled out ``horizon`` steps against the *privileged* forecast of every person
  (the pedestrian simulator forked from now).
* **Cost** (a walker's preferences, not a robot's critics): progress, staying in lane, personal
  space (Hall's 1.2 m, steep below 0.45 m), passing oncoming people on the right (right-hand
  traffic: they go by on the walker's left), never between the members of a group, clearance
  from walls, and not changing its mind (hysteresis).
* **Perception** (stop 46, ``perceive``, the default): it reacts only to the people it has seen,
  with the robot's own test (:func:`~splatsearch.social.convoi.perception.visible_people`: within
  ``sense_range`` m and in line of sight past the walls). Once seen, a person stays known (a
  teleoperator remembers someone who stepped behind a wall). People never seen add no cost, no
  passing side and no group line. ``perceive=False`` is the omniscient walker of stops 33-45
  (``"human_omniscient"``: the "expert with full knowledge").
* **Yielding**: in a 1 m door the candidates that enter while someone is coming through meet them
  in the door at any lateral shift, so standing aside / waiting wins until the door is free.

The chosen candidate is tracked by the robot's unicycle within its limits (the same 0.6 m/s as
the planners compared), so the reference is a path the robot can drive.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import pedsim
from .dwa import step_unicycle
from .geometry import F32, DistanceField, field_lookup, point_segment_distance
from .perception import visible_people
from .scenarios import PERSON_RADIUS, ROBOT_RADIUS, Scenario, resample_polyline

MAX_ROUTE = 512
MAX_PAIRS = 16


@dataclass(frozen=True)
class HumanWalkerConfig:
    """The walker's limits and preferences (SI units).

    v_max (m/s), w_max (rad/s), acc (m/s²): the robot's limits; a_lat: lateral acceleration
    a walker accepts in a turn (m/s²) and a_dec: its braking (m/s²) for corners; offsets: lateral
    shifts of the route (m, + = left); speeds: speed factors; horizon: rollout steps; shift_length:
    arc length (m) over which a shift is blended in (or shift_time s when it walks slower); personal, intimate: Hall's zones (m, edge to
    edge); perceive: react only to people it has seen (robot's range and line of sight),
    False: to everyone (omniscient); sense_range: that range (m, the robot's 8 m);
    oncoming_cone: a person counts as oncoming (to be passed on the right) when walking
    within this angle (rad, 25°) of head-on; group_margin: distance (m) from the line between two group members below which the
    walker would split them; w_*: cost weights."""

    v_max: float = 0.6
    w_max: float = 1.2
    acc: float = 1.0
    a_lat: float = 0.18
    a_dec: float = 0.3
    offsets: tuple = tuple(np.round(np.linspace(-2.4, 2.4, 17), 3).tolist())
    speeds: tuple = (0.0, 0.3, 0.6, 1.0)
    horizon: int = 40
    shift_length: float = 1.2
    shift_time: float = 3.0
    personal: float = 1.2
    intimate: float = 0.45
    group_margin: float = 0.45
    wall_margin: float = 0.1
    w_progress: float = 1.0
    w_lane: float = 0.25
    w_personal: float = 1.5
    w_intimate: float = 30.0
    w_side: float = 0.8
    w_group: float = 20.0
    w_wall: float = 100.0
    w_change: float = 0.15
    lookahead: float = 0.45
    k_heading: float = 2.5
    oncoming_cone: float = 0.44
    perceive: bool = True
    sense_range: float = 8.0


class Route(NamedTuple):
    """The walker's route (padded to MAX_ROUTE): points (M, 2), arc length s (M,), unit
    normals (M, 2) (left), speed cap (M,) from the curvature, n valid points ()."""

    pts: jax.Array
    s: jax.Array
    normal: jax.Array
    vcap: jax.Array
    n: jax.Array


def make_route(path: np.ndarray, cfg: HumanWalkerConfig = HumanWalkerConfig()) -> Route:
    """The :class:`Route` of a polyline ``path`` (M, 2) (m): arc length, normals and the speed
    profile (corner caps from the curvature, with braking distance)."""
    p = np.asarray(path, np.float64)
    if len(p) > MAX_ROUTE:
        length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
        p = np.asarray(resample_polyline(p, length / (MAX_ROUTE - 1) * 1.001), np.float64)[:MAX_ROUTE]
    if len(p) < 2:
        p = np.vstack([p, p + [1e-3, 0.0]])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    d = np.gradient(p, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], -1)
    # curvature from the heading change over +-0.3 m (the route is sampled every 0.1 m)
    h = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    k = 3
    dh = np.abs(np.r_[h[k:], np.repeat(h[-1], k)] - np.r_[np.repeat(h[0], k), h[:-k]])
    ds = np.maximum(np.r_[s[k:], np.repeat(s[-1], k)] - np.r_[np.repeat(s[0], k), s[:-k]], 1e-6)
    kappa = dh / ds
    vcap = np.minimum(cfg.v_max, np.sqrt(cfg.a_lat / np.maximum(kappa, 1e-6)))
    for i in range(len(vcap) - 2, -1, -1):  # brake early enough for what comes
        vcap[i] = min(vcap[i], np.sqrt(vcap[i + 1] ** 2 + 2 * cfg.a_dec * seg[i]))
    n = len(p)
    pad = lambda a, fill: np.concatenate([a, np.repeat(a[-1:] * 0 + fill, MAX_ROUTE - n, 0)])  # noqa: E731
    pts = np.concatenate([p, np.repeat(p[-1:], MAX_ROUTE - n, 0)])
    return Route(jnp.asarray(pts, F32), jnp.asarray(np.r_[s, s[-1] + 1e-3 * np.arange(1, MAX_ROUTE - n + 1)], F32),
                 jnp.asarray(np.concatenate([normal, np.repeat(normal[-1:], MAX_ROUTE - n, 0)]), F32),
                 jnp.asarray(pad(vcap, vcap[-1]), F32), jnp.asarray(n, jnp.int32))


def _interp(route: Route, q):
    """Route point, normal and speed cap at arc lengths ``q`` (...)."""
    s = route.s
    i = jnp.clip(jnp.searchsorted(s, q, side="right") - 1, 0, route.pts.shape[0] - 2)
    t = jnp.clip((q - s[i]) / jnp.maximum(s[i + 1] - s[i], 1e-6), 0.0, 1.0)
    pt = route.pts[i] + t[..., None] * (route.pts[i + 1] - route.pts[i])
    nm = route.normal[i]
    v = route.vcap[i] + t * (route.vcap[i + 1] - route.vcap[i])
    return pt, nm, v


def project(route: Route, pos):
    """(arc length s, signed lateral offset l (m, + = left)) of ``pos`` (2,) on the route."""
    valid = jnp.arange(route.pts.shape[0]) < route.n
    d = jnp.where(valid, jnp.linalg.norm(route.pts - pos, axis=1), jnp.inf)
    i = jnp.argmin(d)
    return route.s[i], jnp.dot(pos - route.pts[i], route.normal[i])


class WalkerWorld(NamedTuple):
    field: DistanceField
    capsules: jax.Array
    capsules_valid: jax.Array
    route: Route
    goal: jax.Array
    pairs: jax.Array
    pairs_valid: jax.Array


class WalkerCarry(NamedTuple):
    pose: jax.Array
    vel: jax.Array
    peds: pedsim.PedState
    t_index: jax.Array
    offset: jax.Array  # the lateral shift chosen last (m)
    # (P,) bool: people the walker has seen so far (perceive=True); None: nobody yet (the first
    # step fills it from what is visible at the start)
    seen: jax.Array | None = None


def candidates(route: Route, s0, l0, v0, cfg: HumanWalkerConfig):
    """(C, H, 2) candidate positions, (C, H) speeds, (C,) offsets, (C,) speed factors: every
    lateral shift x speed factor, from arc length ``s0``, offset ``l0`` and speed ``v0``."""
    offs = jnp.asarray(cfg.offsets, F32)
    fac = jnp.asarray(cfg.speeds, F32)
    O, S = offs.shape[0], fac.shape[0]
    off = jnp.repeat(offs, S)
    f = jnp.tile(fac, O)
    dt = 0.1

    def body(c, _):
        s, v = c
        _, _, cap = _interp(route, s)
        target = f * cap
        v = jnp.clip(target, v - cfg.acc * dt, v + cfg.acc * dt)
        v = jnp.maximum(v, 0.0)
        s = s + v * dt
        return (s, v), (s, v)

    init = (jnp.full(off.shape, s0, F32), jnp.full(off.shape, v0, F32))
    _, (ss, vs) = jax.lax.scan(body, init, None, length=cfg.horizon)  # (H, C)
    ss, vs = ss.T, vs.T
    # a walker steps aside while it walks on (over shift_length m) or while it stands (over shift_time s)
    k_time = jnp.arange(1, cfg.horizon + 1, dtype=F32)[None] * dt / cfg.shift_time
    blend = jnp.clip(jnp.maximum((ss - s0) / cfg.shift_length, k_time), 0.0, 1.0)
    blend = blend * blend * (3 - 2 * blend)  # smoothstep
    lat = l0 + (off[:, None] - l0) * blend
    pt, nm, _ = _interp(route, ss)
    return pt + lat[..., None] * nm, vs, off, f


def walker_cost(pos, speed, off, world: WalkerWorld, people, people_vel, active, prev_offset, s_start,
                cfg: HumanWalkerConfig):
    """(C,) cost of candidates ``pos`` (C, H, 2) with speeds (C, H) and shifts ``off`` (C,)
    against the people's forecast ``people`` (H, P, 2)."""
    route = world.route
    H = pos.shape[1]
    # progress along the route (m) at the horizon, relative to the best possible
    s_end, _ = jax.vmap(lambda p: project(route, p))(pos[:, -1])
    progress = (s_end - s_start) / (cfg.v_max * H * 0.1)
    # lane: stay on the route (which already carries the lane shift)
    lane = jnp.mean(jnp.abs(jax.vmap(jax.vmap(lambda p: project(route, p)[1]))(pos)), 1)
    # people: Hall's zones, edge to edge
    d = jnp.linalg.norm(pos[:, :, None] - people[None], axis=-1) - (ROBOT_RADIUS + PERSON_RADIUS)  # (C, H, P)
    d = jnp.where(active[None, None], d, 1e3)
    w_t = jnp.linspace(1.0, 0.5, H)[None, :, None]  # near future weighs more
    personal = jnp.sum(w_t * jnp.clip(cfg.personal - d, 0.0, None) ** 2, (1, 2)) / H
    intimate = jnp.sum(w_t * jnp.clip(cfg.intimate - d, 0.0, None) ** 2, (1, 2))
    # side: an oncoming person (walking against the walker's direction) should go by on its left
    heading = jnp.diff(pos, axis=1)
    heading = jnp.concatenate([heading, heading[:, -1:]], 1)
    heading = heading / jnp.maximum(jnp.linalg.norm(heading, axis=-1, keepdims=True), 1e-6)
    rel = people[None] - pos[:, :, None]  # (C, H, P, 2)
    cross = heading[..., None, 0] * rel[..., 1] - heading[..., None, 1] * rel[..., 0]  # > 0: person on the left
    # head-on only (within ``oncoming_cone`` of anti-parallel, walking faster than 0.3 m/s): a person
    # crossing diagonally passes on whichever side their path takes them; forcing them to the
    # walker's left would make it cross their path
    ped_speed = jnp.linalg.norm(people_vel, axis=-1)  # (H, P)
    along = jnp.sum(heading[:, :, None, :] * people_vel[None], -1)  # (C, H, P)
    oncoming = (along < -jnp.cos(cfg.oncoming_cone) * ped_speed[None]) & (ped_speed[None] > 0.3)
    near = (d < 1.0) & oncoming
    side = jnp.sum(jnp.where(near & (cross < 0), 1.0, 0.0), (1, 2)) / H
    # groups: never through the line between two members of a group
    a = people[:, world.pairs[:, 0]]  # (H, G, 2)
    b = people[:, world.pairs[:, 1]]
    gd, _ = point_segment_distance(pos[:, :, None], a[None], b[None])  # (C, H, G)
    gap = jnp.linalg.norm(a - b, axis=-1)[None]
    split = (gd < cfg.group_margin + ROBOT_RADIUS) & world.pairs_valid[None, None] & (gap < 2.5)
    group = jnp.sum(split, (1, 2)).astype(F32)
    # walls
    clr = field_lookup(world.field, pos)
    wall = jnp.sum(clr < ROBOT_RADIUS + cfg.wall_margin, 1).astype(F32)
    change = (off - prev_offset) ** 2
    return (-cfg.w_progress * progress + cfg.w_lane * lane + cfg.w_personal * personal + cfg.w_intimate * intimate
            + cfg.w_side * side + cfg.w_group * group + cfg.w_wall * wall + cfg.w_change * change)


@partial(jax.jit, static_argnames=("cfg", "sf"))
def walker_step(carry: WalkerCarry, world: WalkerWorld, seed_key, cfg: HumanWalkerConfig,
                sf: pedsim.SocialForceConfig):
    """One step of the walker (perceive, plan over the route, move, then step the people, who see
    it). Returns the new carry (its ``seen`` (P,): the people known when this step planned), the
    command (v, ω), the chosen candidate (H, 2), the people's contacts with the robot (P,) and
    whether the move was refused (wall)."""
    pose, vel, peds = carry.pose, carry.vel, carry.peds
    if cfg.perceive:
        # a teleoperator reacts to someone only once the robot could see them, and remembers them
        vis = visible_people(pose, peds.pos, peds.active, world.capsules, world.capsules_valid, cfg.sense_range)
        seen = vis if carry.seen is None else carry.seen | vis
    else:
        seen = jnp.ones_like(peds.active) if carry.seen is None else jnp.ones_like(carry.seen)
    known = peds.active & seen
    pv = world.pairs_valid & known[world.pairs[:, 0]] & known[world.pairs[:, 1]]
    heading = jnp.stack([jnp.cos(pose[2]), jnp.sin(pose[2])])
    # the forecast still forks the whole simulator (unseen people may push seen ones), but only
    # the known people's futures enter the cost below
    fut = pedsim.forecast(peds, world.capsules, world.capsules_valid, pose[:2], vel[0] * heading, seed_key,
                          carry.t_index, cfg.horizon, sf)
    fut_vel = jnp.diff(jnp.concatenate([peds.pos[None], fut]), axis=0) / sf.dt
    s0, l0 = project(world.route, pose[:2])
    pos, speed, off, fac = candidates(world.route, s0, l0, vel[0], cfg)
    pos = pos.at[:, 0].set(pos[:, 0])
    cost = walker_cost(pos, speed, off, world._replace(pairs_valid=pv), fut, fut_vel, known, carry.offset, s0, cfg)
    k = jnp.argmin(cost)
    path = pos[k]
    # track: the point ``lookahead`` m ahead on the chosen candidate, at its speed
    dist = jnp.linalg.norm(path - pose[:2], axis=1)
    j = jnp.argmax(dist > cfg.lookahead)
    j = jnp.where(jnp.any(dist > cfg.lookahead), j, path.shape[0] - 1)
    tgt = path[j]
    near_goal = jnp.linalg.norm(world.goal - pose[:2]) < cfg.lookahead
    tgt = jnp.where(near_goal, world.goal, tgt)
    err = jnp.arctan2(tgt[1] - pose[1], tgt[0] - pose[0]) - pose[2]
    err = jnp.arctan2(jnp.sin(err), jnp.cos(err))
    w = jnp.clip(cfg.k_heading * err, -cfg.w_max, cfg.w_max)
    w = jnp.clip(w, vel[1] - 2.5 * 0.1, vel[1] + 2.5 * 0.1)
    # a standing candidate still steps aside (its shift blends in over shift_time): drive that
    # sidestep, or a walker that stopped beside a door post could never get clear of it
    m = max(min(9, cfg.horizon - 1), 1)
    v_ref = jnp.where(fac[k] > 0, speed[k, 0], jnp.linalg.norm(path[m] - path[0]) / (0.1 * m))
    v = v_ref * jnp.clip(jnp.cos(err), 0.0, 1.0)
    v = jnp.where(jnp.abs(err) > 1.2, 0.0, v)
    v = jnp.clip(v, vel[0] - cfg.acc * 0.1, vel[0] + cfg.acc * 0.1)
    v = jnp.clip(v, 0.0, cfg.v_max)
    cmd = jnp.stack([v, w]).astype(F32)
    new_pose = step_unicycle(pose, cmd, 0.1)
    hit = field_lookup(world.field, new_pose[:2]) < ROBOT_RADIUS
    new_pose = jnp.where(hit, pose, new_pose)
    new_vel = jnp.where(hit, jnp.zeros(2, F32), cmd)
    robot_vel = new_vel[0] * jnp.stack([jnp.cos(new_pose[2]), jnp.sin(new_pose[2])])
    peds2, info = pedsim.step(peds, world.capsules, world.capsules_valid, new_pose[:2], robot_vel,
                              pedsim.step_key(seed_key, carry.t_index), sf)
    new = WalkerCarry(new_pose.astype(F32), new_vel.astype(F32), peds2, carry.t_index + 1, off[k], seen)
    return new, cmd, path, info.robot_contact, hit


def make_walker_world(scn: Scenario, cfg: HumanWalkerConfig = HumanWalkerConfig()) -> WalkerWorld:
    """The walker's :class:`WalkerWorld` for ``scn``: its route is the lane-shifted path around
    standing groups (:func:`splatsearch.social.convoi.runner.lane_path`)."""
    from .runner import lane_path

    key = ("walker_world", cfg)
    if key in scn._cache:
        return scn._cache[key]
    caps, valid = scn.padded_capsules()
    route = make_route(lane_path(scn, scn.lane_offset), cfg)
    pairs = [(a, b) for g in scn.groups for k, a in enumerate(g) for b in g[k + 1:]]
    pa = np.zeros((MAX_PAIRS, 2), np.int32)
    pv = np.zeros(MAX_PAIRS, bool)
    if pairs:
        pa[: len(pairs)] = pairs[:MAX_PAIRS]
        pv[: len(pairs)] = True
    w = WalkerWorld(scn.field(), jnp.asarray(caps), jnp.asarray(valid), route, jnp.asarray(scn.goal, F32),
                    jnp.asarray(pa), jnp.asarray(pv))
    scn._cache[key] = w
    return w


def run_walker(scn: Scenario, *, max_steps: int | None = None, cfg: HumanWalkerConfig = HumanWalkerConfig(),
               sf: pedsim.SocialForceConfig | None = None):
    """The walker's episode in ``scn`` as an :class:`~splatsearch.social.convoi.runner.EpisodeResult`
    (planner ``"human"``, or ``"human_omniscient"`` when ``cfg.perceive`` is False); its
    ``detected`` (T, P) holds the people the walker knew when planning each step. Deterministic
    for a given scenario seed."""
    from .runner import GOAL_TOLERANCE, EpisodeResult

    sf = sf or pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    world = make_walker_world(scn, cfg)
    seed_key = jax.random.PRNGKey(scn.seed)
    carry = WalkerCarry(jnp.asarray(scn.start, F32), jnp.zeros(2, F32), scn.peds, jnp.asarray(0, jnp.int32),
                        jnp.asarray(0.0, F32), jnp.zeros_like(scn.peds.active))
    n = scn.max_steps if max_steps is None else int(max_steps)
    poses, people, cmds, contacts = [np.asarray(scn.start, np.float32)], [np.asarray(scn.peds.pos)], [], []
    known = []
    shifts = [0.0]
    wall_hits = 0
    reached = False
    t0 = time.perf_counter()
    for t in range(n):
        if t == 1:
            t0 = time.perf_counter()
        carry, cmd, _, contact, hit = walker_step(carry, world, seed_key, cfg, sf)
        pose = np.asarray(carry.pose)
        poses.append(pose)
        people.append(np.asarray(carry.peds.pos))
        cmds.append(np.asarray(cmd))
        shifts.append(float(carry.offset))
        known.append(np.asarray(carry.seen))
        contacts.append(int(np.asarray(contact).sum()))
        wall_hits += bool(hit)
        if np.linalg.norm(pose[:2] - scn.goal) < GOAL_TOLERANCE:
            reached = True
            break
    T = len(cmds)
    P = len(np.asarray(scn.peds.active))
    return EpisodeResult(scn.name, "human" if cfg.perceive else "human_omniscient", scn.seed, np.asarray(poses),
                         np.asarray(cmds).reshape(T, 2), np.asarray(people), np.asarray(scn.peds.active),
                         np.asarray(known, bool).reshape(T, P) & np.asarray(scn.peds.active)[None],
                         np.arange(T + 1) * scn.dt, np.asarray(scn.goal), np.asarray(scn.start), reached, 0,
                         np.asarray(contacts), wall_hits, 0, 1e3 * (time.perf_counter() - t0) / max(T - 1, 1), {},
                         scn.dt, np.asarray(shifts, np.float32))


def walker_rollout(scn: Scenario, pose, vel, peds: pedsim.PedState, t_index: int, n_steps: int,
                   cfg: HumanWalkerConfig = HumanWalkerConfig(), offset: float = 0.0,
                   seen: np.ndarray | None = None) -> np.ndarray:
    """The walker's poses (k + 1, 3), k <= n_steps, forked from an arbitrary state (pose (3,),
    vel (2,) = (v, ω), the people, the scenario step): what the reference would do from there.

    ``offset`` (m, + = left): the lateral shift the walker holds when forked (its hysteresis,
    ``w_change``, is measured from it). 0 is a walker that has not chosen a side; the reference
    episode's own shift at that step (:attr:`EpisodeResult.shifts`) forks the walker that made
    the reference's choices, which keeps a sidestep it already began.

    ``seen`` (P,) bool: the people the forked walker already knows (with ``cfg.perceive``); None:
    only those visible from ``pose`` (it learns of the others as it walks)."""
    from .runner import GOAL_TOLERANCE

    sf = pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    world = make_walker_world(scn, cfg)
    seed_key = jax.random.PRNGKey(scn.seed)
    known = jnp.zeros_like(peds.active) if seen is None else jnp.asarray(np.asarray(seen, bool))
    carry = WalkerCarry(jnp.asarray(pose, F32), jnp.asarray(vel, F32), peds, jnp.asarray(int(t_index), jnp.int32),
                        jnp.asarray(float(offset), F32), known)
    out = [np.asarray(pose, np.float32)]
    for _ in range(int(n_steps)):
        carry, *_ = walker_step(carry, world, seed_key, cfg, sf)
        out.append(np.asarray(carry.pose))
        if np.linalg.norm(out[-1][:2] - scn.goal) < GOAL_TOLERANCE:
            break
    return np.stack(out)
