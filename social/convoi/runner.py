"""Closed-loop episodes: a planner drives the robot through a scenario among simulated people.

Planners (:data:`PLANNERS`):

* ``dwa``: the JAX DWA (:mod:`.dwa`) with its default critics, following a carrot on the static
  global path; it sees the people in its line of sight and extrapolates them at constant velocity.
* ``convoi``: the same DWA plus CoNVOI's reference-path critic (eq 5, 6), the reference path coming
  from :class:`splatsearch.social.convoi.CoNVOI` (context, marked image, VLM, extrapolation, re-query).
* ``human``: the human-like reference walker (:mod:`.human`): plans over the whole route with the
  people's privileged future, walker's preferences (lanes, personal space, passing side, groups,
  corners, doors); the reference of OLiVia-Nav's tables. It reacts to a person only once the
  robot could see them (range and line of sight, as the robot's perception); ``human_omniscient``
  is the same walker reacting to everyone from the start (the reference of stops 33-45).
* ``expert``: the DWA-with-critics "teleoperation" reference (the alternative): a privileged, socially compliant DWA that
  knows every pedestrian's future (it forks the simulator every step), keeps out of personal
  space (1 m), never cuts between group members, and keeps right on a lane-shifted global path
  where the scenario asks for it.

Each control step (dt = 0.1 s): perceive, plan, move the robot (a move into a wall is refused
and counted), then step the pedestrians, who see the robot. The episode ends at the goal
(``goal_tolerance``) or after the scenario's ``max_steps``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import pedsim
from .costs import CriticSpec
from .dwa import (
    DWAConfig,
    DWAInputs,
    constant_velocity_forecast,
    plan,
    reference_critic,
    step_unicycle,
)
from .geometry import F32, DistanceField, field_lookup
from .perception import visible_people
from .scenarios import (
    PERSON_RADIUS,
    ROBOT_RADIUS,
    Scenario,
    resample_polyline,
    smooth_polyline,
)

PLANNERS = ("dwa", "convoi", "expert", "human", "human_omniscient")
#: the reference walkers (:mod:`.human`): "human" reacts to people once the robot could see them
#: (the default since stop 46), "human_omniscient" to everyone from the start
WALKERS = ("human", "human_omniscient")
#: the reference of OLiVia-Nav's Tables I-II and of its training data (:mod:`.human`); "expert" is the
#: DWA-with-critics alternative
REFERENCE = "human"
MAX_PATH = 256
MAX_REF = 16
MAX_GROUP_PAIRS = 16
LOOKAHEAD = 2.0
GOAL_TOLERANCE = 0.3
CONVOI_THETA_FOV = 0.7854  # half of the 90-degree camera of CoNVOIConfig
EXPERT_STANDING_BERTH = 0.8  # the expert's route keeps this far (m) from people standing still


def planner_config(kind: str) -> DWAConfig:
    """The DWA configuration of a planner kind (see the module doc)."""
    base = DWAConfig(robot_radius=ROBOT_RADIUS, person_radius=PERSON_RADIUS)
    if kind == "dwa":
        return base
    if kind == "convoi":
        # eq 6's θ_fov: the goal must be inside the camera's field of view, |θ_goal| <= HFOV / 2
        return base.with_critic(reference_critic(theta_fov=CONVOI_THETA_FOV))
    if kind == "expert":
        cfg = base
        for spec in (CriticSpec.make("personal_space", 20.0, normalize=False, zone=1.0),
                     CriticSpec.make("group_gap", 6.0, normalize=False, margin=0.6, penalty=3.0),
                     CriticSpec.make("lane", 1.0, normalize=False, offset=0.0)):
            cfg = cfg.with_critic(spec)
        return cfg
    raise ValueError(f"unknown planner {kind!r}; choose from {PLANNERS}")


class World(NamedTuple):
    """Per-episode constants (a pytree): static field, padded obstacles, global path, goal and
    the group pairs a planner may know about."""

    field: DistanceField
    capsules: jax.Array
    capsules_valid: jax.Array
    path: jax.Array
    path_valid: jax.Array
    goal: jax.Array
    groups: jax.Array
    groups_valid: jax.Array


class Carry(NamedTuple):
    pose: jax.Array
    vel: jax.Array
    peds: pedsim.PedState
    t_index: jax.Array


class StepOut(NamedTuple):
    cmd: jax.Array
    fallback: jax.Array
    feasible: jax.Array
    best_traj: jax.Array
    detected: jax.Array
    carrot: jax.Array
    robot_contact: jax.Array
    ped_contacts: jax.Array
    wall_contacts: jax.Array
    robot_wall_hit: jax.Array


def lane_path(scn: Scenario, offset: float, margin: float = 0.2) -> np.ndarray:
    """The expert's route: the global path around standing people, shifted ``offset`` m to its
    left (negative: right), the shift reduced wherever it would bring the robot closer than
    radius + ``margin`` to a wall."""
    path = scn.global_path(avoid_standing=EXPERT_STANDING_BERTH)
    if offset == 0 or len(path) < 3:
        return path
    d = np.gradient(path.astype(np.float64), axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], -1)
    f = scn.field()
    out = path.astype(np.float64).copy()
    for frac in np.linspace(1.0, 0.0, 11):
        cand = path + frac * offset * normal
        ok = np.asarray(field_lookup(f, jnp.asarray(cand, F32))) > ROBOT_RADIUS + margin
        todo = ok & (np.abs(out - path).sum(1) == 0)
        out[todo] = cand[todo]
    # fade in and out so the lane starts at the robot and ends at the goal
    n = len(path)
    ramp = np.clip(np.minimum(np.arange(n), n - 1 - np.arange(n)) / 15.0, 0, 1)[:, None]
    out = path + ramp * (out - path)
    return resample_polyline(smooth_polyline(out, 5), 0.1)


def make_world(scn: Scenario, kind: str) -> World:
    """The :class:`World` a planner kind gets for scenario ``scn``."""
    caps, valid = scn.padded_capsules()
    path = lane_path(scn, scn.lane_offset) if kind == "expert" else scn.global_path()
    if len(path) > MAX_PATH:
        path = resample_polyline(path, float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))) / (MAX_PATH - 1))
    pa = np.zeros((MAX_PATH, 2), np.float32)
    pv = np.zeros(MAX_PATH, bool)
    pa[: len(path)] = path
    pv[: len(path)] = True
    ga = np.zeros((MAX_GROUP_PAIRS, 2), np.int32)
    gv = np.zeros(MAX_GROUP_PAIRS, bool)
    if kind == "expert":
        pairs = [(a, b) for g in scn.groups for k, a in enumerate(g) for b in g[k + 1:]]
        if pairs:
            ga[: len(pairs)] = pairs
            gv[: len(pairs)] = True
    return World(scn.field(), jnp.asarray(caps), jnp.asarray(valid), jnp.asarray(pa), jnp.asarray(pv),
                 jnp.asarray(scn.goal, F32), jnp.asarray(ga), jnp.asarray(gv))


def carrot(path, path_valid, pos, goal, lookahead: float = LOOKAHEAD):
    """(2,) the point ``lookahead`` m further along ``path`` (M, 2) than the point nearest to
    ``pos``; the goal itself once it is within ``lookahead``."""
    seg = jnp.linalg.norm(jnp.diff(path, axis=0), axis=1) * (path_valid[1:] & path_valid[:-1])
    s = jnp.concatenate([jnp.zeros(1, F32), jnp.cumsum(seg)])
    d = jnp.where(path_valid, jnp.linalg.norm(path - pos, axis=1), jnp.inf)
    i = jnp.argmin(d)
    target = s[i] + lookahead
    j = jnp.argmax(jnp.where(path_valid, s >= target, False))
    last = jnp.sum(path_valid) - 1
    j = jnp.where(jnp.any(path_valid & (s >= target)), j, last)
    pt = path[j]
    return jnp.where(jnp.linalg.norm(goal - pos) < lookahead, goal, pt)


carrot_jit = jax.jit(carrot)


@partial(jax.jit, static_argnames=("kind", "cfg", "sf"))
def control_step(carry: Carry, world: World, ref, ref_valid, ref_active, seed_key, kind: str, cfg: DWAConfig,
                 sf: pedsim.SocialForceConfig) -> tuple[Carry, StepOut]:
    """One closed-loop step (perceive, plan, move, simulate people). ``ref`` (MAX_REF, 2) world
    reference path with ``ref_valid`` and ``ref_active`` (used by the reference critic only)."""
    pose, vel, peds = carry.pose, carry.vel, carry.peds
    goal = carrot(world.path, world.path_valid, pose[:2], world.goal)
    heading = jnp.stack([jnp.cos(pose[2]), jnp.sin(pose[2])])
    if kind == "expert":
        detected = peds.active
        fut = pedsim.forecast(peds, world.capsules, world.capsules_valid, pose[:2], vel[0] * heading, seed_key,
                              carry.t_index, cfg.n_steps, sf)
    else:
        detected = visible_people(pose, peds.pos, peds.active, world.capsules, world.capsules_valid)
        fut = constant_velocity_forecast(peds.pos, peds.vel, cfg.n_steps, cfg.dt)
    inputs = DWAInputs(pose, vel, goal, world.field, fut, detected, ref, ref_valid, ref_active, world.groups,
                       world.groups_valid, world.path, world.path_valid)
    res = plan(inputs, cfg)
    new_pose = step_unicycle(pose, res.cmd, cfg.control_dt)
    hit = field_lookup(world.field, new_pose[:2]) < cfg.robot_radius
    new_pose = jnp.where(hit, pose, new_pose)
    new_vel = jnp.where(hit, jnp.zeros(2, F32), res.cmd)
    robot_vel = new_vel[0] * jnp.stack([jnp.cos(new_pose[2]), jnp.sin(new_pose[2])])
    peds2, info = pedsim.step(peds, world.capsules, world.capsules_valid, new_pose[:2], robot_vel,
                              pedsim.step_key(seed_key, carry.t_index), sf)
    out = StepOut(res.cmd, res.fallback, res.feasible, res.trajectories[res.index], detected, goal,
                  info.robot_contact, info.ped_contacts, info.wall_contacts, hit)
    return Carry(new_pose, new_vel, peds2, carry.t_index + 1), out


@dataclass
class EpisodeResult:
    """One episode's record (host numpy arrays).

    robot: (T+1, 3) poses from the start; cmds: (T, 2); people: (T+1, P, 2) centres; active: (P,);
    detected: (T, P) bool; times: (T+1,) s; reached: goal reached; fallbacks: steps where the
    DWA found nothing feasible; robot_contacts: (T,) number of people overlapping the robot;
    wall_hits: refused moves into walls; plan_ms: mean wall-clock per control step (the first,
    compiling, step left out);
    convoi: CoNVOI statistics (queries, extrapolations, failures, reference paths), if any;
    shifts: (T+1,) the human walker's carried lateral shift (m, + = left) at each pose, the
    ``prev_offset`` its next step is planned with (``None`` for the other planners).
    """

    scenario: str
    planner: str
    seed: int
    robot: np.ndarray
    cmds: np.ndarray
    people: np.ndarray
    active: np.ndarray
    detected: np.ndarray
    times: np.ndarray
    goal: np.ndarray
    start: np.ndarray
    reached: bool
    fallbacks: int
    robot_contacts: np.ndarray
    wall_hits: int
    ped_contacts: int
    plan_ms: float
    convoi: dict = field(default_factory=dict)
    dt: float = 0.1
    shifts: np.ndarray | None = None


def run_episode(scn: Scenario, kind: str, *, convoi=None, observer=None, max_steps: int | None = None,
                sf: pedsim.SocialForceConfig | None = None) -> EpisodeResult:
    """Drive planner ``kind`` through ``scn``.

    convoi: a :class:`splatsearch.social.convoi.CoNVOI` (required for ``kind="convoi"``; its
    VLM decides the reference paths). observer: optional callable ``observer(t, carry, out,
    ref_world)`` after every step (the live viewer). Deterministic for a given scenario seed.
    """
    if kind not in PLANNERS:
        raise ValueError(f"unknown planner {kind!r}; choose from {PLANNERS}")
    if kind in WALKERS:
        from .human import HumanWalkerConfig, run_walker

        return run_walker(scn, max_steps=max_steps, sf=sf, cfg=HumanWalkerConfig(perceive=kind == "human"))
    if kind == "convoi" and convoi is None:
        raise ValueError("kind='convoi' needs a CoNVOI instance (splatsearch.social.convoi.CoNVOI)")
    cfg = planner_config(kind)
    sf = sf or pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    world = make_world(scn, kind)
    seed_key = jax.random.PRNGKey(scn.seed)
    carry = Carry(jnp.asarray(scn.start, F32), jnp.zeros(2, F32), scn.peds, jnp.asarray(0, jnp.int32))
    n = scn.max_steps if max_steps is None else int(max_steps)
    ref = np.zeros((MAX_REF, 2), np.float32)
    ref_valid = np.zeros(MAX_REF, bool)
    poses = [np.asarray(scn.start, np.float32)]
    people = [np.asarray(scn.peds.pos)]
    cmds, det, contacts = [], [], []
    fallbacks = wall_hits = ped_contacts = 0
    reached = False
    if convoi is not None:
        convoi.reset(scn, world)
    t0 = time.perf_counter()
    timed_from = 1  # the first step compiles; leave it out of plan_ms
    for t in range(n):
        if t == timed_from:
            t0 = time.perf_counter()
        if kind == "convoi":
            ref_pts = convoi.update(t * scn.dt, np.asarray(carry.pose), carry.peds, world)
            ref[:] = 0
            ref_valid[:] = False
            if ref_pts is not None and len(ref_pts):
                k = min(len(ref_pts), MAX_REF)
                ref[:k] = ref_pts[-k:] if len(ref_pts) > MAX_REF else ref_pts[:k]
                ref_valid[:k] = True
        carry, out = control_step(carry, world, jnp.asarray(ref), jnp.asarray(ref_valid),
                                  jnp.asarray(bool(ref_valid.any())), seed_key, kind, cfg, sf)
        pose = np.asarray(carry.pose)
        poses.append(pose)
        people.append(np.asarray(carry.peds.pos))
        cmds.append(np.asarray(out.cmd))
        det.append(np.asarray(out.detected))
        contacts.append(int(np.asarray(out.robot_contact).sum()))
        fallbacks += bool(out.fallback)
        wall_hits += bool(out.robot_wall_hit)
        ped_contacts += int(out.ped_contacts)
        if observer is not None:
            observer(t, carry, out, ref[ref_valid].copy())
        if np.linalg.norm(pose[:2] - scn.goal) < GOAL_TOLERANCE:
            reached = True
            break
    elapsed = time.perf_counter() - t0
    T = len(cmds)
    n_timed = max(T - timed_from, 1)
    return EpisodeResult(scn.name, kind, scn.seed, np.asarray(poses), np.asarray(cmds).reshape(T, 2),
                         np.asarray(people), np.asarray(scn.peds.active), np.asarray(det).reshape(T, -1),
                         np.arange(T + 1) * scn.dt, np.asarray(scn.goal), np.asarray(scn.start), reached, fallbacks,
                         np.asarray(contacts), wall_hits, ped_contacts, 1e3 * elapsed / n_timed,
                         convoi.stats() if convoi is not None else {}, scn.dt)


def expert_rollout(scn: Scenario, pose, vel, peds: pedsim.PedState, t_index: int, n_steps: int,
                   world: World | None = None) -> np.ndarray:
    """What the expert would do from an arbitrary state: its closed loop forked from the robot at
    ``pose`` (3,) world with velocity ``vel`` (2,) (v m/s, ω rad/s), the people in ``peds`` and
    the scenario clock at step ``t_index``, for ``n_steps`` steps (or until the goal).

    Returns the expert's poses (k + 1, 3), k <= n_steps, starting at ``pose``. The people of the
    fork react to the expert, not to the real robot; the caller's state is not touched. This is
    the privileged oracle behind the offline captioner's "correct action" for views the robot
    collects itself (the LLU buffer), as the expert episodes are for the training views."""
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if np.shape(pose) != (3,) or np.shape(vel) != (2,):
        raise ValueError(f"pose must be (3,) and vel (2,), got {np.shape(pose)} and {np.shape(vel)}")
    if t_index < 0:
        raise ValueError(f"t_index must be >= 0, got {t_index}")
    cfg = planner_config("expert")
    sf = pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    world = world if world is not None else make_world(scn, "expert")
    seed_key = jax.random.PRNGKey(scn.seed)
    carry = Carry(jnp.asarray(pose, F32), jnp.asarray(vel, F32), peds, jnp.asarray(int(t_index), jnp.int32))
    ref = jnp.zeros((MAX_REF, 2), F32)
    ref_valid = jnp.zeros(MAX_REF, bool)
    out = [np.asarray(pose, np.float32)]
    for _ in range(int(n_steps)):
        carry, _ = control_step(carry, world, ref, ref_valid, jnp.asarray(False), seed_key, "expert", cfg, sf)
        out.append(np.asarray(carry.pose))
        if np.linalg.norm(out[-1][:2] - scn.goal) < GOAL_TOLERANCE:
            break
    return np.stack(out)


def min_wall_clearance(res: EpisodeResult, scn: Scenario) -> float:
    """Smallest static clearance (m, centre to wall surface) along the robot's trajectory."""
    return float(np.min(np.asarray(field_lookup(scn.field(), jnp.asarray(res.robot[:, :2], F32)))))


def people_gaps(res: EpisodeResult) -> np.ndarray:
    """(T+1,) distance (m) from the robot centre to the nearest active person's centre."""
    d = np.linalg.norm(res.people[:, res.active] - res.robot[:, None, :2], axis=-1)
    return d.min(1) if d.shape[1] else np.full(len(d), np.inf)


__all__ = ["PLANNERS", "REFERENCE", "WALKERS", "Carry", "EpisodeResult", "StepOut", "World", "carrot", "control_step", "expert_rollout", "lane_path",
           "make_world", "min_wall_clearance", "people_gaps", "planner_config", "run_episode"]
