"""Simulator walks through procedural houses, with optional noisy odometry.

:func:`sim_trajectory` is a smooth camera walk (FMM paths between random navigable points, one
frame every ``step`` metres or ``turn_deg`` of turning); :func:`sim_walk` wraps it as an
:class:`~splatsearch.datasets.base.RGBDSequence` and adds the odometry a wheeled robot reports:
the true planar motion between frames with noise as :class:`splatsearch.sim.OdometryNoise` draws
it (``trans_sigma`` per metre moved, ``rot_sigma`` rad per frame), integrated from the true first
pose.
"""

from __future__ import annotations

import numpy as np

from splatsearch.datasets.base import RGBDSequence
from splatsearch.mapper import Frame
from splatsearch.nav.grid import wrap_angle

#: Odometry noise of the benchmark walk: 5 % of the distance moved, 0.01 rad (0.57 deg) a frame.
DEFAULT_ODOMETRY_NOISE = (0.05, 0.01)


def walk_poses(env, seed: int, n_frames: int, step: float = 0.1, turn_deg: float = 6.0) -> list[tuple]:
    """(x, y, yaw) camera poses of a smooth walk through ``env``'s house."""
    nav = env.nav
    rng = np.random.default_rng(seed)
    cells = np.argwhere(nav.navigable)
    cur = cells[int(rng.integers(len(cells)))]
    yaw = float(rng.uniform(-np.pi, np.pi))
    poses: list[tuple] = []
    while len(poses) < n_frames:
        goal = cells[int(rng.integers(len(cells)))]
        tgt = np.zeros(nav.shape, bool)
        tgt[tuple(goal)] = True
        dist = nav.geodesic_from(tgt)
        if not np.isfinite(dist[tuple(cur)]) or dist[tuple(cur)] < 2.0:
            continue
        path = [cur]
        while dist[tuple(path[-1])] > 0 and len(path) < 5000:
            r, c = path[-1]
            nb = [(r + a, c + b) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
            path.append(np.array(min(nb, key=lambda n: dist[n])))
        pts = nav.cell_to_world(np.array(path))
        acc = 0.0
        for i in range(1, len(pts)):
            acc += float(np.linalg.norm(pts[i] - pts[i - 1]))
            if acc < step:
                continue
            acc = 0.0
            look = pts[min(i + 8, len(pts) - 1)] - pts[i]
            want = float(np.arctan2(look[1], look[0])) if np.linalg.norm(look) > 1e-6 else yaw
            while True:  # turn towards the path in small steps, one frame each
                d = wrap_angle(want - yaw)
                if abs(d) <= np.radians(turn_deg):
                    yaw = want
                    break
                yaw += np.sign(d) * np.radians(turn_deg)
                poses.append((pts[i][0], pts[i][1], yaw))
            poses.append((pts[i][0], pts[i][1], yaw))
        cur = path[-1]
    return poses[:n_frames]


def sim_trajectory(seed: int = 0, n_frames: int = 100, width: int = 320, height: int = 240, step: float = 0.1,
                   turn_deg: float = 6.0):
    """A smooth camera walk through procedural house ``seed``, at camera height.

    Returns ``(frames, K, width, height, env)`` with ground-truth viewmats.
    """
    from splatsearch import sim

    env = sim.HouseEnv(sim.make_house(seed), width=width, height=height)
    frames = []
    for x, y, yw in walk_poses(env, seed, n_frames, step, turn_deg):
        vm = sim.camera_viewmat(x, y, yw).astype(np.float32)
        f = env.render_view(vm)
        frames.append(Frame(f.rgb, f.depth, vm))
    return frames, env.K, width, height, env


def noisy_odometry(poses: np.ndarray, trans_sigma: float, rot_sigma: float, seed: int = 0) -> np.ndarray:
    """(N, 3) odometry (x, y, yaw) of true planar poses (N, 3): each frame's true motion (distance
    moved in the direction of travel, change of yaw) with multiplicative distance noise and
    additive yaw noise, integrated from the true first pose."""
    poses = np.asarray(poses, np.float64)
    rng = np.random.default_rng(seed)
    odom = [poses[0].copy()]
    for a, b in zip(poses[:-1], poses[1:]):
        dxy = b[:2] - a[:2]
        # motion in the previous true heading's frame, replayed from the odometry's heading
        c, s = np.cos(a[2]), np.sin(a[2])
        fwd, left = c * dxy[0] + s * dxy[1], -s * dxy[0] + c * dxy[1]
        k = 1.0 + (rng.normal(0, trans_sigma) if trans_sigma > 0 else 0.0)
        dyaw = wrap_angle(b[2] - a[2]) + (rng.normal(0, rot_sigma) if rot_sigma > 0 else 0.0)
        o = odom[-1]
        co, so = np.cos(o[2]), np.sin(o[2])
        odom.append(np.array([o[0] + k * (co * fwd - so * left), o[1] + k * (so * fwd + co * left),
                              wrap_angle(o[2] + dyaw)]))
    return np.array(odom)


def sim_walk(seed: int = 0, n_frames: int = 100, width: int = 320, height: int = 240, *,
             odometry_noise: tuple[float, float] | None = DEFAULT_ODOMETRY_NOISE, odometry_seed: int = 0,
             step: float = 0.1, turn_deg: float = 6.0) -> RGBDSequence:
    """A simulator walk as a sequence with ground truth and (optionally noisy) odometry.

    ``sequence.odometry`` holds (N, 4, 4) world-to-camera matrices of the odometry poses
    (``odometry_noise`` = (trans_sigma per metre, rot_sigma rad per frame); None: no odometry).
    """
    from splatsearch import sim

    env = sim.HouseEnv(sim.make_house(seed), width=width, height=height)
    poses = np.array(walk_poses(env, seed, n_frames, step, turn_deg))
    frames = []
    for x, y, yw in poses:
        vm = sim.camera_viewmat(x, y, yw).astype(np.float32)
        f = env.render_view(vm)
        frames.append(Frame(f.rgb, f.depth, vm))
    seq = RGBDSequence(frames, env.K, width, height, "sim", f"sim:house{seed}", np.arange(len(frames), dtype=float),
                       [f"frame{i:04d}" for i in range(len(frames))])
    if odometry_noise is not None:
        odom = noisy_odometry(poses, *odometry_noise, seed=odometry_seed)
        seq.odometry = np.stack([sim.camera_viewmat(*p) for p in odom]).astype(np.float32)
        seq.notes.append(f"odometry noise: {odometry_noise[0]:.3f} per metre, {odometry_noise[1]:.4f} rad per frame")
    return seq
