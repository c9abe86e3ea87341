"""Habitat-like agent in a procedural house: discrete actions, collisions, RGB-D observations.

Actions: ``move_forward`` (0.25 m), ``turn_left`` / ``turn_right`` (30 deg), ``stop``. The agent
is a disc of radius 0.17 m with its camera at 1.31 m. A forward move is integrated in small
sub-steps against the inflated navigable grid; a blocked sub-step slides along the free axis or
stops, so the agent never passes through geometry. Pose: (x, y, yaw) in the world frame, yaw
about +z from +x (counter-clockwise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from splatsearch.nav.grid import wrap_angle

from .house import House
from .navgrid import NavGrid, build_navgrid
from .raycast import Frame, HouseRenderer, SensorNoise

ACTIONS = ("stop", "move_forward", "turn_left", "turn_right")
CAMERA_HEIGHT = 1.31
FORWARD_STEP = 0.25
TURN_DEG = 30.0
MAX_STEPS = 1000


def intrinsics(width: int = 320, height: int = 240, hfov_deg: float = 79.0) -> np.ndarray:
    """Pinhole K with square pixels and a centred principal point."""
    if width <= 0 or height <= 0 or not 0 < hfov_deg < 180:
        raise ValueError(f"need positive size and 0 < hfov < 180, got {width}x{height}, {hfov_deg}")
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)


def camera_viewmat(x: float, y: float, yaw: float, z: float = CAMERA_HEIGHT, pitch: float = 0.0) -> np.ndarray:
    """World-to-camera 4x4 (OpenCV) of a camera at (x, y, z) heading ``yaw`` and tilted up by
    ``pitch`` radians (negative looks down)."""
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ np.array([x, y, z])
    return vm


def look_at_viewmat(eye, target) -> np.ndarray:
    """World-to-camera 4x4 (OpenCV) at ``eye`` looking at ``target`` (world z up, no roll)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    d = target - eye
    yaw = float(np.arctan2(d[1], d[0]))
    pitch = float(np.arctan2(d[2], np.hypot(d[0], d[1])))
    return camera_viewmat(eye[0], eye[1], yaw, eye[2], pitch)


@dataclass
class Observation:
    """What the agent senses after a step. ``frame`` holds rgb, depth, instance, class ids;
    ``pose`` is the odometry estimate (x, y, yaw), ``gt_pose`` the true one; ``viewmat`` is the
    camera's world-to-camera matrix under the *odometry* pose."""

    frame: Frame
    pose: np.ndarray
    gt_pose: np.ndarray
    viewmat: np.ndarray
    step: int
    collided: bool
    done: bool


@dataclass
class OdometryNoise:
    """Per-step std of translation (m per metre moved) and rotation (rad per step) drift."""

    trans_sigma: float = 0.0
    rot_sigma: float = 0.0


@dataclass
class _State:
    pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    odom: np.ndarray = field(default_factory=lambda: np.zeros(3))
    steps: int = 0
    path_length: float = 0.0
    collisions: int = 0
    stopped: bool = False


class HouseEnv:
    """Discrete-action RGB-D environment over a :class:`House`.

    Args:
        house: the scene; its navigable grid and renderer are built on construction.
        width, height, hfov_deg: camera (default 320x240, 79 deg horizontal; 640x480 works too).
        max_depth: depth range in metres (beyond it depth is 0).
        sensor_noise, odometry_noise: optional noise models (none by default).
        max_steps: episode cap (default 1000).
        seed: seeds the noise.
    """

    def __init__(self, house: House, *, width: int = 320, height: int = 240, hfov_deg: float = 79.0,
                 max_depth: float = 5.0, sensor_noise: SensorNoise | None = None,
                 odometry_noise: OdometryNoise | None = None, max_steps: int = MAX_STEPS, seed: int = 0,
                 navgrid: NavGrid | None = None, renderer: HouseRenderer | None = None):
        self.house = house
        self.K = intrinsics(width, height, hfov_deg)
        self.width, self.height = int(width), int(height)
        self.max_depth = float(max_depth)
        self.sensor_noise = sensor_noise
        self.odometry_noise = odometry_noise or OdometryNoise()
        self.max_steps = int(max_steps)
        self.renderer = renderer if renderer is not None else HouseRenderer(house)
        self.nav = navgrid if navgrid is not None else build_navgrid(house, mesh=self.renderer.mesh)
        self.rng = np.random.default_rng(seed)
        self.seed = int(seed)
        self.s = _State()

    # -- state ------------------------------------------------------------------------------
    @property
    def pose(self) -> np.ndarray:
        return self.s.pose.copy()

    @property
    def path_length(self) -> float:
        return self.s.path_length

    @property
    def steps(self) -> int:
        return self.s.steps

    def reset(self, pose) -> Observation:
        """Place the agent at ``pose`` = (x, y, yaw); it must be navigable."""
        pose = np.asarray(pose, np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be finite (x, y, yaw), got {pose}")
        if not self.nav.is_navigable(pose[:2]):
            raise ValueError(f"pose {pose[:2].round(3).tolist()} is outside the navigable area of the house")
        self.s = _State(pose=pose.copy(), odom=pose.copy())
        return self._observe(False)

    def step(self, action: str | int) -> Observation:
        """Apply one action and return the new observation."""
        if isinstance(action, (int, np.integer)):
            if not 0 <= action < len(ACTIONS):
                raise ValueError(f"action index must be in 0..{len(ACTIONS) - 1}, got {action}")
            action = ACTIONS[action]
        if action not in ACTIONS:
            raise ValueError(f"unknown action {action!r}; expected one of {ACTIONS}")
        if self.s.stopped or self.s.steps >= self.max_steps:
            raise RuntimeError("episode is over: call reset() first")
        s = self.s
        s.steps += 1
        collided = False
        on = self.odometry_noise
        if action == "move_forward":
            moved, collided = self._move(FORWARD_STEP)
            s.path_length += moved
            if moved > 0:
                d = moved * (1.0 + self.rng.normal(0, on.trans_sigma)) if on.trans_sigma > 0 else moved
                s.odom[0] += d * np.cos(s.odom[2])
                s.odom[1] += d * np.sin(s.odom[2])
        elif action in ("turn_left", "turn_right"):
            a = np.radians(TURN_DEG) * (1 if action == "turn_left" else -1)
            s.pose[2] = float(wrap_angle(s.pose[2] + a))
            noise = self.rng.normal(0, on.rot_sigma) if on.rot_sigma > 0 else 0.0
            s.odom[2] = float(wrap_angle(s.odom[2] + a + noise))
        else:
            s.stopped = True
        s.collisions += int(collided)
        return self._observe(collided)

    def _move(self, dist: float) -> tuple[float, bool]:
        """Integrate a forward move in sub-steps; returns (distance moved, collided)."""
        s = self.s
        n_sub = max(1, int(np.ceil(dist / (0.25 * self.nav.cell_size))))
        step = dist / n_sub
        dx, dy = step * np.cos(s.pose[2]), step * np.sin(s.pose[2])
        moved = 0.0
        collided = False
        for _ in range(n_sub):
            x, y = s.pose[0], s.pose[1]
            for cand in ((x + dx, y + dy), (x + dx, y), (x, y + dy)):  # straight, then slide along x or y
                if self.nav.is_navigable(cand):
                    moved += float(np.hypot(cand[0] - x, cand[1] - y))
                    s.pose[0], s.pose[1] = cand
                    if cand != (x + dx, y + dy):
                        collided = True
                    break
            else:
                collided = True
                break
        return moved, collided

    def viewmat(self, pose=None) -> np.ndarray:
        p = self.s.pose if pose is None else np.asarray(pose, float)
        return camera_viewmat(p[0], p[1], p[2])

    def _observe(self, collided: bool) -> Observation:
        s = self.s
        frame = self.renderer.render(self.viewmat(), self.K, self.width, self.height, max_depth=self.max_depth,
                                     noise=self.sensor_noise, noise_seed=self.seed * 100003 + s.steps)
        done = s.stopped or s.steps >= self.max_steps
        return Observation(frame, s.odom.copy(), s.pose.copy(), camera_viewmat(*s.odom), s.steps, collided, done)

    def render_view(self, viewmat, width: int | None = None, height: int | None = None, K=None) -> Frame:
        """Render an arbitrary camera (no noise), e.g. for goal images."""
        w, h = width or self.width, height or self.height
        return self.renderer.render(viewmat, self.K if K is None else K, w, h, max_depth=self.max_depth)
