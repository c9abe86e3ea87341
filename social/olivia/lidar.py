"""OLiVia-Nav's simulated 3-D LiDAR (thesis 3.3): rings x azimuths over the wall distance field
and the people; two sweeps (now and ``PREV_STEPS`` steps earlier, ego-motion compensated) so that
the point cloud carries motion.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..convoi.geometry import F32, DistanceField, world_to_robot
from .render import MAX_RANGE, PERSON_HEIGHT, WALL_HEIGHT, _cast


LIDAR_HEIGHT = 0.45             # m
LIDAR_AZ = 180                  # azimuth rays over 360°
LIDAR_ELEV = (-0.05, 0.05, 0.15, 0.3)  # ring elevations (rad)
PREV_STEPS = 3                  # the second sweep is this many sim steps old (0.3 s)
N_POINTS = 2 * len(LIDAR_ELEV) * LIDAR_AZ


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
