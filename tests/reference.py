"""Dense pure-JAX reference rasterizer (float64) with exactly the rules of the Warp kernels.

No tiles: every pixel walks over every non-culled Gaussian in (depth, index) order. It is slow
(O(pixels x N)) and only meant for small test scenes; ``jax.grad`` through it is the gradient
oracle for the hand-written Warp backward.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4


def quat_to_rotmat(q):
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def project(means, quats, scales, opacities, viewmat, K, width, height, near=0.01, far=1e10, eps2d=0.3):
    """Returns means2d (N,2), conics (N,3), depths (N,), radii (N,2) int, valid (N,) bool."""
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Rq = quat_to_rotmat(quats)
    M = Rq * scales[:, None, :]
    Sigma = M @ jnp.swapaxes(M, 1, 2)
    Sc = R @ Sigma @ R.T
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_xp = (width - cx) / fx + 0.3 * tan_fovx
    lim_xn = cx / fx + 0.3 * tan_fovx
    lim_yp = (height - cy) / fy + 0.3 * tan_fovy
    lim_yn = cy / fy + 0.3 * tan_fovy
    zs = jnp.where(z > 0, z, 1.0)  # keeps culled Gaussians finite (and their gradients zero)
    tx = zs * jnp.clip(x / zs, -lim_xn, lim_xp)
    ty = zs * jnp.clip(y / zs, -lim_yn, lim_yp)
    zero = jnp.zeros_like(zs)
    J = jnp.stack([
        jnp.stack([fx / zs, zero, -fx * tx / zs**2], -1),
        jnp.stack([zero, fy / zs, -fy * ty / zs**2], -1),
    ], -2)
    cov = J @ Sc @ jnp.swapaxes(J, 1, 2)
    c00 = cov[:, 0, 0] + eps2d
    c01 = cov[:, 0, 1]
    c11 = cov[:, 1, 1] + eps2d
    det = c00 * c11 - c01 * c01
    dets = jnp.where(det > 0, det, 1.0)
    conics = jnp.stack([c11 / dets, -c01 / dets, c00 / dets], -1)
    mx = fx * x / zs + cx
    my = fy * y / zs + cy
    op = jnp.maximum(opacities, ALPHA_MIN)
    extend = jnp.minimum(3.33, jnp.sqrt(2.0 * jnp.log(op / ALPHA_MIN)))
    rx = jnp.ceil(extend * jnp.sqrt(jnp.maximum(c00, 0)))
    ry = jnp.ceil(extend * jnp.sqrt(jnp.maximum(c11, 0)))
    valid = (z >= near) & (z <= far) & (opacities >= ALPHA_MIN) & (det > 0)
    valid &= ~((rx <= 0) & (ry <= 0))
    valid &= ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
    radii = jnp.where(valid[:, None], jnp.stack([rx, ry], -1), 0).astype(jnp.int32)
    # depth order and composited depth use the distance along the ray (turn-invariant)
    return jnp.stack([mx, my], -1), conics, jnp.sqrt(x * x + y * y + z * z), radii, valid


def rasterize_dense(means, quats, scales, opacities, colors, viewmat, K, width, height,
                    near=0.01, far=1e10, eps2d=0.3):
    """Returns (color (H,W,C), depth D (H,W,1), alpha (H,W,1), radii (N,2))."""
    means2d, conics, depths, radii, valid = project(
        means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
    N = means.shape[0]
    C = colors.shape[1]
    order = jnp.argsort(jnp.where(valid, depths, jnp.inf), stable=True)
    py, px = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    pix = jnp.stack([px.ravel() + 0.5, py.ravel() + 0.5], -1).astype(means.dtype)
    P = pix.shape[0]

    def step(carry, g):
        T, acc, dep, done = carry
        d = means2d[g] - pix
        cn = conics[g]
        sigma = 0.5 * (cn[0] * d[:, 0] ** 2 + cn[2] * d[:, 1] ** 2) + cn[1] * d[:, 0] * d[:, 1]
        alpha = jnp.minimum(ALPHA_MAX, opacities[g] * jnp.exp(-sigma))
        live = valid[g] & ~done & (sigma >= 0) & (alpha >= ALPHA_MIN)
        nT = T * (1 - alpha)
        stop = live & (nT <= T_MIN)
        use = live & ~stop
        w = jnp.where(use, alpha * T, 0.0)
        acc = acc + w[:, None] * colors[g][None, :]
        dep = dep + w * depths[g]
        T = jnp.where(use, nT, T)
        return (T, acc, dep, done | stop), None

    init = (jnp.ones(P, means.dtype), jnp.zeros((P, C), means.dtype), jnp.zeros(P, means.dtype),
            jnp.zeros(P, bool))
    (T, acc, dep, _), _ = jax.lax.scan(step, init, order) if N else (init, None)
    # back to z-depth: per pixel, z per unit of distance along its ray
    K = jnp.asarray(K, means.dtype)
    zfac = 1.0 / jnp.sqrt(1.0 + ((pix[:, 0] - K[0, 2]) / K[0, 0]) ** 2 + ((pix[:, 1] - K[1, 2]) / K[1, 1]) ** 2)
    return (acc.reshape(height, width, C), (dep * zfac).reshape(height, width, 1),
            (1 - T).reshape(height, width, 1), radii)


def top_ids_dense(means, quats, scales, opacities, viewmat, K, width, height, near=0.01, far=1e10, eps2d=0.3):
    """(ids (H, W), weights (H, W)): per pixel the Gaussian with the largest alpha * T, -1 if none."""
    means2d, conics, depths, _, valid = project(
        means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
    order = jnp.argsort(jnp.where(valid, depths, jnp.inf), stable=True)
    py, px = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    pix = jnp.stack([px.ravel() + 0.5, py.ravel() + 0.5], -1).astype(means.dtype)
    P = pix.shape[0]

    def step(carry, g):
        T, best, best_w, done = carry
        d = means2d[g] - pix
        cn = conics[g]
        sigma = 0.5 * (cn[0] * d[:, 0] ** 2 + cn[2] * d[:, 1] ** 2) + cn[1] * d[:, 0] * d[:, 1]
        alpha = jnp.minimum(ALPHA_MAX, opacities[g] * jnp.exp(-sigma))
        live = valid[g] & ~done & (sigma >= 0) & (alpha >= ALPHA_MIN)
        nT = T * (1 - alpha)
        stop = live & (nT <= T_MIN)
        use = live & ~stop
        w = jnp.where(use, alpha * T, 0.0)
        win = w > best_w
        return (jnp.where(use, nT, T), jnp.where(win, g.astype(jnp.int32), best), jnp.where(win, w, best_w), done | stop), None

    init = (jnp.ones(P, means.dtype), jnp.full(P, -1, jnp.int32), jnp.zeros(P, means.dtype), jnp.zeros(P, bool))
    (_, best, best_w, _), _ = jax.lax.scan(step, init, order) if means.shape[0] else (init, None)
    return best.reshape(height, width), best_w.reshape(height, width)
