"""OLiVia-Nav data (thesis 3.3): egocentric renders, LiDAR, captions and training samples built
from the social module's scenarios, pedestrian simulator and expert episodes.

The three datasets of the thesis come from one pass over expert episodes
(:func:`splatsearch.social.runner.run_episode` with ``kind="expert"``, the "teleoperated" reference):

* D_SC: (I_RGB, T_l, T_s) triples. Images are rendered egocentric views
  (:func:`render_view`): a column ray-caster over the scenario's wall distance field and the
  people (cylinders), with a checkered floor in world coordinates, so a view shows people (each in
  a named shirt colour), walls and the layout (corridor, corner, open room). Captions come from
  templates (:class:`TemplateCaptioner`) describing the scenario, the people and the correct
  high-level action; they stand in for GPT-4o. A real VLM can caption instead
  (:class:`OpenAICaptioner`, or anything with ``caption(image, scene) -> Caption``).
* D_TPN: (I_RGB, LiDAR, goal, expert future). The future is 10 poses every ``FUTURE_DT`` s in the
  frame of the current pose (thesis: "transformed into the reference frame of the initial robot
  pose"). LiDAR is a simulated 3-D scan (rings x azimuths), two sweeps (now and ``PREV_STEPS``
  steps earlier, ego-motion compensated) so that the point cloud carries motion.
* D_TSM: the action index of each caption (:data:`ACTIONS`); k* is computed later from the TPN's
  predictions (:func:`splatsearch.social.tsm.best_index`).

Augmentation: each expert state is also used with the robot displaced sideways and turned
(the labels blend from the displaced pose back onto the expert's future), which teaches the
planner to recover when it drifts off the expert's states in closed loop.

Frames: robot frame x forward, y left (metres); angles in radians counter-clockwise.
"""

from __future__ import annotations

import json
import os
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, Sequence, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np
from splatsearch.nav.grid import wrap_angle

from .geometry import F32, DistanceField, field_lookup, world_to_robot

if TYPE_CHECKING:
    from .pedsim import PedState
    from .runner import World
    from .scenarios import Scenario

# -- sensor and label constants ----------------------------------------------------------------
IMG_H, IMG_W = 32, 64          # egocentric view (pixels)
HFOV = np.radians(120.0)        # horizontal field of view (rad)
CAM_HEIGHT = 1.0                # m
WALL_HEIGHT, PERSON_HEIGHT = 2.0, 1.7  # m
PERSON_RADIUS = 0.25            # m
MAX_RANGE = 8.0                 # m, camera and LiDAR
LIDAR_HEIGHT = 0.45             # m
LIDAR_AZ = 180                  # azimuth rays over 360°
LIDAR_ELEV = (-0.05, 0.05, 0.15, 0.3)  # ring elevations (rad)
PREV_STEPS = 3                  # the second sweep is this many sim steps old (0.3 s)
N_POINTS = 2 * len(LIDAR_ELEV) * LIDAR_AZ
HORIZON = 10                    # future poses per trajectory (thesis 3.3)
FUTURE_STRIDE = 4               # sim steps between future poses (0.4 s at dt = 0.1 s)
GOAL_LOOKAHEAD = 3.0            # m along the global path: the TPN's goal G
GOAL_DIM = 5
LONG_LEN, SHORT_LEN = 96, 32    # token lengths of T_l and T_s

ACTIONS = ("straight", "keep_right", "keep_left", "turn_left", "turn_right", "yield")
ACTION_PHRASES = {
    "straight": ("continue moving straight ahead at a steady pace",
                 "keep going straight along the path"),
    "keep_right": ("keep to the right side and pass on the right",
                   "move gently to the right and keep right while passing"),
    "keep_left": ("move slightly to the left and pass on the left",
                  "keep to the left side of the path while passing"),
    "turn_left": ("turn left and follow the way around",
                  "gradually turn to the left"),
    "turn_right": ("turn right and follow the way around",
                   "gradually turn to the right"),
    "yield": ("slow down and yield to the people before moving on",
              "stop and give way to the people"),
}
COLOURS = ("red", "blue", "orange", "purple", "green", "yellow", "pink", "brown")
COLOUR_RGB = np.asarray([(0.85, 0.15, 0.12), (0.12, 0.30, 0.85), (0.95, 0.55, 0.05), (0.50, 0.18, 0.65),
                         (0.10, 0.60, 0.25), (0.92, 0.85, 0.10), (0.95, 0.50, 0.70), (0.50, 0.30, 0.12)], np.float32)
FLOOR_RGB = np.asarray((0.80, 0.74, 0.62), np.float32)
WALL_RGB = np.asarray((0.62, 0.64, 0.68), np.float32)
CEIL_RGB = np.asarray((0.93, 0.94, 0.96), np.float32)


def person_colour(index: int, seed: int) -> int:
    """Palette index of person ``index`` in a scenario of ``seed`` (shirt colours vary by seed)."""
    return (int(index) + int(seed)) % len(COLOURS)


# -- ray casting ---------------------------------------------------------------------------------

def _cast(field: DistanceField, origin, angles, people, people_valid, n_iter: int = 40):
    """Horizontal rays from ``origin`` (2,) at world ``angles`` (N,) rad.

    Returns wall distance (N,) by sphere tracing the clearance field (MAX_RANGE when nothing
    is hit) and person distances (P, N) by ray-circle intersection (inf when missed)."""
    # float32 throughout, also when a caller enables jax_enable_x64
    origin, angles, people = jnp.asarray(origin, F32), jnp.asarray(angles, F32), jnp.asarray(people, F32)
    d = jnp.stack([jnp.cos(angles), jnp.sin(angles)], -1)  # (N, 2)

    def body(_, t):
        c = field_lookup(field, origin + t[:, None] * d)
        return jnp.minimum(t + jnp.maximum(c, 0.0), MAX_RANGE).astype(F32)

    t = jax.lax.fori_loop(0, n_iter, body, jnp.full(angles.shape, 0.02, F32))
    t = jnp.where(field_lookup(field, origin + t[:, None] * d) < 0.05, t, MAX_RANGE)
    oc = people - origin  # (P, 2)
    b = oc @ d.T  # (P, N)
    disc = b ** 2 - (jnp.sum(oc ** 2, -1)[:, None] - PERSON_RADIUS ** 2)
    hit = b - jnp.sqrt(jnp.maximum(disc, 0.0))
    ok = (disc > 0) & (b > 0) & people_valid[:, None]
    tp = jnp.where(ok, jnp.maximum(hit, 0.01), jnp.inf)
    return t, tp


@jax.jit
def render_view(field: DistanceField, pose, people, people_valid, palette) -> jax.Array:
    """Egocentric RGB view (IMG_H, IMG_W, 3) float32 in [0, 1] from ``pose`` (3,) world.

    people: (P, 2) world centres with ``people_valid`` (P,); palette: (P,) int32 shirt colour
    indices into :data:`COLOURS`. Walls are 2 m tall grey slabs shaded by distance, people
    1.7 m cylinders (shirt colour, dark legs, skin-tone head), the floor a 0.5 m checker in world
    coordinates (it moves with the robot: the layout and motion are visible), the ceiling light."""
    pose = jnp.asarray(pose, F32)
    f = 0.5 * IMG_W / np.tan(0.5 * HFOV)
    u = jnp.arange(IMG_W, dtype=F32) + 0.5
    v = jnp.arange(IMG_H, dtype=F32) + 0.5
    alpha = jnp.arctan((0.5 * IMG_W - u) / f)  # column angle off the optical axis (left > 0)
    ang = pose[2] + alpha
    cos_a = jnp.cos(alpha)
    tan_b = (0.5 * IMG_H - v) / f  # (H,) tangent of each row's elevation
    tw, tp = _cast(field, pose[:2], ang, people, people_valid)
    dist = jnp.concatenate([tw[None], tp], 0)  # (1+P, W)
    height = jnp.concatenate([jnp.full((1,), WALL_HEIGHT, F32), jnp.full((tp.shape[0],), PERSON_HEIGHT, F32)])
    # pinhole: a row's elevation applies to the depth along the optical axis, d cos(alpha)
    z = CAM_HEIGHT + (dist * cos_a)[:, None, :] * tan_b[None, :, None]  # (1+P, H, W) height of the hit
    cover = (z >= 0) & (z <= height[:, None, None]) & jnp.isfinite(dist)[:, None, :] & (dist < MAX_RANGE)[:, None, :]
    dd = jnp.where(cover, dist[:, None, :], jnp.inf)
    k = jnp.argmin(dd, 0)  # (H, W) nearest covering object
    near = jnp.min(dd, 0)
    zk = jnp.take_along_axis(z, k[None], 0)[0]
    shade = jnp.clip(1.0 - 0.06 * jnp.where(jnp.isfinite(near), near, 0.0), 0.45, 1.0)[..., None]
    shirt = jnp.asarray(COLOUR_RGB)[jnp.clip(palette, 0, len(COLOURS) - 1)]  # (P, 3)
    pc = jnp.where((zk < 0.8)[..., None], jnp.asarray([0.2, 0.2, 0.25], F32),
                   jnp.where((zk > 1.45)[..., None], jnp.asarray([0.85, 0.68, 0.55], F32),
                             shirt[jnp.clip(k - 1, 0, shirt.shape[0] - 1)]))
    obj = jnp.where((k == 0)[..., None], jnp.asarray(WALL_RGB) * (0.9 + 0.1 * (zk < 0.12))[..., None], pc) * shade
    # floor: where nothing covers a ray below the horizon
    df = CAM_HEIGHT / jnp.maximum(-tan_b, 1e-6)[:, None] / cos_a[None]  # (H, W) ray length to the floor
    fx = pose[0] + df * jnp.cos(ang)[None]
    fy = pose[1] + df * jnp.sin(ang)[None]
    checker = (jnp.floor(fx / 0.5) + jnp.floor(fy / 0.5)) % 2
    floor = jnp.asarray(FLOOR_RGB) * (0.88 + 0.12 * checker)[..., None] * jnp.clip(1 - 0.04 * df, 0.5, 1)[..., None]
    below = (tan_b < 0)[:, None]
    bg = jnp.where(below[..., None], floor, jnp.asarray(CEIL_RGB))
    img = jnp.where(jnp.isfinite(near)[..., None], obj, bg)
    return jnp.clip(img, 0.0, 1.0).astype(F32)


def _scan(field, pose, people, people_valid):
    """One LiDAR sweep from ``pose``: (R*A, 3) world-frame xyz and (R*A,) validity."""
    ang = pose[2] + jnp.arange(LIDAR_AZ, dtype=F32) * (2 * np.pi / LIDAR_AZ)
    tw, tp = _cast(field, pose[:2], ang, people, people_valid)
    dist = jnp.concatenate([tw[None], tp], 0)  # (1+P, A)
    height = jnp.concatenate([jnp.full((1,), WALL_HEIGHT, F32), jnp.full((tp.shape[0],), PERSON_HEIGHT, F32)])
    tan_e = jnp.tan(jnp.asarray(LIDAR_ELEV, F32))  # (R,)
    z = LIDAR_HEIGHT + dist[None] * tan_e[:, None, None]  # (R, 1+P, A)
    ok = (z >= 0) & (z <= height[None, :, None]) & (dist < MAX_RANGE)[None] & jnp.isfinite(dist)[None]
    dd = jnp.where(ok, dist[None], jnp.inf)
    r = jnp.min(dd, 1)  # (R, A)
    k = jnp.argmin(dd, 1)
    zz = jnp.take_along_axis(z, k[:, None], 1)[:, 0]
    valid = jnp.isfinite(r)
    r = jnp.where(valid, r, 0.0)
    xy = pose[:2] + r[..., None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)[None]
    pts = jnp.concatenate([xy, zz[..., None]], -1).reshape(-1, 3)
    return pts, valid.reshape(-1)


@jax.jit
def lidar_points(field: DistanceField, pose, people, people_valid, prev_pose, prev_people) -> tuple[jax.Array, jax.Array]:
    """Two LiDAR sweeps in the frame of ``pose`` (3,): now, and from ``prev_pose`` with
    ``prev_people`` (PREV_STEPS steps earlier, motion-compensated by odometry).

    Returns points (N_POINTS, 4) ``(x, y, z, age)`` (metres; age 0 now, 1 earlier) and
    valid (N_POINTS,) bool (rays that hit nothing within MAX_RANGE are invalid)."""
    pose = jnp.asarray(pose, F32)
    prev_pose = jnp.asarray(prev_pose, F32)
    out_p, out_v = [], []
    for age, (p, ppl) in enumerate(((pose, people), (prev_pose, prev_people))):
        pts, ok = _scan(field, p, ppl, people_valid)
        xy = world_to_robot(pts[:, :2], pose)
        out_p.append(jnp.concatenate([xy, pts[:, 2:3], jnp.full((pts.shape[0], 1), float(age), F32)], -1))
        out_v.append(ok)
    return jnp.concatenate(out_p, 0).astype(F32), jnp.concatenate(out_v, 0)


# -- goal and labels -------------------------------------------------------------------------------

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


def goal_features(path: np.ndarray, goal: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(GOAL_DIM,) goal G in the robot frame: carrot x/3, y/3 (m), cos/sin of the path direction
    there, and the distance to the final goal / 5 (clipped to 1)."""
    pose = np.asarray(pose, np.float64)
    c, heading = path_carrot(path, pose[:2])
    r = world_to_robot(c, pose)
    a = heading - pose[2]
    dg = min(float(np.linalg.norm(np.asarray(goal, np.float64) - pose[:2])), 5.0) / 5.0
    return np.array([r[0] / GOAL_LOOKAHEAD, r[1] / GOAL_LOOKAHEAD, np.cos(a), np.sin(a), dg], np.float32)


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


def action_of(traj) -> int:
    """Index into :data:`ACTIONS` of a robot-frame trajectory (HORIZON, >= 2) (metres, rad):
    ``yield`` if it advances < 0.6 m over the horizon, ``turn_*`` if it ends turned > 0.7 rad,
    ``keep_*`` if it ends > 0.35 m to the side, else ``straight``."""
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
    if end[1] < -0.35:
        return ACTIONS.index("keep_right")
    if end[1] > 0.35:
        return ACTIONS.index("keep_left")
    return ACTIONS.index("straight")


def expert_action(scn: Scenario, pose: np.ndarray, vel: np.ndarray, peds: PedState, t_index: int,
                  world: World | None = None) -> int:
    """The "correct" high-level action (index into :data:`ACTIONS`) at an arbitrary state: the
    action of the expert's future from there (:func:`splatsearch.social.runner.expert_rollout`
    over the TPN horizon, continued to the goal when it arrives), labelled like the training
    views (:func:`action_of` of :func:`future_in_frame`).

    pose (3,) world; vel (2,) the robot's (v, ω); peds: the simulator's people; t_index: the
    scenario step. This is what the offline captioner says the robot *should* do, as a VLM
    judging the view would, whatever the robot then did."""
    from .runner import GOAL_TOLERANCE, expert_rollout

    poses = expert_rollout(scn, pose, vel, peds, t_index, FUTURE_STRIDE * HORIZON, world)
    if np.linalg.norm(poses[-1, :2] - np.asarray(scn.goal)[:2]) < GOAL_TOLERANCE:
        poses = extend_to_goal(poses, scn.goal)
    return action_of(future_in_frame(poses, 0, np.asarray(pose, np.float64)))


# -- captions ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Caption:
    """long: T_l; short: T_s; action: index into :data:`ACTIONS` read from T_l (-1: none);
    ok: usable; source: which captioner."""

    long: str
    short: str
    action: int
    ok: bool = True
    source: str = "template"


@dataclass(frozen=True)
class CaptionScene:
    """What a privileged captioner knows at one instant (robot frame, metres, m/s).

    context, description: the scenario's; seed; people: (k, 2) visible people; people_vel:
    (k, 2); colours: (k,) palette indices; groups: (k,) group ids (-1 alone); walls: (left,
    right, ahead) wall distances (m); action: the expert's action index."""

    context: str
    description: str
    seed: int
    people: np.ndarray
    people_vel: np.ndarray
    colours: np.ndarray
    groups: np.ndarray
    walls: tuple[float, float, float]
    action: int


@runtime_checkable
class Captioner(Protocol):
    """The large VLM of SC-CLIP and the LLU: caption an egocentric image."""

    def caption(self, image: np.ndarray, scene: CaptionScene | None = None) -> Caption: ...


def _bearing(p) -> str:
    a = np.degrees(np.arctan2(p[1], p[0]))
    if abs(a) < 12:
        return "straight ahead"
    if abs(a) < 35:
        return "slightly to the left" if a > 0 else "slightly to the right"
    return "to the left" if a > 0 else "to the right"


def _range(d) -> str:
    return "very close" if d < 1.5 else "nearby" if d < 3.5 else "far ahead"


def _motion(p, v) -> str:
    s = np.linalg.norm(v)
    if s < 0.2:
        return "standing"
    toward = -np.dot(v, p) / max(np.linalg.norm(p), 1e-6) / s
    if toward > 0.6:
        return "walking towards you"
    if toward < -0.6:
        return "walking away"
    return "crossing your path from the left" if v[1] < 0 else "crossing your path from the right"


_NUM = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


def _layout(walls) -> tuple[str, str]:
    left, right, ahead = walls
    if left < 2.0 and right < 2.0:
        long = "the walls are close on both sides in a narrow hallway"
        short = "narrow hallway with walls on both sides"
    elif left < 2.0 or right < 2.0:
        side = "left" if left < right else "right"
        long = f"there is a wall close on the {side} side"
        short = f"wall on the {side}"
    else:
        long = "the space is open and wide"
        short = "open space"
    if ahead < 3.0:
        long += " and a wall is ahead where the path turns"
        short += " with a corner ahead"
    return long, short


class TemplateCaptioner:
    """Offline stand-in for GPT-4o: long and short captions from templates over the privileged
    :class:`CaptionScene` (it ignores the pixels). Wording varies with ``variant`` so that the
    SCTE sees paraphrases."""

    def caption(self, image: np.ndarray | None, scene: CaptionScene | None = None, variant: int = 0) -> Caption:
        if scene is None:
            return Caption("", "", -1, ok=False, source="template")
        act = ACTIONS[scene.action]
        people = np.asarray(scene.people, np.float64).reshape(-1, 2)
        vel = np.asarray(scene.people_vel, np.float64).reshape(-1, 2)
        order = np.argsort(np.linalg.norm(people, axis=1)) if len(people) else np.zeros(0, int)
        descr = []
        for i in order[:2]:
            colour = COLOURS[int(scene.colours[i])]
            grp = int(scene.groups[i]) if len(scene.groups) else -1
            together = " in a group" if grp >= 0 else ""
            descr.append(f"a person in a {colour} shirt {_motion(people[i], vel[i])}{together} "
                         f"{_bearing(people[i])} {_range(np.linalg.norm(people[i]))}")
        n = len(people)
        count = _NUM[min(n, 10)]
        place = scene.context
        lay_long, lay_short = _layout(scene.walls)
        phrase = ACTION_PHRASES[act][variant % 2]
        if n == 0:
            ppl_long = "There are no people in view"
        else:
            ppl_long = (f"There {'is' if n == 1 else 'are'} {count} {'person' if n == 1 else 'people'} present, "
                        f"including " + " and ".join(descr))
        opening = ("In the provided image, the scenario involves" if variant % 2 == 0
                   else "In this view, the scenario is")
        safety = (f" Ensure to maintain a safe distance from the person in the {COLOURS[int(scene.colours[order[0]])]} shirt."
                  if n else " Ensure to keep a safe distance from the walls.")
        long = f"{opening} {place}. {ppl_long}. The pathway: {lay_long}. To navigate safely, you should {phrase}.{safety}"
        moving = sum(np.linalg.norm(vel, axis=1) > 0.2) if n else 0
        if n == 0:
            ppl_short = "No people"
        else:
            cols = " and ".join(dict.fromkeys(COLOURS[int(c)] for c in scene.colours[order[:2]]))
            ppl_short = f"{count.capitalize()} {'person' if n == 1 else 'people'} in {cols} shirts " + (
                "walking" if moving else "standing")
        short = f"{ppl_short} in {place}. {lay_short.capitalize()}."
        return Caption(long, short, int(scene.action), True, "template")


def action_from_text(text: str) -> int:
    """The high-level action a long caption asks for (index into :data:`ACTIONS`; -1 if none):
    the first action phrase after "should", else anywhere in the text."""
    t = text.lower()
    tail = t.split("should", 1)[1] if "should" in t else t
    rules = (("yield", ("yield", "give way", "stop", "wait", "slow down")),
             ("turn_left", ("turn left", "turn to the left", "turning left")),
             ("turn_right", ("turn right", "turn to the right", "turning right")),
             ("keep_right", ("keep right", "to the right", "keep to the right", "pass on the right")),
             ("keep_left", ("keep left", "to the left", "keep to the left", "pass on the left")),
             ("straight", ("straight", "continue", "keep going", "forward")))
    for part in (tail, t):
        best, pos = -1, len(part) + 1
        for name, keys in rules:
            for k in keys:
                i = part.find(k)
                if 0 <= i < pos:
                    best, pos = ACTIONS.index(name), i
        if best >= 0:
            return best
    return -1


def with_action(long: str, action: int) -> str | None:
    """T_l with its navigation-action phrase replaced by a phrase of ``action`` (index into
    :data:`ACTIONS`), the rest of the description kept: the counterfactual captions that teach
    the TSM to select by E_T. None when ``long`` holds no template action phrase (free text from
    a real VLM), because its action cannot be rewritten reliably."""
    target = ACTION_PHRASES[ACTIONS[int(action)]]
    for phrases in ACTION_PHRASES.values():
        for v, phrase in enumerate(phrases):
            if phrase in long:
                return long.replace(phrase, target[v])
    return None


CAPTION_PROMPT = ("You are guiding a mobile robot among people. Describe this first-person image for the robot. "
                  "Reply with JSON {\"long\": ..., \"short\": ...}: 'long' describes the social scenario, the "
                  "people (clothing, where they are, how they move), the layout, and the high-level action the "
                  "robot should take to stay socially compliant (continue straight, keep right, keep left, turn "
                  "left, turn right, or slow down and yield); 'short' is one or two short sentences about the "
                  "people and the layout.")


class OpenAICaptioner:
    """Captions from an OpenAI-compatible ``/chat/completions`` endpoint (GPT-4o, vLLM, ...).

    The social module's :class:`~splatsearch.social.vlm.VLM` protocol only selects marker labels,
    so this adapter sends its own captioning prompt with the same endpoint settings. Pass either
    ``base_url`` + ``model`` or an existing ``OpenAICompatibleVLM`` as ``vlm`` (its URL, model,
    key and timeout are reused). Never raises for network problems: ``Caption.ok`` is False."""

    def __init__(self, base_url: str | None = None, model: str | None = None, *, vlm: Any = None,
                 api_key: str | None = None, timeout: float = 30.0, max_tokens: int = 400):
        if vlm is not None:
            self.url, self.model = vlm.url, vlm.model
            self.api_key, self.timeout = vlm.api_key, vlm.timeout
        else:
            if not base_url or not model:
                raise ValueError("OpenAICaptioner needs base_url and model, or vlm=")
            if not base_url.startswith(("http://", "https://")):
                raise ValueError(f"base_url must start with http:// or https://, got {base_url!r}")
            self.url = base_url.rstrip("/") + "/chat/completions"
            self.model, self.api_key, self.timeout = model, api_key or os.environ.get("OPENAI_API_KEY"), timeout
        self.max_tokens = int(max_tokens)

    def caption(self, image: np.ndarray, scene: CaptionScene | None = None) -> Caption:
        import base64

        from .vlm import encode_png

        b64 = base64.b64encode(encode_png(image)).decode("ascii")
        body = {"model": self.model, "temperature": 0.0, "max_tokens": self.max_tokens,
                "messages": [{"role": "user", "content": [
                    {"type": "text", "text": CAPTION_PROMPT},
                    {"type": "image_url", "image_url": {"url": f"data:image/png;base64,{b64}"}}]}]}
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        req = urllib.request.Request(self.url, json.dumps(body).encode(), headers, method="POST")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                content = json.loads(r.read().decode("utf-8", "replace"))["choices"][0]["message"]["content"]
        except (urllib.error.URLError, OSError, ValueError, KeyError, IndexError, TypeError) as e:
            return Caption("", "", -1, ok=False, source=f"openai: {type(e).__name__}")
        return parse_caption_reply(content if isinstance(content, str) else str(content), "openai")


def parse_caption_reply(text: str, source: str = "vlm") -> Caption:
    """A :class:`Caption` from a VLM reply: JSON ``{"long", "short"}`` (also inside a code
    fence), else the whole text as T_l and its first sentence as T_s."""
    import re

    m = re.search(r"\{.*\}", text, re.S)
    long = short = ""
    if m:
        try:
            obj = json.loads(m.group(0))
            long, short = str(obj.get("long", "")), str(obj.get("short", ""))
        except (ValueError, AttributeError):
            pass
    if not long:
        long = text.strip()
        short = long.split(".")[0]
    return Caption(long, short, action_from_text(long), bool(long), source)


# -- scene description at one instant -------------------------------------------------------------

@jax.jit
def _side_walls(field: DistanceField, pose) -> jax.Array:
    """(3,) wall distances (m) to the left, right and ahead of ``pose`` (3,)."""
    angles = pose[2] + jnp.asarray([np.pi / 2, -np.pi / 2, 0.0], F32)
    return _cast(field, pose[:2], angles, jnp.zeros((1, 2), F32), jnp.zeros(1, bool))[0]


def caption_scene(scn, pose: np.ndarray, people: np.ndarray, people_vel: np.ndarray, action: int) -> CaptionScene:
    """The :class:`CaptionScene` of scenario ``scn`` with the robot at ``pose`` (3,) world and the
    people at ``people`` (P, 2) / ``people_vel`` (P, 2) world (inactive rows are ignored): only
    people inside the camera's field of view, within range and in line of sight are described."""
    from .perception import visible_people

    pose = np.asarray(pose, np.float32)
    caps, valid = scn.padded_capsules()
    act = np.asarray(scn.peds.active)
    vis = np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(people, F32), jnp.asarray(act),
                                    jnp.asarray(caps), jnp.asarray(valid), MAX_RANGE))
    pr = world_to_robot(np.asarray(people, np.float64), pose.astype(np.float64))
    in_fov = np.abs(np.arctan2(pr[:, 1], pr[:, 0])) < 0.5 * HFOV
    sel = np.flatnonzero(vis & in_fov)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    vr = np.asarray(people_vel, np.float64) @ np.array([[c, -s], [s, c]])
    gid = np.full(len(act), -1)
    for g, members in enumerate(scn.groups):
        gid[list(members)] = g
    tw = np.asarray(_side_walls(scn.field(), jnp.asarray(pose)))
    return CaptionScene(scn.context, scn.description, scn.seed, pr[sel], vr[sel],
                        np.array([person_colour(i, scn.seed) for i in sel], np.int64), gid[sel],
                        (float(tw[0]), float(tw[1]), float(tw[2])), int(action))


# -- samples ------------------------------------------------------------------------------------

@dataclass
class Samples:
    """A dataset of N samples (host arrays).

    image: (N, IMG_H, IMG_W, 3) uint8; points: (N, N_POINTS, 4) float32 robot frame (x, y, z,
    age); points_valid: (N, N_POINTS) bool; goal: (N, GOAL_DIM); future: (N, HORIZON, 3) expert
    poses (robot frame); action: (N,) int; long, short: lists of N captions; scenario: (N,)
    int index into :data:`~splatsearch.social.scenarios.SCENARIOS`; seed: (N,); t: (N,) step."""

    image: np.ndarray
    points: np.ndarray
    points_valid: np.ndarray
    goal: np.ndarray
    future: np.ndarray
    action: np.ndarray
    long: list
    short: list
    scenario: np.ndarray
    seed: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return len(self.action)

    def subset(self, idx) -> "Samples":
        idx = np.asarray(idx)
        return Samples(self.image[idx], self.points[idx], self.points_valid[idx], self.goal[idx], self.future[idx],
                       self.action[idx], [self.long[i] for i in idx], [self.short[i] for i in idx],
                       self.scenario[idx], self.seed[idx], self.t[idx])

    @staticmethod
    def concat(parts: Sequence["Samples"]) -> "Samples":
        parts = [p for p in parts if len(p)]
        if not parts:
            raise ValueError("no samples to concatenate")
        cat = lambda k: np.concatenate([getattr(p, k) for p in parts])  # noqa: E731
        return Samples(cat("image"), cat("points"), cat("points_valid"), cat("goal"), cat("future"), cat("action"),
                       sum((p.long for p in parts), []), sum((p.short for p in parts), []), cat("scenario"),
                       cat("seed"), cat("t"))

    def save(self, path: str) -> None:
        """Write the samples as npz (atomically)."""
        d = os.path.dirname(os.path.abspath(path))
        os.makedirs(d, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".samples-", suffix=".npz", dir=d)
        os.close(fd)
        try:
            np.savez(tmp, image=self.image, points=self.points, points_valid=self.points_valid, goal=self.goal,
                     future=self.future, action=self.action, long=np.asarray(self.long, dtype=np.str_),
                     short=np.asarray(self.short, dtype=np.str_), scenario=self.scenario, seed=self.seed, t=self.t)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)

    @staticmethod
    def load(path: str) -> "Samples":
        try:
            with np.load(path, allow_pickle=False) as z:
                return Samples(z["image"], z["points"], z["points_valid"], z["goal"], z["future"], z["action"],
                               [str(s) for s in z["long"]], [str(s) for s in z["short"]], z["scenario"], z["seed"],
                               z["t"])
        except (OSError, KeyError, ValueError) as e:
            raise ValueError(f"cannot read the sample file {path!r}: {e}") from e


@dataclass(frozen=True)
class Observation:
    """What OLiVia-Nav's sensors give at one instant: image (IMG_H, IMG_W, 3) float32 [0, 1],
    points (N_POINTS, 4), points_valid (N_POINTS,), goal (GOAL_DIM,)."""

    image: np.ndarray
    points: np.ndarray
    points_valid: np.ndarray
    goal: np.ndarray


def palette_of(scn) -> jax.Array:
    """(P,) int32 shirt colours of a scenario's (padded) people."""
    return jnp.asarray([person_colour(i, scn.seed) for i in range(np.asarray(scn.peds.pos).shape[0])], jnp.int32)


def observe(scn, pose, people, prev_pose, prev_people, path: np.ndarray | None = None) -> Observation:
    """Sensors of the robot at ``pose`` (3,) world among ``people`` (P, 2) world (the scenario's
    padded rows; inactive ones are ignored), with the sweep of ``PREV_STEPS`` steps earlier."""
    act = jnp.asarray(scn.peds.active)
    field = scn.field()
    img = render_view(field, jnp.asarray(pose, F32), jnp.asarray(people, F32), act, palette_of(scn))
    pts, ok = lidar_points(field, jnp.asarray(pose, F32), jnp.asarray(people, F32), act,
                           jnp.asarray(prev_pose, F32), jnp.asarray(prev_people, F32))
    g = goal_features(scn.global_path() if path is None else path, scn.goal, np.asarray(pose, np.float64))
    return Observation(np.asarray(img), np.asarray(pts), np.asarray(ok), g)


def to_uint8(img) -> np.ndarray:
    return (np.clip(np.asarray(img), 0, 1) * 255 + 0.5).astype(np.uint8)


def samples_from_episode(scn, res, *, every: int = 4, augment: int = 1, rng: np.random.Generator | None = None,
                         captioner: Captioner | None = None, max_lateral: float = 0.35,
                         max_yaw: float = 0.35) -> Samples:
    """Samples along one expert episode ``res`` (:class:`~splatsearch.social.runner.EpisodeResult`)
    of scenario ``scn``: every ``every`` steps, the expert state plus ``augment`` displaced
    copies (lateral shift up to ``max_lateral`` m, yaw up to ``max_yaw`` rad; refused if the
    displaced robot would be within 0.3 m of a wall). When the expert reached the goal, the
    labels continue to the goal itself (:func:`extend_to_goal`)."""
    from .scenarios import SCENARIOS

    rng = rng if rng is not None else np.random.default_rng(scn.seed)
    captioner = captioner if captioner is not None else TemplateCaptioner()
    poses = np.asarray(res.robot, np.float64)
    people = np.asarray(res.people, np.float32)
    vel = np.diff(people, axis=0, prepend=people[:1]) / res.dt
    field = scn.field()
    path = scn.global_path()
    recs = []
    T = len(poses) - 1
    # labels only: the states sampled stay those of the episode (people are known up to T)
    label_poses = extend_to_goal(poses, scn.goal) if getattr(res, "reached", False) else poses
    for t in range(0, max(T - FUTURE_STRIDE, 1), every):
        for a in range(1 + augment):
            pose = poses[t].copy()
            off, dyaw = np.zeros(2), 0.0
            if a > 0:
                lat = rng.uniform(-max_lateral, max_lateral)
                dyaw = rng.uniform(-max_yaw, max_yaw)
                off = lat * np.array([-np.sin(pose[2]), np.cos(pose[2])])
                cand = pose + np.r_[off, dyaw]
                if float(field_lookup(field, jnp.asarray(cand[:2], F32))) < 0.3:
                    continue
                pose = cand
            tp = max(t - PREV_STEPS, 0)
            prev = poses[tp] + np.r_[off, dyaw]
            obs = observe(scn, pose, people[t], prev, people[tp], path)
            fut = future_in_frame(label_poses, t, pose, off if a else None, dyaw)
            act = action_of(fut)
            cs = caption_scene(scn, pose, people[t], vel[t], act)
            if isinstance(captioner, TemplateCaptioner):
                cap = captioner.caption(None, cs, variant=int(rng.integers(2)))
            else:
                cap = captioner.caption(obs.image, cs)
                if not cap.ok:
                    cap = TemplateCaptioner().caption(None, cs)
            recs.append((to_uint8(obs.image), obs.points, obs.points_valid, obs.goal, fut,
                         act if cap.action < 0 else cap.action, cap.long, cap.short, t))
    if not recs:
        raise ValueError(f"episode of {scn.name} seed {scn.seed} gave no samples")
    n = len(recs)
    col = lambda i: np.stack([r[i] for r in recs])  # noqa: E731
    return Samples(col(0), col(1).astype(np.float32), col(2), col(3), col(4), np.asarray([r[5] for r in recs], np.int32),
                   [r[6] for r in recs], [r[7] for r in recs], np.full(n, SCENARIOS.index(scn.name), np.int32),
                   np.full(n, scn.seed, np.int32), np.asarray([r[8] for r in recs], np.int32))


def build_dataset(scenarios: Sequence[str], seeds: Sequence[int], *, every: int = 4, augment: int = 1,
                  progress=None, expert_cache: dict | None = None) -> Samples:
    """Samples from the expert episodes of every (scenario, seed). ``progress(i, n, label)``
    is called after each episode; ``expert_cache`` (dict) keeps the episodes for reuse."""
    from .runner import run_episode
    from .scenarios import make_scenario

    parts = []
    jobs = [(s, int(k)) for s in scenarios for k in seeds]
    for i, (name, seed) in enumerate(jobs):
        scn = make_scenario(name, seed)
        key = (name, seed)
        res = expert_cache.get(key) if expert_cache is not None else None
        if res is None:
            res = run_episode(scn, "expert")
            if expert_cache is not None:
                expert_cache[key] = res
        parts.append(samples_from_episode(scn, res, every=every, augment=augment,
                                          rng=np.random.default_rng([seed, 7, len(name)])))
        if progress is not None:
            progress(i + 1, len(jobs), f"{name}/{seed}")
    return Samples.concat(parts)
