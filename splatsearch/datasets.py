"""RGB-D frame sources for the mapper: TUM RGB-D folders and simulator trajectories."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np

from splatsearch.mapper import Frame
from splatsearch.nav.grid import wrap_angle


def _read_list(path: str) -> list[tuple[float, list[str]]]:
    out = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            try:
                out.append((float(parts[0]), parts[1:]))
            except ValueError:  # a header line without '#', e.g. "timestamp tx ty tz qx qy qz qw"
                continue
    return out


def _quat_to_R(q):
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _slerp(q0, q1, t):
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - t) * th) * q0 + np.sin(t * th) * q1) / np.sin(th)


def load_tum(path: str, max_frames: int | None = None, stride: int = 1, max_dt: float = 0.02):
    """Load a TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt, intrinsics.json).

    RGB and depth are associated by nearest timestamp (<= ``max_dt`` s); the camera-to-world
    ground truth is interpolated (lerp + slerp) at each RGB timestamp. Depth PNGs are 16-bit with
    5000 per metre unless intrinsics.json says otherwise.

    Returns ``(frames, K, width, height)`` with :class:`Frame` items (viewmat = world-to-camera).
    """
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        if not os.path.exists(os.path.join(path, name)):
            raise FileNotFoundError(f"{path}: missing {name} (expected a TUM RGB-D folder)")
    intr_path = os.path.join(path, "intrinsics.json")
    if os.path.exists(intr_path):
        with open(intr_path) as f:
            intr = json.load(f)
    else:  # TUM's recommended defaults for registered depth
        intr = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "depth_scale": 5000.0}
    K = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]], np.float32)
    scale = float(intr.get("depth_scale", 5000.0))
    rgbs = _read_list(os.path.join(path, "rgb.txt"))
    depths = _read_list(os.path.join(path, "depth.txt"))
    gt = np.array([[t] + [float(v) for v in vals] for t, vals in _read_list(os.path.join(path, "groundtruth.txt"))])
    if gt.ndim != 2 or gt.shape[1] != 8:
        raise ValueError(f"{path}/groundtruth.txt: expected lines 'timestamp tx ty tz qx qy qz qw'")
    dts = np.array([t for t, _ in depths])
    frames = []
    for t, (fname,) in rgbs[::stride]:
        j = int(np.argmin(np.abs(dts - t)))
        if abs(dts[j] - t) > max_dt or t < gt[0, 0] or t > gt[-1, 0]:
            continue
        k = int(np.searchsorted(gt[:, 0], t))
        k = min(max(k, 1), len(gt) - 1)
        a = (t - gt[k - 1, 0]) / max(gt[k, 0] - gt[k - 1, 0], 1e-9)
        trans = (1 - a) * gt[k - 1, 1:4] + a * gt[k, 1:4]
        q = _slerp(gt[k - 1, 4:8], gt[k, 4:8], a)
        c2w = np.eye(4)
        c2w[:3, :3] = _quat_to_R(q)
        c2w[:3, 3] = trans
        rgb = cv2.imread(os.path.join(path, fname), cv2.IMREAD_COLOR)
        dep = cv2.imread(os.path.join(path, depths[j][1][0]), cv2.IMREAD_UNCHANGED)
        if rgb is None or dep is None:
            raise ValueError(f"{path}: cannot read {fname} or its depth image")
        frames.append(Frame(rgb[..., ::-1].astype(np.float32) / 255.0, dep.astype(np.float32) / scale,
                            np.linalg.inv(c2w).astype(np.float32)))
        if max_frames is not None and len(frames) >= max_frames:
            break
    if not frames:
        raise ValueError(f"{path}: no RGB frame could be associated with depth and ground truth")
    H, W = frames[0].depth.shape
    return frames, K, W, H


def sim_trajectory(seed: int = 0, n_frames: int = 100, width: int = 320, height: int = 240, step: float = 0.1,
                   turn_deg: float = 6.0):
    """A smooth camera walk through a procedural house: FMM paths between random navigable
    points, one frame every ``step`` metres (or ``turn_deg`` of turning), at camera height.

    Returns ``(frames, K, width, height, env)``.
    """
    from splatsearch import sim

    house = sim.make_house(seed)
    env = sim.HouseEnv(house, width=width, height=height)
    nav = env.nav
    rng = np.random.default_rng(seed)
    cells = np.argwhere(nav.navigable)
    cur = cells[int(rng.integers(len(cells)))]
    yaw = float(rng.uniform(-np.pi, np.pi))
    poses = []
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
    frames = []
    for x, y, yw in poses[:n_frames]:
        vm = sim.camera_viewmat(x, y, yw).astype(np.float32)
        f = env.render_view(vm)
        frames.append(Frame(f.rgb, f.depth, vm))
    return frames, env.K, width, height, env
