"""Global 2-D occupancy grid (unknown / free / occupied), updated incrementally from depth.

Each depth frame is back-projected to world points (every ``stride``-th pixel). Points whose height
lies in the band ``obstacle_min_z .. robot_height`` above the floor are obstacles. Free space is
the part of the field of view the rays crossed inside that band: the rays are binned by azimuth
around the camera, each bin reaches as far as its nearest obstacle (or as far as its longest
in-band ray when it saw none), and the fan polygon of the bins is rasterised with ``cv2.fillPoly``.
Only a window around the camera is touched, so the cost does not grow with the grid.

Obstacles are sticky: a later free observation does not erase them. The world is assumed static,
and keeping them is what stops the fan's straight polygon edges from nibbling thin walls seen at
grazing angles, and what remembers low obstacles that a level camera loses from view up close.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .grid import GridSpec, disk, known_bbox, wrap_angle

UNKNOWN = np.uint8(0)
FREE = np.uint8(1)
OCCUPIED = np.uint8(2)

ROBOT_RADIUS = 0.17
ROBOT_HEIGHT = 1.5
OBSTACLE_MIN_Z = 0.1
MAX_RANGE = 5.0
_SHIFT = 4  # sub-pixel bits for cv2 polygon rasterisation


@dataclass
class FovFootprint:
    """What one frame saw, on a window ``grid[rows, cols]`` of the map.

    visible: (h, w) bool, cells of the free-space fan that are not occupied (the cells the value
    map may write); camera_xy: (2,) world metres; camera_yaw: azimuth (rad, from +x, CCW) of the
    optical axis projected on the floor; hfov: horizontal field of view (rad).
    """

    rows: slice
    cols: slice
    visible: np.ndarray
    camera_xy: np.ndarray
    camera_yaw: float
    hfov: float

    @property
    def n_visible(self) -> int:
        return int(self.visible.sum())

    def full(self, shape: tuple[int, int]) -> np.ndarray:
        """The visible mask pasted into an all-False (H, W) grid."""
        out = np.zeros(shape, bool)
        out[self.rows, self.cols] = self.visible
        return out


def level_viewmat(x: float, y: float, yaw: float, z: float) -> np.ndarray:
    """World-to-camera 4x4 (OpenCV: x right, y down, z forward) of a level camera at (x, y, z) m
    heading ``yaw`` rad (from +x, CCW about world +z)."""
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ np.array([x, y, z])
    return vm


class OccupancyGrid:
    """Occupancy map over a :class:`GridSpec`; ``state`` (H, W) uint8 holds UNKNOWN/FREE/OCCUPIED.

    Args:
        spec: grid placement (default in :class:`GridSpec`: 1000 x 1000 cells of 5 cm).
        robot_radius: metres; obstacles are inflated by it for planning.
        robot_height: top of the obstacle band (m above the floor).
        obstacle_min_z: bottom of the obstacle band (m); lower points count as floor.
        floor_z: world height of the floor (m).
        max_range: depth beyond this is ignored (m); invalid depth (0) counts as "nothing up to
            max_range" when ``invalid_depth_is_free`` (VLFM's choice for a range-limited sensor;
            turn it off for sensors that drop out on near or shiny surfaces).
        stride: use every ``stride``-th pixel in both directions; None (default) picks
            ``max(1, round(width / 160))``, i.e. about 160 sampled columns (2 at 320 x 240, 4 at
            640 x 480: the same angular sampling, at a cost that does not grow with resolution).
    """

    def __init__(self, spec: GridSpec, *, robot_radius: float = ROBOT_RADIUS, robot_height: float = ROBOT_HEIGHT,
                 obstacle_min_z: float = OBSTACLE_MIN_Z, floor_z: float = 0.0, max_range: float = MAX_RANGE,
                 stride: int | None = None, invalid_depth_is_free: bool = True):
        if not isinstance(spec, GridSpec):
            raise TypeError(f"spec must be a GridSpec, got {type(spec).__name__}")
        if robot_radius < 0 or max_range <= 0 or (stride is not None and int(stride) < 1):
            raise ValueError("need robot_radius >= 0, max_range > 0 and stride >= 1 (or None)")
        if not obstacle_min_z < robot_height:
            raise ValueError(f"obstacle band is empty: obstacle_min_z={obstacle_min_z} >= robot_height={robot_height}")
        self.spec = spec
        self.robot_radius = float(robot_radius)
        self.robot_height = float(robot_height)
        self.obstacle_min_z = float(obstacle_min_z)
        self.floor_z = float(floor_z)
        self.max_range = float(max_range)
        self.stride = None if stride is None else int(stride)
        self.invalid_depth_is_free = bool(invalid_depth_is_free)
        self.state = np.zeros(spec.shape, np.uint8)
        self.n_updates = 0
        self._ray_cache: dict = {}

    # -- views ------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.spec.shape

    @property
    def free(self) -> np.ndarray:
        return self.state == FREE

    @property
    def occupied(self) -> np.ndarray:
        return self.state == OCCUPIED

    @property
    def unknown(self) -> np.ndarray:
        return self.state == UNKNOWN

    @property
    def known(self) -> np.ndarray:
        return self.state != UNKNOWN

    def reset(self) -> None:
        self.state[:] = UNKNOWN
        self.n_updates = 0

    def inflated(self, radius: float | None = None) -> np.ndarray:
        """(H, W) bool: cells whose centre is within ``radius`` m (default the robot radius) of an
        occupied cell centre, i.e. where the robot centre may not go."""
        r = self.robot_radius if radius is None else float(radius)
        occ = self.occupied
        out = np.zeros(self.shape, bool)
        bb = known_bbox(occ, pad=int(np.ceil(r / self.spec.cell_size)) + 1)
        if bb is None:
            return out
        k = disk(r / self.spec.cell_size).astype(np.uint8)
        out[bb] = cv2.dilate(occ[bb].astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
        return out

    def traversable(self, unknown_is_free: bool = False, radius: float | None = None) -> np.ndarray:
        """(H, W) bool planning mask: free (or also unknown) cells outside the inflated obstacles.

        ``unknown_is_free=False`` (default) keeps plans inside space the robot has seen, which is what
        frontier exploration needs; ``True`` is the optimistic choice for a goal behind unseen space.
        """
        ok = (self.state != OCCUPIED) if unknown_is_free else (self.state == FREE)
        return ok & ~self.inflated(radius)

    # -- updates ----------------------------------------------------------------------------
    def mark_footprint(self, xy, radius: float | None = None) -> None:
        """Mark unknown cells under the robot disc at world ``xy`` as free: the robot stands there,
        so that space is empty even if the camera never saw it. Occupied cells are left alone."""
        r = self.robot_radius if radius is None else float(radius)
        rows, cols, m = self.spec.cells_within(xy, r)
        win = self.state[rows, cols]
        win[m & (win == UNKNOWN)] = FREE

    def update_from_pose(self, depth: np.ndarray, pose, K: np.ndarray, camera_height: float) -> FovFootprint:
        """:meth:`update` for a level camera at ``camera_height`` m on a robot at pose (x, y, yaw)."""
        p = np.asarray(pose, np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"pose must be finite (x, y, yaw), got {pose!r}")
        return self.update(depth, level_viewmat(p[0], p[1], p[2], self.floor_z + camera_height), K)

    def update(self, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> FovFootprint:
        """Fuse one depth frame.

        depth: (H, W) float metres (z-depth, 0 = invalid); viewmat: (4, 4) world-to-camera (OpenCV
        frame, world z up); K: (3, 3) intrinsics in pixels. Returns the frame's :class:`FovFootprint`.
        """
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.size == 0:
            raise ValueError(f"depth must be a non-empty (H, W) array, got shape {depth.shape}")
        vm = np.asarray(viewmat, np.float64)
        K = np.asarray(K, np.float64)
        if vm.shape != (4, 4) or not np.all(np.isfinite(vm)):
            raise ValueError(f"viewmat must be a finite (4, 4) matrix, got shape {vm.shape}")
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("K must be a finite (3, 3) intrinsics matrix with positive focal lengths")
        H, W = depth.shape
        s = self.stride if self.stride is not None else max(1, int(round(W / 160)))
        c2w = np.linalg.inv(vm)
        R, t = c2w[:3, :3], c2w[:3, 3]
        cam_xy = t[:2].copy()
        fwd = R[:, 2]
        yaw = float(np.arctan2(fwd[1], fwd[0]))
        hfov = float(2 * np.arctan(0.5 * W / K[0, 0]))

        # camera-frame ray per sampled pixel (z = 1), cached per (shape, K, stride)
        key = (H, W, s, K.tobytes())
        rays = self._ray_cache.get(key)
        if rays is None:
            u = np.arange(s // 2, W, s, dtype=np.float64) + 0.5
            v = np.arange(s // 2, H, s, dtype=np.float64) + 0.5
            x = (u[None, :] - K[0, 2]) / K[0, 0]
            y = (v[:, None] - K[1, 2]) / K[1, 1]
            rays = np.stack(np.broadcast_arrays(x, y, np.ones_like(x * y)), -1).reshape(-1, 3)
            self._ray_cache = {key: rays}
        z = depth[s // 2::s, s // 2::s].reshape(-1).astype(np.float64)
        valid = np.isfinite(z) & (z > 0) & (z <= self.max_range)
        if self.invalid_depth_is_free:
            # no return within range: the ray crossed max_range of empty space
            z = np.where(valid, z, np.where(np.isfinite(z) & (z > self.max_range), self.max_range,
                                            np.where(z == 0, self.max_range, np.nan)))
            use = np.isfinite(z)
        else:
            use = valid
        if not use.any():
            self.n_updates += 1
            return FovFootprint(slice(0, 0), slice(0, 0), np.zeros((0, 0), bool), cam_xy, yaw, hfov)
        rw = rays[use] @ R.T  # world direction per unit camera z
        zz = z[use]
        pts = t + rw * zz[:, None]
        valid = valid[use]

        dxy = pts[:, :2] - cam_xy
        rho = np.hypot(dxy[:, 0], dxy[:, 1])
        h = pts[:, 2] - self.floor_z
        cam_h = t[2] - self.floor_z
        lo, hi = self.obstacle_min_z, self.robot_height
        obstacle = valid & (h >= lo) & (h <= hi)
        # how far (horizontally) each ray stayed inside the band before leaving through its top:
        # a ray that rises above the robot says nothing about obstacles further along
        dz = h - cam_h
        with np.errstate(divide="ignore", invalid="ignore"):
            t_exit = np.where((h > hi) & (dz > 0), np.clip((hi - cam_h) / dz, 0.0, 1.0), 1.0)
        extent = rho * t_exit

        # azimuth bins (as many as sampled columns) relative to the optical axis
        phi = np.arctan2(dxy[:, 1], dxy[:, 0]) - yaw
        phi = wrap_angle(phi)
        nb = max(2, (W + s - 1) // s)
        pmin, pmax = float(phi.min()), float(phi.max())
        span = max(pmax - pmin, 1e-6)
        b = np.minimum(((phi - pmin) / span * nb).astype(np.int64), nb - 1)
        reach = np.zeros(nb)
        np.maximum.at(reach, b, extent)
        r_obs = np.full(nb, np.inf)
        if obstacle.any():
            np.minimum.at(r_obs, b[obstacle], rho[obstacle])
        reach = np.minimum(reach, r_obs)
        # columns are uniform in tan(angle), bins uniform in angle: a bin between two columns gets
        # no ray; give it the shorter of its neighbours rather than a notch back to the camera
        empty = np.bincount(b, minlength=nb) == 0
        if empty.any():
            idx = np.arange(nb)
            left = np.maximum.accumulate(np.where(~empty, idx, 0))
            right = np.minimum.accumulate(np.where(~empty, idx, nb - 1)[::-1])[::-1]
            reach[empty] = np.minimum(reach[left[empty]], reach[right[empty]])
        ang = yaw + pmin + (np.arange(nb) + 0.5) * span / nb
        # widen the fan by half a bin on each side so neighbouring frames tile without slivers
        ang[0] -= 0.5 * span / nb
        ang[-1] += 0.5 * span / nb
        fan = np.concatenate([cam_xy[None], cam_xy + reach[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1)])

        spec = self.spec
        c = spec.cell_size
        o = np.asarray(spec.origin_xy)
        fan_f = (fan - o) / c - 0.5  # continuous (col, row), cell centres at integers
        obs_rc = np.floor((pts[obstacle, :2] - o) / c).astype(np.int64)[:, ::-1]
        lo_f = np.floor(fan_f.min(0)).astype(np.int64) - 1
        hi_f = np.ceil(fan_f.max(0)).astype(np.int64) + 2
        if len(obs_rc):
            lo_f = np.minimum(lo_f, obs_rc.min(0)[::-1])
            hi_f = np.maximum(hi_f, obs_rc.max(0)[::-1] + 1)
        r0, r1 = max(0, lo_f[1]), min(spec.shape[0], hi_f[1])
        c0, c1 = max(0, lo_f[0]), min(spec.shape[1], hi_f[0])
        self.n_updates += 1
        if r0 >= r1 or c0 >= c1:
            return FovFootprint(slice(0, 0), slice(0, 0), np.zeros((0, 0), bool), cam_xy, yaw, hfov)
        buf = np.zeros((r1 - r0, c1 - c0), np.uint8)
        poly = np.round((fan_f - [c0, r0]) * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(buf, [poly], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        fan_mask = buf.astype(bool)
        win = self.state[r0:r1, c0:c1]
        win[fan_mask & (win != OCCUPIED)] = FREE
        if len(obs_rc):
            rr, cc = obs_rc[:, 0] - r0, obs_rc[:, 1] - c0
            ok = (rr >= 0) & (rr < r1 - r0) & (cc >= 0) & (cc < c1 - c0)
            win[rr[ok], cc[ok]] = OCCUPIED
        return FovFootprint(slice(r0, r1), slice(c0, c1), fan_mask & (win != OCCUPIED), cam_xy, yaw, hfov)
