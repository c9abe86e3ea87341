"""OLiVia-Nav's Navigation Controller (NC, thesis 3.2.4): PID control of (v, ω) along a trajectory.

The follower picks a target on the trajectory ``lookahead`` metres past the point nearest to the
robot (the last point near the end), expresses it in the robot frame and runs two PID loops:

* linear: error = the target's forward distance ``x_r`` (m) -> v, scaled by ``max(cos e_θ, 0)`` so
  the robot turns before it drives when the target is beside or behind it;
* angular: error = the bearing ``e_θ = atan2(y_r, x_r)`` (rad) -> ω.

Both outputs are clipped to the limits and rate-limited by the accelerations. The integrators
are clamped (anti-windup) and the derivative acts on the error, zero on the first step. All of
it is pure JAX; :func:`track` closes the loop on a unicycle with ``lax.scan``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .geometry import F32, world_to_robot


@dataclass(frozen=True)
class PIDGains:
    """kp, ki, kd; i_limit: |integral| clamp (error·s); out_limit: |output| clamp."""

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    i_limit: float = 1.0
    out_limit: float = float("inf")

    def __post_init__(self):
        if min(self.kp, self.ki, self.kd) < 0 or self.i_limit < 0 or self.out_limit <= 0:
            raise ValueError("PID gains and limits must be >= 0 (out_limit > 0)")


class PIDState(NamedTuple):
    """integral: () error·s; prev_error: (); started: () bool (False until the first update)."""

    integral: jax.Array
    prev_error: jax.Array
    started: jax.Array


def pid_init() -> PIDState:
    return PIDState(jnp.asarray(0.0, F32), jnp.asarray(0.0, F32), jnp.asarray(False))


def pid_update(gains: PIDGains, state: PIDState, error, dt: float) -> tuple[jax.Array, PIDState]:
    """One PID step: returns (u, new state). ``dt`` in seconds (> 0)."""
    error = jnp.asarray(error, F32)
    integral = jnp.clip(state.integral + error * dt, -gains.i_limit, gains.i_limit)
    deriv = jnp.where(state.started, (error - state.prev_error) / dt, 0.0)
    u = gains.kp * error + gains.ki * integral + gains.kd * deriv
    u = jnp.clip(u, -gains.out_limit, gains.out_limit)
    return u, PIDState(integral, error, jnp.asarray(True))


@dataclass(frozen=True)
class FollowerConfig:
    """Trajectory follower: PID gains, look-ahead (m) and the robot's limits (m/s, rad/s, m/s²,
    rad/s²); ``goal_tolerance`` (m) stops the robot at the last point."""

    linear: PIDGains = PIDGains(1.2, 0.05, 0.05, i_limit=0.5)
    angular: PIDGains = PIDGains(2.5, 0.0, 0.15, i_limit=0.5)
    lookahead: float = 0.5
    v_max: float = 0.6
    w_max: float = 1.2
    acc_v: float = 1.0
    acc_w: float = 2.5
    goal_tolerance: float = 0.05

    def __post_init__(self):
        if self.lookahead <= 0 or self.v_max <= 0 or self.w_max <= 0 or self.acc_v <= 0 or self.acc_w <= 0:
            raise ValueError("lookahead, limits and accelerations must be > 0")


class FollowerState(NamedTuple):
    linear: PIDState
    angular: PIDState
    cmd: jax.Array  # (2,) last command, for the rate limits


def follower_init() -> FollowerState:
    return FollowerState(pid_init(), pid_init(), jnp.zeros(2, F32))


def target_point(traj, pose, lookahead: float):
    """(2,) world target on ``traj`` (N, 2): ``lookahead`` m of arc past the nearest point."""
    seg = jnp.linalg.norm(jnp.diff(traj, axis=0), axis=1)
    s = jnp.concatenate([jnp.zeros(1, traj.dtype), jnp.cumsum(seg)])
    i = jnp.argmin(jnp.linalg.norm(traj - pose[:2], axis=1))
    goal_s = jnp.minimum(s[i] + lookahead, s[-1])
    k = jnp.clip(jnp.searchsorted(s, goal_s, side="right") - 1, 0, traj.shape[0] - 2)
    t = jnp.where(s[k + 1] > s[k], (goal_s - s[k]) / jnp.where(s[k + 1] > s[k], s[k + 1] - s[k], 1.0), 0.0)
    return traj[k] + jnp.clip(t, 0.0, 1.0) * (traj[k + 1] - traj[k])


@partial(jax.jit, static_argnames=("cfg", "dt"))
def follow_step(cfg: FollowerConfig, state: FollowerState, pose, traj, dt: float) -> tuple[jax.Array, FollowerState]:
    """One NC step: (v, ω) command (2,) toward the trajectory ``traj`` (N >= 2, 2) world points
    from ``pose`` (3,), and the new controller state."""
    traj = traj[:, :2]
    tgt = target_point(traj, pose, cfg.lookahead)
    r = world_to_robot(tgt, pose)
    e_th = jnp.arctan2(r[1], r[0])
    dist_end = jnp.linalg.norm(traj[-1] - pose[:2])
    done = dist_end < cfg.goal_tolerance
    v_raw, lin = pid_update(cfg.linear, state.linear, r[0], dt)
    w_raw, ang = pid_update(cfg.angular, state.angular, e_th, dt)
    v = jnp.clip(v_raw, 0.0, cfg.v_max) * jnp.maximum(jnp.cos(e_th), 0.0)
    w = jnp.clip(w_raw, -cfg.w_max, cfg.w_max)
    v = jnp.where(done, 0.0, v)
    w = jnp.where(done, 0.0, w)
    dv, dw = cfg.acc_v * dt, cfg.acc_w * dt
    v = jnp.clip(v, state.cmd[0] - dv, state.cmd[0] + dv)
    w = jnp.clip(w, state.cmd[1] - dw, state.cmd[1] + dw)
    cmd = jnp.stack([v, w]).astype(F32)
    return cmd, FollowerState(lin, ang, cmd)


@partial(jax.jit, static_argnames=("cfg", "dt", "n_steps"))
def track(cfg: FollowerConfig, traj, start_pose, dt: float, n_steps: int) -> tuple[jax.Array, jax.Array]:
    """Closed loop: a unicycle starting at ``start_pose`` (3,) follows ``traj`` (N, 2) for
    ``n_steps`` steps of ``dt`` s. Returns poses (n_steps + 1, 3) and commands (n_steps, 2)."""

    def body(carry, _):
        pose, st = carry
        cmd, st = follow_step(cfg, st, pose, traj, dt)
        mid = pose[2] + 0.5 * cmd[1] * dt
        pose = jnp.stack([pose[0] + cmd[0] * jnp.cos(mid) * dt, pose[1] + cmd[0] * jnp.sin(mid) * dt,
                          pose[2] + cmd[1] * dt])
        return (pose, st), (pose, cmd)

    p0 = jnp.asarray(start_pose, F32)
    _, (poses, cmds) = jax.lax.scan(body, (p0, follower_init()), None, length=n_steps)
    return jnp.concatenate([p0[None], poses]), cmds
