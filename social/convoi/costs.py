"""Trajectory critics for the JAX DWA, in the style of Nav2's DWB critics.

A critic scores every sampled trajectory: ``fn(inp, cfg, **params) -> (N,) float32``, lower is
better, ``+inf`` marks the sample infeasible (a collision). :class:`CriticSpec` names a
registered critic with a weight and parameters; the planner min-max normalises each critic over
the feasible samples (the σ of CoNVOI eq 1, after Fox et al. 1997) unless ``normalize=False``,
and sums the weighted results. Register new critics with :func:`register_critic`.

Built-in critics (CoNVOI eq 1, 5, 6 and the expert's social terms):

============== =====================================================================================
heading        eq 1 head: |angle from the final pose's heading to the goal| / pi
clearance      eq 1 obs, static part: 1 - min(clearance, clip) / clip along the rollout, clearance
               read in the distance field; a rollout that comes closer than ``margin`` to a wall
               costs 1..2 (the sooner, the more) if the robot could still brake before, else +inf
               (Fox et al.'s admissible velocities)
people         eq 1 obs, people part: the same against the predicted person discs; +inf only
               within ``horizon`` seconds (a forecast further out is not worth trusting)
velocity       eq 1 vel: (v_max - v) / v_max
goal_distance  distance (m) from the final pose to the goal
progress       distance (m) still to go along the straight line to the goal after the rollout
reference_path eq 5 |y_ref,i - y_{t+t_hor}| in the robot frame, gated by eq 6 |θ_goal| <= θ_fov
personal_space mean over the rollout of the deepest intrusion into any person's zone, / zone
group_gap      ``penalty`` (default +inf) when the rollout passes between two members of a group
               (closer than the robot radius to the segment joining them), else a margin penalty
lane           |signed lateral offset from the global path - offset| at the final pose; a
               negative ``offset`` keeps to the right
============== =====================================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
from splatsearch.nav.grid import wrap_angle

from .geometry import (
    DistanceField,
    field_lookup,
    point_segment_distance,
    world_to_robot,
)


class CostInputs(NamedTuple):
    """Everything a critic may look at (a pytree; shapes are static per compiled planner).

    traj: (N, T, 3) world poses (x, y, yaw) after each rollout step; samples: (N, 2) (v m/s,
    ω rad/s); pose: (3,) current pose; goal: (2,) local goal (m).
    field: static clearance :class:`DistanceField`.
    people: (T, P, 2) predicted person centres at each rollout step; people_valid: (P,) bool.
    ref: (R, 2) world reference-path points; ref_valid: (R,) bool; ref_active: () bool.
    groups: (G, 2) int32 person-index pairs of the same group; groups_valid: (G,) bool.
    path: (M, 2) global path polyline (world); path_valid: (M,) bool.
    """

    traj: jax.Array
    samples: jax.Array
    pose: jax.Array
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


@dataclass(frozen=True)
class CriticSpec:
    """A registered critic, its weight and its parameters (hashable: part of the jit key)."""

    name: str
    weight: float
    params: tuple[tuple[str, float], ...] = field(default_factory=tuple)
    normalize: bool = True

    def __post_init__(self):
        if self.name not in CRITICS:
            raise ValueError(f"unknown critic {self.name!r}; registered: {sorted(CRITICS)}")
        if not (self.weight >= 0):
            raise ValueError(f"critic {self.name!r} weight must be >= 0, got {self.weight}")

    @classmethod
    def make(cls, name: str, weight: float, normalize: bool = True, **params: float) -> CriticSpec:
        """``CriticSpec.make("lane", 3.0, offset=-0.4)``."""
        return cls(name, float(weight), tuple(sorted((k, float(v)) for k, v in params.items())), normalize)


CriticFn = Callable[..., jax.Array]
CRITICS: dict[str, CriticFn] = {}


def register_critic(name: str) -> Callable[[CriticFn], CriticFn]:
    """Decorator: register ``fn(inp: CostInputs, cfg, **params) -> (N,)`` under ``name``."""

    def deco(fn: CriticFn) -> CriticFn:
        CRITICS[name] = fn
        return fn

    return deco


# -- helpers ----------------------------------------------------------------------------------

def people_gap(inp: CostInputs, person_radius: float) -> jax.Array:
    """(N, T) distance (m) from each rollout point to the nearest predicted person's edge
    (+1e6 with nobody)."""
    d = jnp.linalg.norm(inp.traj[:, :, None, :2] - inp.people[None], axis=-1) - person_radius  # (N, T, P)
    d = jnp.where(inp.people_valid[None, None], d, 1e6)
    return jnp.min(d, -1)


def static_clearance(inp: CostInputs) -> jax.Array:
    """(N, T) clearance (m) of each rollout point in the static distance field."""
    return field_lookup(inp.field, inp.traj[..., :2])


def time_to_collision(inp: CostInputs, cfg) -> jax.Array:
    """(N,) number of rollout steps before the first collision (T when none)."""
    c = jnp.minimum(static_clearance(inp), people_gap(inp, cfg.person_radius))
    hit = c < cfg.robot_radius
    T = hit.shape[1]
    return jnp.where(hit.any(1), jnp.argmax(hit, 1), T)


# -- built-in critics -------------------------------------------------------------------------

@register_critic("heading")
def heading(inp: CostInputs, cfg) -> jax.Array:
    end = inp.traj[:, -1]
    to_goal = jnp.arctan2(inp.goal[1] - end[:, 1], inp.goal[0] - end[:, 0])
    return jnp.abs(wrap_angle(to_goal - end[:, 2])) / jnp.pi


@register_critic("clearance")
def clearance(inp: CostInputs, cfg, clip: float = 0.5, margin: float = 0.05) -> jax.Array:
    # Fox et al.'s admissibility: a rollout that reaches a wall is still a valid command when
    # the robot could brake (at acc_v, after one control period) before getting there; only
    # sooner contacts are +inf. Later ones cost 1..2, the sooner the dearer, and free rollouts
    # pay for coming within `clip` of a wall.
    c = static_clearance(inp) - cfg.robot_radius
    T = c.shape[1]
    hit = c < margin
    k = jnp.where(hit.any(1), jnp.argmax(hit, 1), T)
    v = jnp.abs(inp.samples[:, 0])
    travelled = k * v * cfg.dt
    stop = v * v / (2.0 * cfg.acc_v) + v * cfg.control_dt
    admissible = (k > 0) & (travelled > stop)
    free_cost = 1.0 - jnp.clip(jnp.min(c, 1), 0.0, clip) / clip
    late_cost = 1.0 + (T - k) / T
    cost = jnp.where(hit.any(1), late_cost, free_cost)
    return jnp.where(hit.any(1) & ~admissible, jnp.inf, cost)


@register_critic("people")
def people(inp: CostInputs, cfg, clip: float = 1.0, horizon: float = 1.5, margin: float = 0.05) -> jax.Array:
    ppl = people_gap(inp, cfg.person_radius)
    T = ppl.shape[1]
    near = (jnp.arange(T) + 1) * cfg.dt <= horizon + 1e-6
    collide = jnp.any(near[None] & (ppl < cfg.robot_radius + margin), 1)
    c = jnp.min(ppl, 1) - cfg.robot_radius
    return jnp.where(collide, jnp.inf, 1.0 - jnp.clip(c, 0.0, clip) / clip)


@register_critic("velocity")
def velocity(inp: CostInputs, cfg) -> jax.Array:
    return (cfg.v_max - inp.samples[:, 0]) / max(cfg.v_max, 1e-6)


@register_critic("goal_distance")
def goal_distance(inp: CostInputs, cfg) -> jax.Array:
    return jnp.linalg.norm(inp.traj[:, -1, :2] - inp.goal, axis=-1)


@register_critic("progress")
def progress(inp: CostInputs, cfg) -> jax.Array:
    # distance still to go along the goal direction: unlike goal_distance it does not punish
    # a lateral offset, so it leaves lane keeping to the other critics
    d = inp.goal - inp.pose[:2]
    u = d / jnp.maximum(jnp.linalg.norm(d), 1e-6)
    moved = (inp.traj[:, -1, :2] - inp.pose[:2]) @ u
    return jnp.maximum(jnp.linalg.norm(d) - moved, 0.0)


def reference_gate(inp: CostInputs, theta_fov: float) -> jax.Array:
    """eq 6: () bool, whether |θ_goal| <= θ_fov (θ_goal: heading to goal direction, radians)."""
    theta_goal = wrap_angle(jnp.arctan2(inp.goal[1] - inp.pose[1], inp.goal[0] - inp.pose[0]) - inp.pose[2])
    return jnp.abs(theta_goal) <= theta_fov


def reference_point(inp: CostInputs, min_ahead: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """eq 5's point: the reference point with the smallest robot-frame x among those with
    x > ``min_ahead``. Returns its robot-frame (2,) and whether one exists (() bool)."""
    rob = world_to_robot(inp.ref, inp.pose)
    ok = inp.ref_valid & (rob[:, 0] > min_ahead)
    i = jnp.argmin(jnp.where(ok, rob[:, 0], jnp.inf))
    return rob[i], jnp.any(ok)


@register_critic("reference_path")
def reference_path(inp: CostInputs, cfg, theta_fov: float = 1.5708, min_ahead: float = 0.0) -> jax.Array:
    p, exists = reference_point(inp, min_ahead)
    end_rob = world_to_robot(inp.traj[:, -1, :2], inp.pose)
    cost = jnp.abs(p[1] - end_rob[:, 1])
    on = inp.ref_active & exists & reference_gate(inp, theta_fov)
    return jnp.where(on, cost, 0.0)


@register_critic("personal_space")
def personal_space(inp: CostInputs, cfg, zone: float = 1.0) -> jax.Array:
    gap = people_gap(inp, cfg.person_radius) - cfg.robot_radius  # edge to edge
    return jnp.mean(jnp.clip(zone - gap, 0.0, zone), 1) / zone


@register_critic("group_gap")
def group_gap(inp: CostInputs, cfg, margin: float = 0.5, stride: float = 3, penalty: float = float("inf")) -> jax.Array:
    # every stride-th rollout point is enough: they are at most v_max * dt * stride apart, well
    # under the robot diameter, so no rollout can hop across a member-to-member segment unseen
    k = max(int(stride), 1)
    i, j = inp.groups[:, 0], inp.groups[:, 1]
    a = inp.people[k - 1::k][:, i]  # (T', G, 2)
    b = inp.people[k - 1::k][:, j]
    d, _ = point_segment_distance(inp.traj[:, k - 1::k, None, :2], a[None], b[None])  # (N, T', G)
    d = jnp.where(inp.groups_valid[None, None], d, 1e6)
    dmin = jnp.min(d, (1, 2))
    return jnp.where(dmin < cfg.robot_radius, penalty, jnp.clip(margin - (dmin - cfg.robot_radius), 0.0, margin))


def lateral_offset(points, path, path_valid, near=None, window: int = 48) -> jax.Array:
    """Signed lateral offset (m, left of the path's direction positive) of points (..., 2)
    from the polyline ``path`` (M, 2) with validity (M,). With ``near`` (2,), only the
    ``window`` segments from the path point nearest to it are searched (rollouts end within a
    couple of metres of the robot, so that is all the path they can be near)."""
    if near is not None and path.shape[0] > window + 1:
        d0 = jnp.where(path_valid, jnp.linalg.norm(path - near, axis=-1), jnp.inf)
        i0 = jnp.clip(jnp.argmin(d0) - window // 4, 0, path.shape[0] - window - 1)
        path = jax.lax.dynamic_slice_in_dim(path, i0, window + 1)
        path_valid = jax.lax.dynamic_slice_in_dim(path_valid, i0, window + 1)
    a, b = path[:-1], path[1:]
    seg_ok = path_valid[:-1] & path_valid[1:]
    d, _ = point_segment_distance(points[..., None, :], a, b)  # (..., M-1)
    d = jnp.where(seg_ok, d, jnp.inf)
    k = jnp.argmin(d, -1)
    ab = b[k] - a[k]
    side = jnp.sign(ab[..., 0] * (points[..., 1] - a[k][..., 1]) - ab[..., 1] * (points[..., 0] - a[k][..., 0]))
    return side * jnp.take_along_axis(d, k[..., None], -1)[..., 0]


@register_critic("lane")
def lane(inp: CostInputs, cfg, offset: float = -0.4) -> jax.Array:
    off = lateral_offset(inp.traj[:, -1, :2], inp.path, inp.path_valid, near=inp.pose[:2])
    return jnp.where(jnp.sum(inp.path_valid) >= 2, jnp.abs(off - offset), 0.0)
