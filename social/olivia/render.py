"""OLiVia-Nav's egocentric camera (thesis 3.3): a column ray-caster over a scenario's wall
distance field and the people (cylinders), with a checkered floor in world coordinates, so a view
shows people (each in a named shirt colour), walls and the layout.

Frames: robot frame x forward, y left (metres); angles in radians counter-clockwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..convoi.geometry import F32, DistanceField, field_lookup


IMG_H, IMG_W = 32, 64          # egocentric view (pixels)
HFOV = np.radians(120.0)        # horizontal field of view (rad)
CAM_HEIGHT = 1.0                # m
WALL_HEIGHT, PERSON_HEIGHT = 2.0, 1.7  # m
PERSON_RADIUS = 0.25            # m
MAX_RANGE = 8.0                 # m, camera and LiDAR
COLOURS = ("red", "blue", "orange", "purple", "green", "yellow", "pink", "brown")
COLOUR_RGB = np.asarray([(0.85, 0.15, 0.12), (0.12, 0.30, 0.85), (0.95, 0.55, 0.05), (0.50, 0.18, 0.65),
                         (0.10, 0.60, 0.25), (0.92, 0.85, 0.10), (0.95, 0.50, 0.70), (0.50, 0.30, 0.12)], np.float32)
FLOOR_RGB = np.asarray((0.80, 0.74, 0.62), np.float32)
WALL_RGB = np.asarray((0.62, 0.64, 0.68), np.float32)
CEIL_RGB = np.asarray((0.93, 0.94, 0.96), np.float32)


def person_colour(index: int, seed: int) -> int:
    """Palette index of person ``index`` in a scenario of ``seed`` (shirt colours vary by seed)."""
    return (int(index) + int(seed)) % len(COLOURS)


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


def palette_of(scn) -> jax.Array:
    """(P,) int32 shirt colours of a scenario's (padded) people."""
    return jnp.asarray([person_colour(i, scn.seed) for i in range(np.asarray(scn.peds.pos).shape[0])], jnp.int32)


def to_uint8(img) -> np.ndarray:
    return (np.clip(np.asarray(img), 0, 1) * 255 + 0.5).astype(np.uint8)
