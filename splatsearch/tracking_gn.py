"""Levenberg-Marquardt pose solver of the tracker (``TrackerConfig.solver = "gn"``).

The tracking loss (masked L1 on depth plus ``w_color`` times L1 on colour, and the odometry
prior ``xi^T Q xi``) is minimised over the pose parameters p (the camera-frame se(3) increment
``basis @ p``: 6 free or 3 planar) by damped Gauss-Newton steps. The L1 terms are reweighted as
in IRLS (curvature 1 / max(|r|, eps) at residual r). The residuals' Jacobian w.r.t. p comes either
from k forward-difference renders (the rasterizer has no forward mode; ``TrackerConfig.jacobian =
"finite-difference"``) or, from the one render at p, analytically (:func:`analytic_jacobian`,
``jacobian = "analytic"``). See
:class:`splatsearch.slam.TrackerConfig` for the settings and :func:`splatsearch.slam.track` for
the caller.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def _derivative(img, axis: int, order: int):
    """d img / d pixel along ``axis`` (0: rows, 1: columns): central differences (``order`` 2) or
    the five-point stencil (-1, 8, 0, -8, 1) / 12 (``order`` 4: closer to the derivative of
    detail near the pixel scale, which the three-point one flattens); one-sided at the border."""
    g2 = jnp.gradient(img, axis=axis)
    if order == 2:
        return g2
    n = img.shape[axis]
    pad = [(0, 0)] * img.ndim
    pad[axis] = (2, 2)
    p = jnp.pad(img, pad, mode="edge")
    sl = lambda a, b: jax.lax.slice_in_dim(p, a, a + n, axis=axis)  # noqa: E731
    g4 = (-sl(4, 0) + 8 * sl(3, 0) - 8 * sl(1, 0) + sl(0, 0)) / 12.0
    idx = jnp.arange(n)
    inner = (idx >= 2) & (idx < n - 2)
    shape = [1] * img.ndim
    shape[axis] = n
    return jnp.where(inner.reshape(shape), g4, g2)


def analytic_jacobian(r: jax.Array, rgb: jax.Array, depth: jax.Array, K: jax.Array, basis: jax.Array,
                      order: int = 2) -> jax.Array:
    """(H, W, 4, k) Jacobian of the tracking residuals (rendered minus observed: depth m, then
    colour) w.r.t. the pose parameters p (the camera-frame increment xi = ``basis @ p``, xi =
    (rotation vector rad, translation m), applied as exp(xi) @ viewmat), from ONE render.

    r (H, W, 4): the residuals at p (the render is ``r + (depth, rgb)``); rgb (H, W, 3), depth
    (H, W) the observed frame; K (3, 3) the intrinsics (pixel centres at +0.5); basis (6, k).

    The map is static, so moving the camera by xi moves the surface point P = z K^-1 (u, 1)
    behind pixel u (z: the rendered depth) to P + w x P + t, whose pixel moves by
    du = d(pi)/dP (w x P + t). To first order the render at the new pose is the old one shifted
    by du, I'(u) = I(u) - grad I(u) . du, and its depth also changes by the point's own z
    motion, D'(u) = D(u) - grad D(u) . du + (w x P + t)_z (direct RGB-D odometry's Jacobian,
    Kerl et al. 2013, with the rendered image in place of the reference frame). Image gradients
    are central differences of the render (one-sided at the border), in pixels. Pixels without
    rendered depth get zero rows (the tracker's mask leaves them out anyway).
    """
    img = r + jnp.concatenate([depth[..., None], rgb], -1)  # the render: depth, colour
    z = img[..., 0]
    H, W = z.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ok = z > 1e-4
    zi = jnp.where(ok, 1.0 / jnp.where(ok, z, 1.0), 0.0)
    xz = ((jnp.arange(W, dtype=z.dtype) + 0.5 - cx) / fx)[None, :] * jnp.ones_like(z)  # x / z
    yz = ((jnp.arange(H, dtype=z.dtype) + 0.5 - cy) / fy)[:, None] * jnp.ones_like(z)  # y / z
    x, y = xz * z, yz * z
    zero = jnp.zeros_like(z)
    # d(u, v)/dxi, xi = (w, t): the pinhole's derivative times dP/dxi = [-[P]x | I]
    du = jnp.stack([-fx * xz * yz, fx * (1 + xz * xz), -fx * yz, fx * zi, zero, -fx * xz * zi], -1)
    dv = jnp.stack([-fy * (1 + yz * yz), fy * xz * yz, fy * xz, zero, fy * zi, -fy * yz * zi], -1)
    dz = jnp.stack([y, -x, zero, zero, zero, jnp.ones_like(z)], -1)  # (w x P + t)_z
    gu = _derivative(img, 1, order)  # (H, W, 4) per pixel
    gv = _derivative(img, 0, order)
    J = -(gu[..., None] * du[:, :, None, :] + gv[..., None] * dv[:, :, None, :])  # (H, W, 4, 6)
    J = J.at[:, :, 0, :].add(dz)
    J = jnp.where(ok[..., None, None] & jnp.isfinite(J), J, 0.0)
    return J @ basis.astype(J.dtype)


def axis_information(Hd: jax.Array, v: jax.Array) -> jax.Array:
    """The information a data metric ``Hd`` (k, k) holds on the parameter direction ``v`` (k,)
    with every other direction free: 1 / (v^T Hd^-1 v) for a unit ``v`` (the Schur complement of
    the rest; ``v`` is normalised here). 0 for a zero ``v``."""
    nv = jnp.linalg.norm(v)
    u = v / jnp.maximum(nv, 1e-12)
    x = jnp.linalg.solve(Hd + 1e-9 * jnp.eye(Hd.shape[0], dtype=Hd.dtype), u)
    return jnp.where(nv > 1e-6, 1.0 / jnp.maximum(u @ x, 1e-30), 0.0)


def fade_weight(info: jax.Array, extra: jax.Array) -> jax.Array:
    """The fraction (in [0, 1]) of an extra prior precision on one direction that is kept, given
    the image's information ``info`` on that direction (:func:`axis_information`, the data
    loss's curvature) and the extra prior's own curvature ``extra`` there (2 x its precision):
    1 - info / extra, clipped. The prior fills in up to its own precision what the image does not
    supply: all of it where the image says nothing (a plain corridor seen along its axis), none
    where the image alone already fixes the direction that well. ``extra`` <= 0: 0."""
    return jnp.where(extra > 0, jnp.clip(1.0 - info / jnp.maximum(extra, 1e-30), 0.0, 1.0), 0.0)


def make_gn_stage(cfg) -> Callable:
    """The Levenberg-Marquardt stage for the tracker settings ``cfg`` (a ``TrackerConfig``).

    Returns ``gn_stage(p, n_iters, lr_scale, fn, margs, rgb, depth, vm_ref, basis, pw, info_ref, fade)``
    -> (p, loss, steps, trusted mask, last loss, rot_info, start loss, fwd_info, fade weight), run
    inside the tracker's jit: p (k,) the start, ``fn`` = (mask_at, loss, value_and_grad of loss,
    residual) of one image level (rgb (H, W, 3), depth (H, W) m), ``pw`` (6, 6) the prior's
    precision on xi, ``info_ref`` the usual rotation information (0: no information weighting);
    ``fade`` = (pf (6, 6), axis (6,), scale): an extra prior precision on xi kept in the fraction
    :func:`fade_weight` of ``scale`` x the image's information on ``axis`` (an xi direction;
    zero: no axis, fwd_info 0 and the weight 0); ``lr_scale`` is unused.
    """
    w_c = cfg.w_color
    h_fd = cfg.gn_fd_step
    eps = jnp.array([cfg.gn_eps_depth] + [cfg.gn_eps_color] * 3, jnp.float32)
    step_tol = cfg.gn_step_tol
    loss_tol = cfg.gn_loss_tol
    eps_rel = cfg.gn_eps_rel
    refresh = cfg.gn_refresh
    info_max = cfg.prior_info_max
    analytic = cfg.jacobian == "analytic"

    def _lm_delta(Hm, g, lam):
        """The damped step -(Hm + lam diag(Hm))^-1 g; a non-finite component becomes 0."""
        A = Hm + lam * jnp.diag(jnp.diag(Hm)) + 1e-9 * jnp.eye(Hm.shape[0], dtype=Hm.dtype)
        delta = -jnp.linalg.solve(A, g)
        return jnp.where(jnp.isfinite(delta), delta, 0.0)

    def _fixed_metric(p, n_iters, vg, args, Hd, Pp, mf, L0, g0):
        """Levenberg-Marquardt steps from p (loss L0, gradient g0) with the data metric ``Hd``
        formed once and the exact gradient of the loss (the rasterizer's pose-only backward) after
        every accepted step: one forward + backward per step instead of k + 1 forwards, and the
        fixed point is the loss's own minimum whatever the metric's error.

        The IRLS weights are about 1 / (``gn_eps_rel`` x the mean |residual|) for most pixels, so
        the data metric grows as the data loss falls: ``Hd`` is scaled by the data loss where it
        was formed over the current one (without this, a start far from the minimum leaves a
        metric several times too flat near it, and steps overshoot and are rejected).

        The rasterizer's backward runs only when its gradient is used: after a step that is
        accepted and followed by another one (a rejected step keeps the old gradient, the last
        step's is never read). ``vg`` is (loss, its value-and-gradient); the loss's vjp gives the
        forward at once and the backward on demand."""
        loss_fn = vg[0]
        Ld0 = jnp.maximum(L0 - p @ Pp @ p, 1e-12)

        def cond(c):
            return (c[0] < n_iters) & ~c[-1]

        def body(c):
            it, p, L, g, _, lam, done = c
            Ld = jnp.maximum(L - p @ Pp @ p, 1e-12)
            Hm = Hd * jnp.clip(Ld0 / Ld, 1.0, 100.0) + 2.0 * Pp
            delta = _lm_delta(Hm, jnp.where(jnp.isfinite(g), g, 0.0), lam)
            L_new, pull = jax.vjp(lambda q: loss_fn(q, *args), p + delta)
            accept = L_new < L
            small = (jnp.max(jnp.abs(delta)) < step_tol) | (accept & (L - L_new < loss_tol * L))
            lam = jnp.where(accept, lam * 0.3, lam * 10.0)
            done = small | (lam > 1e6)
            need = accept & ~done & (it + 1 < n_iters)  # another step follows from p + delta
            g_new = jax.lax.cond(need, lambda: pull(jnp.ones_like(L_new))[0], lambda: g)
            p, L = jnp.where(accept, p + delta, p), jnp.where(accept, L_new, L)
            return it + 1, p, L, g_new, Hm, lam, done

        c = (jnp.int32(0), p, L0, g0, Hd, jnp.float32(1e-4), jnp.asarray(False))
        k, p, L, _, _, _, _ = jax.lax.while_loop(cond, body, c)
        return p, L, k, mf, L

    def rotation_info(Hd, k_dim):
        """The image's information on the rotation once the translation is free: the Schur
        complement of the translation block of the data metric (planar: the yaw's; 6 DoF: the
        smallest eigenvalue of the 3 x 3 rotation block's)."""
        nr = 1 if k_dim == 3 else 3
        Hrr, Hrt, Htt = Hd[:nr, :nr], Hd[:nr, nr:], Hd[nr:, nr:]
        M = Hrr - Hrt @ jnp.linalg.solve(Htt + 1e-12 * jnp.eye(Htt.shape[0], dtype=Htt.dtype), Hrt.T)
        return M[0, 0] if nr == 1 else jnp.linalg.eigvalsh(M)[0]

    def gn_stage(p, n_iters, lr_scale, fn, margs, rgb, depth, vm_ref, basis, pw, info_ref, fade):
        """Levenberg-Marquardt from p on one level, same loss and trusted pixels as the Adam stage.

        The L1 terms are reweighted (IRLS): at residual r the quadratic model of |r| has curvature
        1 / max(|r|, eps) and slope sign(r), which majorises |r|, so a step that lowers the model
        lowers the loss while the linearisation holds. The Jacobian of the rendered depth and
        colour w.r.t. the k pose parameters comes from k forward-difference renders (the
        rasterizer has no forward mode) or, with ``cfg.jacobian == "analytic"``, from the render
        at p (:func:`analytic_jacobian`); a rejected step raises the damping and reuses it."""
        mask_at, loss, vg, residual, K = fn
        k_dim = p.shape[0]
        r0, mf = residual(p, margs, rgb, depth, vm_ref, basis, with_mask=True)
        n = jnp.maximum(mf.sum(), 1.0)
        a = mf[..., None] * jnp.array([1.0, w_c, w_c, w_c], jnp.float32) / n  # (H, W, 4) L1 weights

        def data_eq(p, r):
            if analytic:
                J = analytic_jacobian(r, rgb, depth, K, basis)
            else:
                cols = [(residual(p + h_fd * jnp.eye(k_dim, dtype=p.dtype)[j], margs, rgb, depth, vm_ref, basis) - r)
                        / h_fd for j in range(k_dim)]
                J = jnp.stack(cols, -1)  # (H, W, 4, k)
            ar = jnp.abs(r)
            scale = jnp.sum(ar * mf[..., None], (0, 1)) / n  # mean |residual| per channel
            w = a / jnp.maximum(ar, jnp.maximum(eps, eps_rel * scale))
            return jnp.einsum("hwck,hwc,hwcl->kl", J, w, J), jnp.einsum("hwck,hwc->k", J, a * jnp.sign(r))

        Hd0, gd0 = data_eq(p, r0)
        Ld0 = jnp.sum(a * jnp.abs(r0))
        # per trusted-pixel share of the image, independent of the residuals' size (the IRLS
        # weights scale as 1 / mean |r|)
        info = rotation_info(Hd0, k_dim) * Ld0 * mf.mean()
        if info_max > 1:  # the image fixes the rotation less than usual: trust the odometry more
            f = jnp.where(info_ref > 0, jnp.clip(info_ref / jnp.maximum(info, 1e-30), 1.0, info_max), 1.0)
            sq = jnp.concatenate([jnp.full(3, jnp.sqrt(f)), jnp.ones(3)]).astype(pw.dtype)
            pw = pw * sq[:, None] * sq[None, :]
        # the image's information on the fade axis, at the start pose, in the loss's own curvature
        # units (comparable with the prior's 2 Q), every other pose direction free
        pf, axis, scale = fade
        v = basis.T @ axis.astype(basis.dtype)
        fwd_info = axis_information(Hd0, v)
        nv = jnp.maximum(jnp.linalg.norm(v), 1e-12)
        wf = fade_weight(scale * fwd_info, 2.0 * (v @ basis.T @ pf @ basis @ v) / nv ** 2)
        pw = pw + wf * pf
        Pp = basis.T @ pw @ basis  # the prior on p: p^T Pp p

        def value(p, r):
            return jnp.sum(a * jnp.abs(r)) + p @ Pp @ p

        def normal_eq(p, r):
            Hd, gd = data_eq(p, r)
            return Hd, gd + 2.0 * Pp @ p

        L0 = value(p, r0)
        g0 = gd0 + 2.0 * Pp @ p

        if not refresh:  # the first step's gradient is the difference quotients'
            return (*_fixed_metric(p, n_iters, (loss, vg), (margs, rgb, depth, vm_ref, basis, mf, pw), Hd0, Pp, mf, L0, g0),
                    info, L0, fwd_info, wf)
        H0 = Hd0 + 2.0 * Pp

        def cond(c):
            it, _, _, _, _, _, _, done = c
            return (it < n_iters) & ~done

        def body(c):
            it, p, L, r, Hm, g, lam, done = c
            delta = _lm_delta(Hm, g, lam)
            p_new = p + delta
            r_new = residual(p_new, margs, rgb, depth, vm_ref, basis)
            L_new = value(p_new, r_new)
            accept = L_new < L  # NaN compares False
            Hn, gn = jax.lax.cond(accept, lambda: normal_eq(p_new, r_new), lambda: (Hm - 2.0 * Pp, g))
            Hn = Hn + 2.0 * Pp
            small = (jnp.max(jnp.abs(delta)) < step_tol) | (accept & (L - L_new < loss_tol * L))
            p, L, r = (jnp.where(accept, p_new, p), jnp.where(accept, L_new, L),
                       jnp.where(accept, r_new, r))
            lam = jnp.where(accept, lam * 0.3, lam * 10.0)
            done = small | (lam > 1e6)
            return it + 1, p, L, r, Hn, gn, lam, done

        c = (jnp.int32(0), p, L0, r0, H0, g0, jnp.float32(1e-4), jnp.asarray(False))
        k, p, L, _, _, _, _, _ = jax.lax.while_loop(cond, body, c)
        return p, L, k, mf, L, info, L0, fwd_info, wf

    return gn_stage
