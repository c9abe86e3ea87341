"""Pedestrian simulation in JAX: the social force model with groups, walls, a robot agent and
hard collisions.

Forces (accelerations, m/s²) on pedestrian i, after Helbing & Molnár 1995, Helbing et al. 2000
and Moussaïd et al. 2010:

* goal: ``(v_des - v_i) / tau`` with ``v_des = v0 * e`` toward the current waypoint; toward the
  last waypoint the speed tapers as ``min(v0, k_arrive * distance)``, so people stop at their
  goal and come back to it when pushed. A *static* pedestrian is one whose only waypoint is
  where it stands (static groups stand in formation this way).
* people: ``A exp((r_ij - d_ij) / B) n_ij w(φ)`` with the anisotropy
  ``w = λ + (1 - λ)(1 + cos φ) / 2`` (people react less to what is behind them). Members of the
  same group skip it and use the group repulsion below instead.
* robot: the same form with its own (A, B); the robot is an agent people see and avoid.
* walls: ``A_w exp((r_i - d_iw) / B_w) n_iw`` summed over the capsule obstacles.
* groups: coherence (pull toward the group's centre beyond ``(n - 1) / 2`` metres), velocity
  alignment with the group's mean velocity, and a short-range repulsion that keeps members from
  overlapping. Moussaïd's gaze term is replaced by the alignment term (walking groups stay
  abreast without a head model).
* noise: Gaussian, ``noise`` m/s² per axis, from the step's PRNG key (deterministic per seed).

Integration is semi-implicit Euler with the speed capped at ``max_speed_factor * v0``. Then
hard collisions: overlapping people are pushed apart and people inside walls pushed out
(``resolve_iters`` passes). Robot contacts are detected and reported, not resolved: the robot is
driven from outside, and the metrics must see the overlap.

All functions are pure and jit-able; the pedestrian count is padded (``active`` mask).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .geometry import F32, capsule_distance, point_segment_distance

FAR = 1e3  # where padded (inactive) pedestrians are parked


class PedState(NamedTuple):
    """Pedestrians (padded to P).

    pos, vel: (P, 2) m, m/s; goals: (P, W, 2) waypoints (m), the last valid one is the final
    goal; goal_idx: (P,) int32 current waypoint; n_goals: (P,) int32 >= 1; v0: (P,) desired speed
    m/s; group: (P,) int32 group id (-1: alone); active: (P,) bool; radius: (P,) m; t: () s.
    """

    pos: jax.Array
    vel: jax.Array
    goals: jax.Array
    goal_idx: jax.Array
    n_goals: jax.Array
    v0: jax.Array
    group: jax.Array
    active: jax.Array
    radius: jax.Array
    t: jax.Array


class StepInfo(NamedTuple):
    """robot_contact: (P,) bool, pedestrian i overlaps the robot; ped_contacts: () int32 pairs
    of people that overlapped before resolution; wall_contacts: () int32 people inside walls
    before resolution."""

    robot_contact: jax.Array
    ped_contacts: jax.Array
    wall_contacts: jax.Array


@dataclass(frozen=True)
class SocialForceConfig:
    """Model parameters (SI units; accelerations in m/s²). Defaults are in the range of
    Helbing et al. 2000 / Moussaïd et al. 2010 divided by an 80 kg mass, tuned so that people
    pass each other and the robot at 0.3-0.6 m in corridors."""

    dt: float = 0.1
    tau: float = 0.5
    k_arrive: float = 1.0
    a_ped: float = 2.1
    b_ped: float = 0.3
    lam: float = 0.35
    a_robot: float = 4.0
    b_robot: float = 0.5
    robot_radius: float = 0.25
    a_wall: float = 3.0
    b_wall: float = 0.15
    coherence: float = 2.0
    alignment: float = 1.0
    group_repulsion: float = 5.0
    goal_radius: float = 0.4
    max_speed_factor: float = 1.3
    min_speed_cap: float = 0.5
    noise: float = 0.05
    resolve_iters: int = 2

    def __post_init__(self):
        if self.dt <= 0 or self.tau <= 0 or self.b_ped <= 0 or self.b_wall <= 0 or self.b_robot <= 0:
            raise ValueError("dt, tau and the B ranges must be > 0")
        if not 0 <= self.lam <= 1:
            raise ValueError(f"lam must be in [0, 1], got {self.lam}")
        if self.resolve_iters < 0:
            raise ValueError("resolve_iters must be >= 0")


def make_state(pos, goals, v0, *, group=None, radius: float = 0.25, vel=None, max_people: int = 12,
               max_waypoints: int = 4) -> PedState:
    """Padded :class:`PedState` from per-person lists.

    pos: (n, 2) starts (m); goals: list of n waypoint lists (each (k_i, 2), 1 <= k_i <=
    max_waypoints); v0: (n,) desired speeds (m/s); group: (n,) ids (-1 alone); vel: (n, 2)
    initial velocities (default: v0 toward the first waypoint, so nobody starts frozen).
    """
    pos = np.asarray(pos, np.float32).reshape(-1, 2)
    n = len(pos)
    if n > max_people:
        raise ValueError(f"{n} pedestrians exceed max_people={max_people}")
    if len(goals) != n:
        raise ValueError(f"need one waypoint list per pedestrian: {len(goals)} lists for {n} people")
    v0 = np.broadcast_to(np.asarray(v0, np.float32), (n,))
    if np.any(v0 < 0) or not np.all(np.isfinite(pos)):
        raise ValueError("v0 must be >= 0 and positions finite")
    P, W = max_people, max_waypoints
    g = np.full((P, W, 2), FAR, np.float32)
    ng = np.ones(P, np.int32)
    for i, wp in enumerate(goals):
        wp = np.asarray(wp, np.float32).reshape(-1, 2)
        if not 1 <= len(wp) <= W:
            raise ValueError(f"pedestrian {i} has {len(wp)} waypoints; need 1..{W}")
        g[i, : len(wp)] = wp
        g[i, len(wp):] = wp[-1]
        ng[i] = len(wp)
    p = np.full((P, 2), FAR, np.float32)
    p[:n] = pos
    p[n:, 0] += 10 * np.arange(P - n)  # keep parked pads apart from each other too
    g[n:] = p[n:, None]
    v = np.zeros((P, 2), np.float32)
    if vel is None:
        d = g[:n, 0] - pos
        nd = np.linalg.norm(d, axis=1, keepdims=True)
        v[:n] = np.where(nd > 1e-6, d / np.maximum(nd, 1e-6), 0) * np.minimum(v0[:, None], nd)
    else:
        v[:n] = np.asarray(vel, np.float32).reshape(n, 2)
    vv = np.zeros(P, np.float32)
    vv[:n] = v0
    gr = np.full(P, -1, np.int32)
    if group is not None:
        gr[:n] = np.asarray(group, np.int32).reshape(n)
    act = np.zeros(P, bool)
    act[:n] = True
    rad = np.full(P, radius, np.float32)
    return PedState(jnp.asarray(p), jnp.asarray(v), jnp.asarray(g), jnp.zeros(P, jnp.int32), jnp.asarray(ng),
                    jnp.asarray(vv), jnp.asarray(gr), jnp.asarray(act), jnp.asarray(rad), jnp.asarray(0.0, F32))


def _unit(v, eps=1e-9):
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.maximum(n, eps), n[..., 0]


def forces(state: PedState, capsules, capsules_valid, robot_pos, robot_vel, cfg: SocialForceConfig,
           key=None) -> jax.Array:
    """(P, 2) total acceleration (m/s²) on every pedestrian (0 for inactive ones)."""
    P = state.pos.shape[0]
    act = state.active
    goal = state.goals[jnp.arange(P), state.goal_idx]
    to_goal, dist = _unit(goal - state.pos)
    last = state.goal_idx >= state.n_goals - 1
    speed = jnp.where(last, jnp.minimum(state.v0, cfg.k_arrive * dist), state.v0)
    f = (to_goal * speed[:, None] - state.vel) / cfg.tau

    # heading used by the anisotropy: where the person walks, or where it wants to go
    move, sp = _unit(state.vel)
    e = jnp.where((sp > 0.05)[:, None], move, to_goal)

    # pedestrian-pedestrian
    diff = state.pos[:, None] - state.pos[None]  # (P, P, 2), i minus j
    n_ij, d_ij = _unit(diff)
    r_ij = state.radius[:, None] + state.radius[None]
    cos_phi = -jnp.sum(n_ij * e[:, None], -1)
    w = cfg.lam + (1 - cfg.lam) * 0.5 * (1 + cos_phi)
    same_group = (state.group[:, None] == state.group[None]) & (state.group[:, None] >= 0)
    pair = act[:, None] & act[None] & ~jnp.eye(P, dtype=bool)
    social = cfg.a_ped * jnp.exp((r_ij - d_ij) / cfg.b_ped) * w
    social = jnp.where(pair & ~same_group, social, 0.0)
    f = f + jnp.sum(social[..., None] * n_ij, 1)
    grp_rep = cfg.group_repulsion * jnp.clip(r_ij + 0.15 - d_ij, 0.0, None)
    f = f + jnp.sum(jnp.where(pair & same_group, grp_rep, 0.0)[..., None] * n_ij, 1)

    # groups: coherence and alignment
    member = (same_group & pair) | (jnp.eye(P, dtype=bool) & (state.group >= 0)[:, None])
    cnt = jnp.sum(member, 1)
    centre = jnp.sum(member[..., None] * state.pos[None], 1) / jnp.maximum(cnt, 1)[:, None]
    mean_vel = jnp.sum(member[..., None] * state.vel[None], 1) / jnp.maximum(cnt, 1)[:, None]
    to_c, dc = _unit(centre - state.pos)
    thr = 0.5 * (cnt - 1.0)
    in_group = cnt > 1
    f = f + jnp.where(in_group[:, None], cfg.coherence * jnp.clip(dc - thr, 0.0, 1.0)[:, None] * to_c, 0.0)
    f = f + jnp.where(in_group[:, None], cfg.alignment * (mean_vel - state.vel), 0.0)

    # robot
    n_r, d_r = _unit(state.pos - robot_pos[None])
    cos_r = -jnp.sum(n_r * e, -1)
    w_r = cfg.lam + (1 - cfg.lam) * 0.5 * (1 + cos_r)
    f = f + (cfg.a_robot * jnp.exp((state.radius + cfg.robot_radius - d_r) / cfg.b_robot) * w_r)[:, None] * n_r

    # walls: every capsule pushes
    a, b, rr = capsules[:, 0:2], capsules[:, 2:4], capsules[:, 4]
    dw, q = point_segment_distance(state.pos[:, None], a[None], b[None])  # (P, S)
    n_w, _ = _unit(state.pos[:, None] - q)
    mag = cfg.a_wall * jnp.exp((state.radius[:, None] - (dw - rr[None])) / cfg.b_wall)
    mag = jnp.where(capsules_valid[None], mag, 0.0)
    f = f + jnp.sum(mag[..., None] * n_w, 1)

    if key is not None and cfg.noise > 0:
        f = f + cfg.noise * jax.random.normal(key, f.shape, F32)
    return jnp.where(act[:, None], f, 0.0)


def _resolve(pos, state: PedState, capsules, capsules_valid, iters: int):
    P = pos.shape[0]
    act = state.active
    pair = act[:, None] & act[None] & ~jnp.eye(P, dtype=bool)
    r_ij = state.radius[:, None] + state.radius[None]
    for _ in range(iters):
        n_ij, d_ij = _unit(pos[:, None] - pos[None])
        overlap = jnp.where(pair, jnp.clip(r_ij - d_ij, 0.0, None), 0.0)
        pos = pos + jnp.sum(0.5 * overlap[..., None] * n_ij, 1)
        dwall, nw = capsule_distance(pos, capsules, capsules_valid)
        push = jnp.clip(state.radius - dwall, 0.0, None)
        pos = pos + jnp.where(act[:, None], push[:, None] * nw, 0.0)
    return pos


@partial(jax.jit, static_argnames="cfg")
def step(state: PedState, capsules, capsules_valid, robot_pos, robot_vel, key,
         cfg: SocialForceConfig = SocialForceConfig()) -> tuple[PedState, StepInfo]:
    """Advance the pedestrians by ``cfg.dt``.

    capsules: (S, 5) obstacles with capsules_valid (S,); robot_pos, robot_vel: (2,) m, m/s
    (the robot as the pedestrians see it); key: PRNG key for the noise. Returns the new state
    and the contacts detected this step.
    """
    P = state.pos.shape[0]
    robot_pos = jnp.asarray(robot_pos, F32)
    robot_vel = jnp.asarray(robot_vel, F32)
    f = forces(state, capsules, capsules_valid, robot_pos, robot_vel, cfg, key).astype(F32)
    vel = state.vel + cfg.dt * f
    cap = cfg.max_speed_factor * jnp.maximum(state.v0, cfg.min_speed_cap)
    u, s = _unit(vel)
    vel = u * jnp.minimum(s, cap)[:, None]
    vel = jnp.where(state.active[:, None], vel, 0.0)
    pos = state.pos + cfg.dt * vel

    act = state.active
    pair = act[:, None] & act[None] & jnp.triu(jnp.ones((P, P), bool), 1)
    d_ij = jnp.linalg.norm(pos[:, None] - pos[None], axis=-1)
    ped_contacts = jnp.sum(pair & (d_ij < state.radius[:, None] + state.radius[None] - 1e-3))
    dwall, _ = capsule_distance(pos, capsules, capsules_valid)
    wall_contacts = jnp.sum(act & (dwall < state.radius - 1e-3))
    new_pos = _resolve(pos, state, capsules, capsules_valid, cfg.resolve_iters)
    robot_contact = act & (jnp.linalg.norm(new_pos - robot_pos[None], axis=-1) < state.radius + cfg.robot_radius)

    goal = state.goals[jnp.arange(P), state.goal_idx]
    reached = jnp.linalg.norm(goal - new_pos, axis=-1) < cfg.goal_radius
    goal_idx = jnp.where(reached & (state.goal_idx < state.n_goals - 1), state.goal_idx + 1, state.goal_idx)
    new = state._replace(pos=new_pos, vel=vel, goal_idx=goal_idx.astype(jnp.int32), t=state.t + cfg.dt)
    return new, StepInfo(robot_contact, ped_contacts.astype(jnp.int32), wall_contacts.astype(jnp.int32))


def step_key(seed_key, t_index):
    """The noise key of simulation step ``t_index``: the episode and a privileged forecast
    share it, so a forecast reproduces the real future exactly when the robot moves as assumed."""
    return jax.random.fold_in(seed_key, t_index)


@partial(jax.jit, static_argnames=("n_steps", "cfg"))
def forecast(state: PedState, capsules, capsules_valid, robot_pos, robot_vel, seed_key, t_index,
             n_steps: int, cfg: SocialForceConfig = SocialForceConfig()) -> jax.Array:
    """(n_steps, P, 2) positions after each of the next ``n_steps`` simulated steps (steps
    ``t_index .. t_index + n_steps - 1``), the robot moving at constant velocity ``robot_vel``
    (2,) from ``robot_pos``: the future that a privileged expert knows."""

    def body(carry, k):
        s, rp = carry
        s, _ = step(s, capsules, capsules_valid, rp, robot_vel, step_key(seed_key, t_index + k), cfg)
        return (s, rp + cfg.dt * robot_vel), s.pos

    robot_pos = jnp.asarray(robot_pos, F32)
    robot_vel = jnp.asarray(robot_vel, F32)
    return jax.lax.scan(body, (state, robot_pos), jnp.arange(n_steps))[1]


@partial(jax.jit, static_argnames="cfg")
def simulate(state: PedState, capsules, capsules_valid, robot_pos, robot_vel, seed_key, t_index=0,
             cfg: SocialForceConfig = SocialForceConfig()) -> tuple[PedState, jax.Array, StepInfo]:
    """Run ``len(robot_pos)`` steps with the robot at ``robot_pos`` (n, 2) moving at ``robot_vel``
    (n, 2) at each step (``lax.scan``). Returns the final state, positions (n, P, 2) after each
    step and the stacked :class:`StepInfo` (leading axis n). Step k uses
    ``step_key(seed_key, t_index + k)``, as a closed-loop episode does."""
    robot_pos = jnp.asarray(robot_pos, F32)
    robot_vel = jnp.asarray(robot_vel, F32)

    def body(s, x):
        k, rp, rv = x
        s, info = step(s, capsules, capsules_valid, rp, rv, step_key(seed_key, t_index + k), cfg)
        return s, (s.pos, info)

    n = robot_pos.shape[0]
    final, (pos, infos) = jax.lax.scan(body, state, (jnp.arange(n), robot_pos, robot_vel))
    return final, pos, infos
