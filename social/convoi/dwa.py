"""Dynamic Window Approach in JAX (Fox et al. 1997; CoNVOI eq 1, 5, 6).

One call of :func:`plan` (jitted, static config):

1. The dynamic window: velocities reachable within ``control_dt`` under the acceleration limits,
   clipped to [v_min, v_max] x [-w_max, w_max].
2. A fixed ``n_v`` x ``n_w`` grid of (v, ω) samples over it (fixed counts: one compiled shape).
3. Rollouts: each sample held for ``n_steps`` steps of ``dt`` (unicycle, exact arcs) by
   ``lax.scan``, ``vmap``-ed over the samples.
4. The critics of :mod:`.costs`; a collision costs +inf. A critic with ``normalize=True`` is
   min-max normalised over the feasible samples (CoNVOI's σ, after Fox et al.); the defaults use
   raw costs (see below). The weighted sum may be smoothed over the (v, ω) grid.
5. The cheapest feasible sample wins. If none is feasible, the explicit fallback takes the
   sample that collides last (largest time to collision), then the slowest, then the best heading,
   and the result says ``fallback=True``.

Units: metres, seconds, radians. Poses are world (x, y, yaw).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .costs import CRITICS, CostInputs, CriticSpec, time_to_collision
from .geometry import F32, DistanceField, pad_rows

# The paper's weights (CoNVOI V-A: heading 10, obstacles 7, velocity 1, reference 7.5, each term
# min-max normalised) make the robot creep to a stop before a pillar: slowing down shortens the
# rollout and so always "improves" clearance. The default adds a progress term and uses raw costs
# (as Nav2's DWB critics do); on that scale the reference critic needs 15 to move the robot
# sideways against heading and progress. The measurements are in docs/results.md.
DEFAULT_CRITICS = (CriticSpec.make("heading", 5.0, normalize=False), CriticSpec.make("clearance", 7.0, normalize=False),
                   CriticSpec.make("people", 7.0, normalize=False), CriticSpec.make("velocity", 1.0, normalize=False),
                   CriticSpec.make("progress", 10.0, normalize=False))
REFERENCE_WEIGHT = 15.0


def reference_critic(weight: float = REFERENCE_WEIGHT, theta_fov: float = 1.5708, min_ahead: float = 0.0,
                     normalize: bool = False) -> CriticSpec:
    """eq 5 + eq 6 critic: lateral distance to the reference point just ahead, used only while
    |θ_goal| <= ``theta_fov`` (rad)."""
    return CriticSpec.make("reference_path", weight, normalize=normalize, theta_fov=theta_fov, min_ahead=min_ahead)


@dataclass(frozen=True)
class DWAConfig:
    """Robot limits, sampling and critics (hashable: a jit key).

    v_min, v_max: m/s; w_max: rad/s; acc_v: m/s²; acc_w: rad/s²; control_dt: s between plans
    (the dynamic window's width); dt: s per rollout step; n_steps: rollout length (t_hor =
    n_steps * dt); n_v x n_w: samples; robot_radius, person_radius: m; smooth: 3x3 mean filter of
    the cost over the (v, ω) grid (Fox's σ applied to the objective).
    """

    v_min: float = 0.0
    v_max: float = 0.6
    w_max: float = 1.2
    acc_v: float = 1.0
    acc_w: float = 2.5
    control_dt: float = 0.1
    dt: float = 0.1
    n_steps: int = 30
    n_v: int = 20
    n_w: int = 20
    robot_radius: float = 0.25
    person_radius: float = 0.25
    critics: tuple[CriticSpec, ...] = DEFAULT_CRITICS
    smooth: bool = False

    def __post_init__(self):
        if not (self.v_max > self.v_min and self.w_max > 0 and self.acc_v > 0 and self.acc_w > 0):
            raise ValueError("need v_max > v_min, w_max > 0 and positive accelerations")
        if not (self.dt > 0 and self.control_dt > 0):
            raise ValueError("dt and control_dt must be > 0")
        if self.n_steps < 1 or self.n_v < 1 or self.n_w < 1:
            raise ValueError("n_steps, n_v and n_w must be >= 1")
        if self.robot_radius < 0 or self.person_radius < 0:
            raise ValueError("radii must be >= 0")
        if not self.critics:
            raise ValueError("at least one critic is needed")
        for c in self.critics:
            if not isinstance(c, CriticSpec):
                raise TypeError(f"critics must be CriticSpec, got {c!r}")

    @property
    def n_samples(self) -> int:
        return self.n_v * self.n_w

    @property
    def horizon(self) -> float:
        """t_hor in seconds."""
        return self.n_steps * self.dt

    def with_critic(self, spec: CriticSpec) -> DWAConfig:
        """A copy with ``spec`` added, or replacing the critic of the same name."""
        rest = tuple(c for c in self.critics if c.name != spec.name)
        return replace(self, critics=rest + (spec,))

    def without_critic(self, name: str) -> DWAConfig:
        return replace(self, critics=tuple(c for c in self.critics if c.name != name))

    def critic(self, name: str) -> CriticSpec | None:
        return next((c for c in self.critics if c.name == name), None)


class DWAInputs(NamedTuple):
    """The world as the planner sees it (a pytree; pad to fixed sizes, see :func:`make_inputs`).

    pose: (3,) world (x, y, yaw); vel: (2,) current (v, ω); goal: (2,) local goal (m);
    field: static :class:`DistanceField`; people: (T, P, 2) predicted centres per rollout step
    (T = n_steps); people_valid: (P,); ref: (R, 2) world reference path; ref_valid: (R,);
    ref_active: () bool; groups: (G, 2) int32 member pairs; groups_valid: (G,);
    path: (M, 2) global path; path_valid: (M,).
    """

    pose: jax.Array
    vel: jax.Array
    goal: jax.Array
    field: DistanceField
    people: jax.Array
    people_valid: jax.Array
    ref: jax.Array
    ref_valid: jax.Array
    ref_active: jax.Array
    groups: jax.Array
    groups_valid: jax.Array
    path: jax.Array
    path_valid: jax.Array


class DWAResult(NamedTuple):
    """cmd: (2,) chosen (v, ω); index: () sample index; cost: () its total (inf on fallback);
    feasible: () bool, some sample was collision-free; fallback: () bool, the fallback chose;
    samples: (N, 2); trajectories: (N, T, 3); costs: (N,) totals (inf = infeasible);
    critic_costs: (C, N) raw per-critic costs in config order."""

    cmd: jax.Array
    index: jax.Array
    cost: jax.Array
    feasible: jax.Array
    fallback: jax.Array
    samples: jax.Array
    trajectories: jax.Array
    costs: jax.Array
    critic_costs: jax.Array


def dynamic_window(vel, cfg: DWAConfig) -> jax.Array:
    """(4,) (v_lo, v_hi, w_lo, w_hi): velocities reachable from ``vel`` (2,) within control_dt."""
    v, w = vel[0], vel[1]
    dv, dw = cfg.acc_v * cfg.control_dt, cfg.acc_w * cfg.control_dt
    v_lo = jnp.clip(v - dv, cfg.v_min, cfg.v_max)
    v_hi = jnp.clip(v + dv, cfg.v_min, cfg.v_max)
    w_lo = jnp.clip(w - dw, -cfg.w_max, cfg.w_max)
    w_hi = jnp.clip(w + dw, -cfg.w_max, cfg.w_max)
    return jnp.stack([v_lo, v_hi, w_lo, w_hi])


def sample_velocities(vel, cfg: DWAConfig) -> jax.Array:
    """(n_v * n_w, 2) samples, v-major: row i * n_w + j holds (v_i, ω_j)."""
    win = dynamic_window(vel, cfg)
    tv = jnp.linspace(0.0, 1.0, cfg.n_v, dtype=F32) if cfg.n_v > 1 else jnp.full((1,), 0.5, F32)
    tw = jnp.linspace(0.0, 1.0, cfg.n_w, dtype=F32) if cfg.n_w > 1 else jnp.full((1,), 0.5, F32)
    vs = win[0] + tv * (win[1] - win[0])
    ws = win[2] + tw * (win[3] - win[2])
    V, W = jnp.meshgrid(vs, ws, indexing="ij")
    return jnp.stack([V.ravel(), W.ravel()], -1)


def rollout(pose, samples, dt: float, n_steps: int) -> jax.Array:
    """(N, n_steps, 3) poses after each step for each (v, ω) sample (N, 2) held constant from
    ``pose`` (3,). ``lax.scan`` over time, ``vmap`` over samples."""

    def one(s):
        # the chord of the arc: length v dt sinc(ω dt / 2) along the mid-step heading (exact)
        chord = s[0] * dt * jnp.sinc(s[1] * dt / (2 * jnp.pi))

        def step(p, _):
            mid = p[2] + 0.5 * s[1] * dt
            q = jnp.stack([p[0] + chord * jnp.cos(mid), p[1] + chord * jnp.sin(mid), p[2] + s[1] * dt])
            return q, q

        return jax.lax.scan(step, pose, None, length=n_steps)[1]

    return jax.vmap(one)(samples)


def _normalise(c: jax.Array, feasible: jax.Array) -> jax.Array:
    fin = feasible & jnp.isfinite(c)
    lo = jnp.min(jnp.where(fin, c, jnp.inf))
    hi = jnp.max(jnp.where(fin, c, -jnp.inf))
    span = hi - lo
    return jnp.where(fin & (span > 1e-9), (c - lo) / jnp.where(span > 1e-9, span, 1.0), 0.0)


def _smooth(total: jax.Array, cfg: DWAConfig) -> jax.Array:
    g = total.reshape(cfg.n_v, cfg.n_w)
    fin = jnp.isfinite(g)
    val = jnp.pad(jnp.where(fin, g, 0.0), 1)
    cnt = jnp.pad(fin.astype(F32), 1)
    s = sum(val[i:i + cfg.n_v, j:j + cfg.n_w] for i in range(3) for j in range(3))
    n = sum(cnt[i:i + cfg.n_v, j:j + cfg.n_w] for i in range(3) for j in range(3))
    return jnp.where(fin, s / jnp.maximum(n, 1.0), jnp.inf).ravel()


def evaluate(inputs: DWAInputs, cfg: DWAConfig) -> tuple[jax.Array, jax.Array, jax.Array, CostInputs]:
    """Samples, rollouts and costs without choosing: returns (total (N,), raw (C, N),
    feasible (N,), the critics' inputs)."""
    samples = sample_velocities(inputs.vel, cfg)
    traj = rollout(inputs.pose, samples, cfg.dt, cfg.n_steps)
    ci = CostInputs(traj, samples, inputs.pose, inputs.goal, inputs.field, inputs.people, inputs.people_valid,
                    inputs.ref, inputs.ref_valid, inputs.ref_active, inputs.groups, inputs.groups_valid,
                    inputs.path, inputs.path_valid)
    raw = jnp.stack([CRITICS[c.name](ci, cfg, **dict(c.params)).astype(F32) for c in cfg.critics])
    feasible = jnp.all(jnp.isfinite(raw), 0)
    total = jnp.zeros(samples.shape[0], F32)
    for k, c in enumerate(cfg.critics):
        term = _normalise(raw[k], feasible) if c.normalize else jnp.where(feasible, raw[k], 0.0)
        total = total + c.weight * term
    total = jnp.where(feasible, total, jnp.inf)
    if cfg.smooth:
        total = _smooth(total, cfg)
    return total, raw, feasible, ci


@partial(jax.jit, static_argnums=1)
def plan(inputs: DWAInputs, cfg: DWAConfig) -> DWAResult:
    """One DWA decision. ``inputs.people`` must be (cfg.n_steps, P, 2). See the module doc."""
    total, raw, feasible, ci = evaluate(inputs, cfg)
    any_ok = jnp.any(feasible)

    def fallback(_):
        # collide as late as possible, then as slowly as possible, then face the goal
        ttc = time_to_collision(ci, cfg).astype(F32)
        head = CRITICS["heading"](ci, cfg)
        score = ttc * 1e4 - ci.samples[:, 0] * 1e2 / max(cfg.v_max, 1e-6) - head
        return jnp.argmax(score)

    idx = jax.lax.cond(any_ok, lambda _: jnp.argmin(total), fallback, None)
    return DWAResult(ci.samples[idx], idx, total[idx], any_ok, ~any_ok, ci.samples, ci.traj, total, raw)


def constant_velocity_forecast(pos, vel, n_steps: int, dt: float) -> jax.Array:
    """(n_steps, P, 2) people centres after each rollout step, assuming constant velocity.
    pos, vel: (P, 2) m and m/s."""
    t = (jnp.arange(n_steps, dtype=F32) + 1.0) * dt
    return pos[None] + t[:, None, None] * vel[None]


def make_inputs(pose, vel, goal, field: DistanceField, cfg: DWAConfig, *, people=None, people_vel=None,
                people_valid=None, people_future=None, max_people: int = 12, ref=None, ref_active: bool = True,
                max_ref: int = 16, groups=None, max_groups: int = 16, path=None, max_path: int = 256) -> DWAInputs:
    """Build padded :class:`DWAInputs` from plain arrays (host-side convenience).

    people: (P, 2) centres (m) with people_vel (P, 2) m/s for a constant-velocity forecast, or
    people_future (T, P, 2) given directly (T = cfg.n_steps). ref: (R, 2) world reference path.
    groups: (G, 2) person-index pairs. path: (M, 2) global path. Arrays are padded to the
    ``max_*`` sizes (raises if larger) so every call shares one compiled planner.
    """
    pose = np.asarray(pose, np.float32).reshape(-1)
    vel = np.asarray(vel, np.float32).reshape(-1)
    goal = np.asarray(goal, np.float32).reshape(-1)
    if pose.shape != (3,) or vel.shape != (2,) or goal.shape != (2,):
        raise ValueError(f"pose must be (3,), vel (2,), goal (2,); got {pose.shape}, {vel.shape}, {goal.shape}")
    for name, a in (("pose", pose), ("vel", vel), ("goal", goal)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite, got {a}")
    T = cfg.n_steps
    P = max_people
    fut = np.zeros((T, P, 2), np.float32)
    pv = np.zeros(P, bool)
    if people_future is not None:
        f = np.asarray(people_future, np.float32)
        if f.ndim != 3 or f.shape[0] != T or f.shape[2] != 2 or f.shape[1] > P:
            raise ValueError(f"people_future must be ({T}, <= {P}, 2), got {f.shape}")
        fut[:, : f.shape[1]] = f
        pv[: f.shape[1]] = True if people_valid is None else np.asarray(people_valid, bool)
    elif people is not None and len(people):
        p = np.asarray(people, np.float32).reshape(-1, 2)
        if len(p) > P:
            raise ValueError(f"{len(p)} people exceed max_people={P}")
        v = np.zeros_like(p) if people_vel is None else np.asarray(people_vel, np.float32).reshape(-1, 2)
        t = (np.arange(T, dtype=np.float32) + 1) * cfg.dt
        fut[:, : len(p)] = p[None] + t[:, None, None] * v[None]
        pv[: len(p)] = True if people_valid is None else np.asarray(people_valid, bool)
    refa, refv = pad_rows(ref, max_ref, what="reference points (max_ref)")
    ga, gv = pad_rows(groups, max_groups, np.int32, what="group pairs (max_groups)")
    if gv.any() and (ga[gv].min() < 0 or ga[gv].max() >= P):
        raise ValueError("group pairs must index people in [0, max_people)")
    pa, pvld = pad_rows(path, max_path, what="path points (max_path)")
    return DWAInputs(jnp.asarray(pose), jnp.asarray(vel), jnp.asarray(goal), field, jnp.asarray(fut),
                     jnp.asarray(pv), jnp.asarray(refa), jnp.asarray(refv), jnp.asarray(bool(ref_active)),
                     jnp.asarray(ga), jnp.asarray(gv), jnp.asarray(pa), jnp.asarray(pvld))


def step_unicycle(pose, cmd, dt: float):
    """Pose (3,) after holding ``cmd`` (v, ω) for ``dt`` seconds (the exact arc, as the rollouts)."""
    mid = pose[2] + 0.5 * cmd[1] * dt
    chord = cmd[0] * dt * jnp.sinc(cmd[1] * dt / (2 * jnp.pi))
    return jnp.stack([pose[0] + chord * jnp.cos(mid), pose[1] + chord * jnp.sin(mid), pose[2] + cmd[1] * dt])


@partial(jax.jit, static_argnames=("cfg", "n_steps"))
def navigate(inputs: DWAInputs, cfg: DWAConfig, n_steps: int, goal_tolerance: float = 0.3
             ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Closed loop in a static world: plan, move ``control_dt``, repeat for ``n_steps`` steps
    (``lax.scan``), toward ``inputs.goal``; people keep their forecast (``inputs.people``).
    The robot stops once within ``goal_tolerance`` m. Returns poses (n_steps + 1, 3),
    commands (n_steps, 2) and fallback flags (n_steps,)."""

    def body(carry, _):
        pose, vel, done = carry
        res = plan(inputs._replace(pose=pose, vel=vel), cfg)
        cmd = jnp.where(done, jnp.zeros(2, F32), res.cmd)
        new = step_unicycle(pose, cmd, cfg.control_dt)
        done = done | (jnp.linalg.norm(new[:2] - inputs.goal) < goal_tolerance)
        return (new, cmd, done), (new, cmd, res.fallback & ~done)

    init = (inputs.pose.astype(F32), inputs.vel.astype(F32), jnp.asarray(False))
    _, (poses, cmds, fb) = jax.lax.scan(body, init, None, length=n_steps)
    return jnp.concatenate([inputs.pose[None].astype(F32), poses]), cmds, fb
