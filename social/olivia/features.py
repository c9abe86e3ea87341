"""OLiVia-Nav's per-step inputs and labels (thesis 3.3): the goal G taken along the global path,
the expert future in the robot frame, the action class of a trajectory, and one observation
(egocentric view + LiDAR + goal) of a scenario state.

Frames: robot frame x forward, y left (metres); angles in radians counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from splatsearch.nav.grid import wrap_angle
from ..convoi.geometry import F32, world_to_robot
from .captions import ACTIONS
from .lidar import lidar_points
from .render import palette_of, render_view

if TYPE_CHECKING:
    from ..convoi.pedsim import PedState
    from ..convoi.runner import World
    from ..convoi.scenarios import Scenario


HORIZON = 10                    # future poses per trajectory (thesis 3.3)
FUTURE_STRIDE = 4               # sim steps between future poses (0.4 s at dt = 0.1 s)
GOAL_LOOKAHEAD = 3.0            # m along the global path: the TPN's goal G
GOAL_DIM = 9                    # goal (5) + local free space (4), see goal_features
FREE_RANGE = 2.0                # m: how far the free-space rays look


def path_carrot(path: np.ndarray, pos: np.ndarray, lookahead: float = GOAL_LOOKAHEAD) -> tuple[np.ndarray, float]:
    """The point ``lookahead`` m further along ``path`` (M, 2) than the point nearest ``pos``
    (2,), and the path direction there (rad, world)."""
    path = np.asarray(path, np.float64)
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    i = int(np.argmin(np.linalg.norm(path - pos, axis=1)))
    q = min(s[i] + lookahead, s[-1])
    x, y = np.interp(q, s, path[:, 0]), np.interp(q, s, path[:, 1])
    j = int(np.clip(np.searchsorted(s, q) , 1, len(path) - 1))
    d = path[j] - path[j - 1]
    return np.array([x, y]), float(np.arctan2(d[1], d[0]))


def free_space(field, pose: np.ndarray, max_range: float = FREE_RANGE) -> np.ndarray:
    """(4,) local free space around the robot at ``pose`` (3,) world: how far (m / ``max_range``,
    clipped to 1) its body can move left, right, ahead-left and ahead-right (rays at ±90° and
    ±30°, 5 cm steps) before touching a static obstacle. It lets the TPN see how wide the passage
    is (a 1 m door vs a 2.6 m hallway) instead of keeping a lane it learned elsewhere."""
    from ..convoi.geometry import field_lookup
    from ..convoi.scenarios import ROBOT_RADIUS

    pose = np.asarray(pose, np.float64)
    steps = np.arange(1, int(max_range / 0.05) + 1) * 0.05
    ang = pose[2] + np.array([np.pi / 2, -np.pi / 2, np.pi / 6, -np.pi / 6])
    pts = pose[None, None, :2] + steps[None, :, None] * np.stack([np.cos(ang), np.sin(ang)], -1)[:, None]
    clr = np.asarray(field_lookup(field, jnp.asarray(pts, F32)))
    blocked = clr < ROBOT_RADIUS
    first = np.where(blocked.any(1), np.argmax(blocked, 1), len(steps))
    return (np.r_[0.0, steps][first] / max_range).astype(np.float32)


def goal_features(path: np.ndarray, goal: np.ndarray, pose: np.ndarray, field=None) -> np.ndarray:
    """(GOAL_DIM,) goal G in the robot frame: carrot x/3, y/3 (m), cos/sin of the path direction
    there, the distance to the final goal / 5 (clipped to 1), then the local free space
    (:func:`free_space`; ones without a ``field``)."""
    pose = np.asarray(pose, np.float64)
    c, heading = path_carrot(path, pose[:2])
    r = world_to_robot(c, pose)
    a = heading - pose[2]
    dg = min(float(np.linalg.norm(np.asarray(goal, np.float64) - pose[:2])), 5.0) / 5.0
    free = free_space(field, pose) if field is not None else np.ones(4, np.float32)
    return np.r_[np.array([r[0] / GOAL_LOOKAHEAD, r[1] / GOAL_LOOKAHEAD, np.cos(a), np.sin(a), dg]), free].astype(
        np.float32)


def future_in_frame(poses: np.ndarray, t: int, frame: np.ndarray, offset=None, dyaw: float = 0.0) -> np.ndarray:
    """(HORIZON, 3) future poses ``poses[t + FUTURE_STRIDE * i]`` (i = 1..HORIZON, the last pose
    repeated past the end) in the frame of ``frame`` (3,). With a displacement ``offset`` (2,)
    world and ``dyaw`` (rad) of the frame from ``poses[t]``, the labels blend from the displaced
    pose back onto the expert's future over the first half of the horizon."""
    idx = np.minimum(t + FUTURE_STRIDE * np.arange(1, HORIZON + 1), len(poses) - 1)
    fut = np.asarray(poses, np.float64)[idx].copy()
    if offset is not None:
        w = 1.0 - np.minimum(1.0, np.arange(1, HORIZON + 1) / (HORIZON / 2))
        fut[:, :2] += w[:, None] * np.asarray(offset, np.float64)[None]
        fut[:, 2] += w * dyaw
    xy = world_to_robot(fut[:, :2], np.asarray(frame, np.float64))
    yaw = wrap_angle(fut[:, 2] - frame[2])
    return np.concatenate([xy, yaw[:, None]], -1).astype(np.float32)


def extend_to_goal(poses: np.ndarray, goal: np.ndarray, min_step: float = 0.05) -> np.ndarray:
    """``poses`` (T, 3) world continued in a straight line to ``goal`` (2,) at the speed of the
    last step (at least ``min_step`` m per step), heading kept.

    An episode ends as soon as the robot is within the goal tolerance, so without this the
    futures of the last states would stop that far short of the goal, and a planner trained on
    them stops short too and never arrives."""
    poses = np.asarray(poses, np.float64)
    if len(poses) < 2:
        return poses
    d = np.asarray(goal, np.float64)[:2] - poses[-1, :2]
    step = max(float(np.linalg.norm(poses[-1, :2] - poses[-2, :2])), min_step)
    n = int(np.ceil(np.linalg.norm(d) / step))
    if n == 0:
        return poses
    f = np.arange(1, n + 1)[:, None] / n
    tail = np.concatenate([poses[-1, :2] + f * d, np.full((n, 1), poses[-1, 2])], -1)
    return np.concatenate([poses, tail])


#: m: how far to the side a trajectory must end to be "keep left / right" (training data, TSM, and
#: by default the LLU buffer's captions; :attr:`~splatsearch.social.olivia.llu.LLUConfig.caption_keep`).
KEEP_THRESHOLD = 0.35


def action_of(traj, keep: float = KEEP_THRESHOLD) -> int:
    """Index into :data:`ACTIONS` of a robot-frame trajectory (HORIZON, >= 2) (metres, rad):
    ``yield`` if it advances < 0.6 m over the horizon, ``turn_*`` if it ends turned > 0.7 rad,
    ``keep_*`` if it ends > ``keep`` m (default 0.35) to the side, else ``straight``."""
    tr = np.asarray(traj, np.float64)
    if tr.ndim != 2 or tr.shape[1] < 2:
        raise ValueError(f"traj must be (N, 2+) robot-frame poses, got {tr.shape}")
    end = tr[-1]
    yaw = end[2] if tr.shape[1] > 2 else np.arctan2(end[1], max(end[0], 1e-6))
    if np.linalg.norm(end[:2]) < 0.6:
        return ACTIONS.index("yield")
    if yaw > 0.7:
        return ACTIONS.index("turn_left")
    if yaw < -0.7:
        return ACTIONS.index("turn_right")
    if end[1] < -keep:
        return ACTIONS.index("keep_right")
    if end[1] > keep:
        return ACTIONS.index("keep_left")
    return ACTIONS.index("straight")


def expert_action(scn: Scenario, pose: np.ndarray, vel: np.ndarray, peds: PedState, t_index: int,
                  world: World | None = None, reference: str | None = None, offset: float | None = None,
                  seen: np.ndarray | None = None, keep: float = KEEP_THRESHOLD) -> int:
    """The "correct" high-level action (index into :data:`ACTIONS`) at an arbitrary state: the
    action of the expert's future from there (:func:`splatsearch.social.convoi.runner.expert_rollout`
    over the TPN horizon, continued to the goal when it arrives), labelled like the training
    views (:func:`action_of` of :func:`future_in_frame`).

    pose (3,) world; vel (2,) the robot's (v, ω); peds: the simulator's people; t_index: the
    scenario step. This is what the offline captioner says the robot *should* do, as a VLM
    judging the view would, whatever the robot then did. ``reference``: whose future
    (default :data:`~splatsearch.social.convoi.runner.REFERENCE`, the human-like walker; ``"expert"``:
    the DWA-with-critics). ``offset`` (m, human walker only): the lateral shift the forked walker
    holds (:func:`~splatsearch.social.convoi.human.walker_rollout`); None or 0: none chosen yet.
    ``seen`` (P,) bool (perceiving walker only): the people the forked walker already knows (the
    robot's own perception so far); None: those visible from ``pose``. ``keep`` (m): the
    :func:`action_of` side threshold (the LLU buffer may caption with its own)."""
    return action_of(expert_future(scn, pose, vel, peds, t_index, world, reference, offset, seen), keep)


def expert_future(scn: Scenario, pose: np.ndarray, vel: np.ndarray, peds: PedState, t_index: int,
                  world: World | None = None, reference: str | None = None, offset: float | None = None,
                  seen: np.ndarray | None = None) -> np.ndarray:
    """The reference's future from ``pose`` in the robot frame, (HORIZON, 3) (m, rad), as
    :func:`expert_action` labels it (arguments as there)."""
    from ..convoi.runner import GOAL_TOLERANCE, REFERENCE, WALKERS, expert_rollout

    ref = reference or REFERENCE
    if ref in WALKERS:
        from ..convoi.human import HumanWalkerConfig, walker_rollout

        poses = walker_rollout(scn, pose, vel, peds, t_index, FUTURE_STRIDE * HORIZON,
                               HumanWalkerConfig(perceive=ref == "human"), offset=float(offset or 0.0), seen=seen)
    else:
        poses = expert_rollout(scn, pose, vel, peds, t_index, FUTURE_STRIDE * HORIZON, world)
    if np.linalg.norm(poses[-1, :2] - np.asarray(scn.goal)[:2]) < GOAL_TOLERANCE:
        poses = extend_to_goal(poses, scn.goal)
    return future_in_frame(poses, 0, np.asarray(pose, np.float64))


@dataclass(frozen=True)
class Observation:
    """What OLiVia-Nav's sensors give at one instant: image (IMG_H, IMG_W, 3) float32 [0, 1],
    points (N_POINTS, 4), points_valid (N_POINTS,), goal (GOAL_DIM,)."""

    image: np.ndarray
    points: np.ndarray
    points_valid: np.ndarray
    goal: np.ndarray


def observe(scn, pose, people, prev_pose, prev_people, path: np.ndarray | None = None) -> Observation:
    """Sensors of the robot at ``pose`` (3,) world among ``people`` (P, 2) world (the scenario's
    padded rows; inactive ones are ignored), with the sweep of ``PREV_STEPS`` steps earlier."""
    act = jnp.asarray(scn.peds.active)
    field = scn.field()
    img = render_view(field, jnp.asarray(pose, F32), jnp.asarray(people, F32), act, palette_of(scn))
    pts, ok = lidar_points(field, jnp.asarray(pose, F32), jnp.asarray(people, F32), act,
                           jnp.asarray(prev_pose, F32), jnp.asarray(prev_people, F32))
    g = goal_features(scn.global_path() if path is None else path, scn.goal, np.asarray(pose, np.float64), field)
    return Observation(np.asarray(img), np.asarray(pts), np.asarray(ok), g)
