"""EWA projection of 3-D Gaussians to 2-D conics, and its hand-written adjoint.

The numeric rules follow gsplat 1.5 ``fully_fused_projection`` (classic mode):

* camera point ``p = R m + t`` with ``viewmat = [[R, t], [0, 1]]`` (world-to-camera, OpenCV frame);
* culled when ``z < near`` or ``z > far``;
* ``Sigma = (Rq S)(Rq S)^T`` with ``Rq`` from the normalised quaternion (w, x, y, z);
* the perspective Jacobian uses the gsplat clipping of x/z and y/z to 1.3x the field of view;
* ``cov2d = J R Sigma R^T J^T + eps2d I`` (the 0.3 px^2 low-pass);
* culled when det(cov2d) <= 0 or the opacity is below 1/255;
* opacity-aware radius ``ceil(min(3.33, sqrt(2 ln(255 o))) * sqrt(cov2d_ii))`` per axis;
* culled when the radius box lies outside the image.

Culled Gaussians get radius (0, 0) and are never binned.
"""

from __future__ import annotations

import warp as wp

# Warp's automatic adjoints are never used: every backward here is written by hand.
wp.set_module_options({"enable_backward": False})

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.999)
T_MIN = wp.constant(1.0e-4)
EXTEND_MAX = wp.constant(3.33)

mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)


@wp.func
def quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of a *normalised* quaternion stored as (w, x, y, z)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def quat_to_rotmat_vjp(q: wp.vec4, v: wp.mat33) -> wp.vec4:
    """Adjoint of ``quat_to_rotmat`` for a normalised quaternion (w, x, y, z)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    vw = 2.0 * (x * (v[2, 1] - v[1, 2]) + y * (v[0, 2] - v[2, 0]) + z * (v[1, 0] - v[0, 1]))
    vx = 2.0 * (-2.0 * x * (v[1, 1] + v[2, 2]) + y * (v[1, 0] + v[0, 1]) + z * (v[2, 0] + v[0, 2])
                + w * (v[2, 1] - v[1, 2]))
    vy = 2.0 * (x * (v[1, 0] + v[0, 1]) - 2.0 * y * (v[0, 0] + v[2, 2]) + z * (v[2, 1] + v[1, 2])
                + w * (v[0, 2] - v[2, 0]))
    vz = 2.0 * (x * (v[2, 0] + v[0, 2]) + y * (v[2, 1] + v[1, 2]) - 2.0 * z * (v[0, 0] + v[1, 1])
                + w * (v[1, 0] - v[0, 1]))
    return wp.vec4(vw, vx, vy, vz)


@wp.func
def camera_rotation(vm: wp.mat44) -> wp.mat33:
    return wp.mat33(vm[0, 0], vm[0, 1], vm[0, 2], vm[1, 0], vm[1, 1], vm[1, 2], vm[2, 0], vm[2, 1], vm[2, 2])


@wp.func
def clip_limits(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> wp.vec4:
    """gsplat's x/z, y/z clipping limits: (lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg)."""
    tan_fovx = 0.5 * float(width) / fx
    tan_fovy = 0.5 * float(height) / fy
    return wp.vec4(
        (float(width) - cx) / fx + 0.3 * tan_fovx,
        cx / fx + 0.3 * tan_fovx,
        (float(height) - cy) / fy + 0.3 * tan_fovy,
        cy / fy + 0.3 * tan_fovy,
    )


@wp.func
def camera_adjoint(p: wp.vec3, Sc: wp.mat33, fx: float, fy: float, lim: wp.vec4, cn: wp.vec3, vm2: wp.vec2,
                   vc: wp.vec3, v_depth: float):
    """Adjoint of the projection from the camera-space point p and covariance Sc to (mean2d, conic,
    depth), for their cotangents (vm2, vc, v_depth): returns (v_p, v_Sc)."""
    z = p[2]
    rz = 1.0 / z
    rz2 = rz * rz
    u = p[0] * rz
    v = p[1] * rz
    tx = z * wp.min(lim[0], wp.max(-lim[1], u))
    ty = z * wp.min(lim[2], wp.max(-lim[3], v))
    J = mat23(fx * rz, 0.0, -fx * tx * rz2, 0.0, fy * rz, -fy * ty * rz2)

    # conic = inverse(cov2d): v_cov = -conic * v_conic_sym * conic
    Cm = wp.mat22(cn[0], cn[1], cn[1], cn[2])
    Vc = wp.mat22(vc[0], 0.5 * vc[1], 0.5 * vc[1], vc[2])
    v_cov = -(Cm * Vc * Cm)

    # cov2d = J Sc J^T (+ eps2d I, which has no parameters)
    v_Sc = wp.transpose(J) * v_cov * J
    v_J = 2.0 * (v_cov * J * Sc)

    # camera-space point: mean2d, depth and the Jacobian's dependence on p
    v_p = wp.vec3(fx * rz * vm2[0], fy * rz * vm2[1],
                  -(fx * p[0] * vm2[0] + fy * p[1] * vm2[1]) * rz2) + (v_depth / wp.length(p)) * p
    x_in = 1.0
    if u > lim[0] or u < -lim[1]:
        x_in = 0.0
    y_in = 1.0
    if v > lim[2] or v < -lim[3]:
        y_in = 0.0
    # J02 = -fx tx / z^2 with tx = x (inside) or z * const (clipped)
    v_p = v_p + wp.vec3(
        -fx * rz2 * v_J[0, 2] * x_in,
        -fy * rz2 * v_J[1, 2] * y_in,
        -fx * rz2 * v_J[0, 0] - fy * rz2 * v_J[1, 1]
        + fx * tx * rz2 * rz * (1.0 + x_in) * v_J[0, 2]
        + fy * ty * rz2 * rz * (1.0 + y_in) * v_J[1, 2],
    )

    return v_p, v_Sc


@wp.kernel
def project_fwd_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    viewmat: wp.array(dtype=wp.mat44),
    intrin: wp.array(dtype=wp.mat33),
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float,
    i0: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    radii: wp.array(dtype=wp.vec2i),
):
    i = wp.tid() + i0
    vm = viewmat[0]
    R = camera_rotation(vm)
    t = wp.vec3(vm[0, 3], vm[1, 3], vm[2, 3])
    p = R * means[i] + t
    z = p[2]
    radii[i] = wp.vec2i(0, 0)
    means2d[i] = wp.vec2(0.0, 0.0)
    conics[i] = wp.vec3(0.0, 0.0, 0.0)
    # sort and composite by the distance along the ray, which a turn of the camera leaves unchanged
    # (the z-depth of a point changes with its angle off the axis); the rasterizer turns the
    # composited distance back into z-depth per pixel
    depths[i] = wp.length(p)
    if z < near or z > far:
        return
    o = opacities[i]
    if o < ALPHA_MIN:
        return
    K = intrin[0]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]

    q = quats[i]
    qn = q / wp.length(q)
    Rq = quat_to_rotmat(qn)
    s = scales[i]
    M = Rq * wp.diag(s)
    Sigma = M * wp.transpose(M)
    Sc = R * Sigma * wp.transpose(R)

    lim = clip_limits(width, height, fx, fy, cx, cy)
    rz = 1.0 / z
    tx = z * wp.min(lim[0], wp.max(-lim[1], p[0] * rz))
    ty = z * wp.min(lim[2], wp.max(-lim[3], p[1] * rz))
    J = mat23(fx * rz, 0.0, -fx * tx * rz * rz, 0.0, fy * rz, -fy * ty * rz * rz)
    cov = J * Sc * wp.transpose(J)
    c00 = cov[0, 0] + eps2d
    c01 = cov[0, 1]
    c11 = cov[1, 1] + eps2d
    det = c00 * c11 - c01 * c01
    if det <= 0.0:
        return
    inv_det = 1.0 / det
    mx = fx * p[0] * rz + cx
    my = fy * p[1] * rz + cy
    extend = wp.min(EXTEND_MAX, wp.sqrt(2.0 * wp.log(o / ALPHA_MIN)))
    rx = wp.ceil(extend * wp.sqrt(c00))
    ry = wp.ceil(extend * wp.sqrt(c11))
    if rx <= 0.0 and ry <= 0.0:
        return
    if mx + rx <= 0.0 or mx - rx >= float(width) or my + ry <= 0.0 or my - ry >= float(height):
        return
    means2d[i] = wp.vec2(mx, my)
    conics[i] = wp.vec3(c11 * inv_det, -c01 * inv_det, c00 * inv_det)
    radii[i] = wp.vec2i(int(rx), int(ry))


@wp.kernel
def project_bwd_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    viewmat: wp.array(dtype=wp.mat44),
    intrin: wp.array(dtype=wp.mat33),
    width: int,
    height: int,
    eps2d: float,
    conics: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=wp.vec2i),
    v_means2d: wp.array(dtype=wp.vec2),
    v_conics: wp.array(dtype=wp.vec3),
    v_depths: wp.array(dtype=float),
    i0: int,
    slot0: int,
    n_slots: int,
    v_means: wp.array(dtype=wp.vec3),
    v_quats: wp.array(dtype=wp.vec4),
    v_scales: wp.array(dtype=wp.vec3),
    v_viewmat: wp.array2d(dtype=float),
):
    """Adjoint of ``project_fwd_kernel``.

    ``v_viewmat`` rows are accumulation slots of 16 floats (row-major 4x4; the last row stays 0);
    Gaussian i adds into row ``slot0 + i % n_slots``: on CUDA this spreads the atomics, on the
    CPU every concurrently running launch gets rows of its own.
    """
    i = wp.tid() + i0
    r = radii[i]
    if r[0] <= 0 and r[1] <= 0:
        v_means[i] = wp.vec3(0.0, 0.0, 0.0)
        v_quats[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        v_scales[i] = wp.vec3(0.0, 0.0, 0.0)
        return
    vm = viewmat[0]
    R = camera_rotation(vm)
    t = wp.vec3(vm[0, 3], vm[1, 3], vm[2, 3])
    m = means[i]
    p = R * m + t
    K = intrin[0]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]

    q = quats[i]
    qlen = wp.length(q)
    qn = q / qlen
    Rq = quat_to_rotmat(qn)
    s = scales[i]
    M = Rq * wp.diag(s)
    Sigma = M * wp.transpose(M)
    Sc = R * Sigma * wp.transpose(R)

    lim = clip_limits(width, height, fx, fy, cx, cy)
    v_p, v_Sc = camera_adjoint(p, Sc, fx, fy, lim, conics[i], v_means2d[i], v_conics[i], v_depths[i])

    # Sc = R Sigma R^T
    v_Sigma = wp.transpose(R) * v_Sc * R
    v_R = 2.0 * (v_Sc * R * Sigma) + wp.outer(v_p, m)
    v_means[i] = wp.transpose(R) * v_p

    # Sigma = M M^T, M = Rq diag(s)
    v_M = 2.0 * (v_Sigma * M)
    v_Rq = v_M * wp.diag(s)
    v_scales[i] = wp.vec3(
        Rq[0, 0] * v_M[0, 0] + Rq[1, 0] * v_M[1, 0] + Rq[2, 0] * v_M[2, 0],
        Rq[0, 1] * v_M[0, 1] + Rq[1, 1] * v_M[1, 1] + Rq[2, 1] * v_M[2, 1],
        Rq[0, 2] * v_M[0, 2] + Rq[1, 2] * v_M[1, 2] + Rq[2, 2] * v_M[2, 2],
    )
    v_qn = quat_to_rotmat_vjp(qn, v_Rq)
    v_quats[i] = (v_qn - qn * wp.dot(qn, v_qn)) / qlen

    slot = slot0 + i % n_slots
    for a in range(3):
        for b in range(3):
            wp.atomic_add(v_viewmat, slot, a * 4 + b, v_R[a, b])
        wp.atomic_add(v_viewmat, slot, a * 4 + 3, v_p[a])


#: Gaussians per row of the pose-only backward's viewmat reduction
VIEW_CHUNK = 256


@wp.kernel
def project_bwd_viewmat_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    viewmat: wp.array(dtype=wp.mat44),
    intrin: wp.array(dtype=wp.mat33),
    width: int,
    height: int,
    conics: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=wp.vec2i),
    acc: wp.array(dtype=float),
    n_groups: int,
    c0: int,
    out: wp.array2d(dtype=float),
):
    """The viewmat part of ``project_bwd_kernel``, one thread per chunk of ``VIEW_CHUNK`` Gaussians.

    Gaussian i's cotangents (depth, conic a, b, c, mean2d x, y) are the sum over ``n_groups``
    accumulator groups of ``acc[6 (k n + i):]`` (k = 0, 1, ..., in that order); chunk c writes its
    16-float sum (row-major 4x4, last row 0) to ``out[c]``. Every sum runs in a fixed order, so the
    result does not depend on how the chunks are split over threads.
    """
    c = wp.tid() + c0
    n = means.shape[0]
    vm = viewmat[0]
    R = camera_rotation(vm)
    t = wp.vec3(vm[0, 3], vm[1, 3], vm[2, 3])
    K = intrin[0]
    fx = K[0, 0]
    fy = K[1, 1]
    lim = clip_limits(width, height, fx, fy, K[0, 2], K[1, 2])
    sR = wp.mat33()
    sp = wp.vec3()
    for i in range(c * VIEW_CHUNK, wp.min(n, (c + 1) * VIEW_CHUNK)):
        r = radii[i]
        if r[0] <= 0 and r[1] <= 0:
            continue
        g = wp.vector(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, dtype=float)
        for k in range(n_groups):
            b = (k * n + i) * 6
            for q in range(6):
                g[q] = g[q] + acc[b + q]
        m = means[i]
        p = R * m + t
        q4 = quats[i]
        Rq = quat_to_rotmat(q4 / wp.length(q4))
        M = Rq * wp.diag(scales[i])
        Sigma = M * wp.transpose(M)
        Sc = R * Sigma * wp.transpose(R)
        v_p, v_Sc = camera_adjoint(p, Sc, fx, fy, lim, conics[i], wp.vec2(g[4], g[5]), wp.vec3(g[1], g[2], g[3]),
                                   g[0])
        sR = sR + 2.0 * (v_Sc * R * Sigma) + wp.outer(v_p, m)
        sp = sp + v_p
    for a in range(3):
        for b2 in range(3):
            out[c, a * 4 + b2] = sR[a, b2]
        out[c, a * 4 + 3] = sp[a]
    for b2 in range(4):
        out[c, 12 + b2] = 0.0
