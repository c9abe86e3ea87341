"""On-device checks of Gaussian and camera values, for calls whose inputs are traced under jit.

The flags come back to the host together with the intersection count (the forward's single
host read), so validation costs one extra cheap pass over N and no extra synchronisation.
"""

from __future__ import annotations

import warp as wp

# Warp's automatic adjoints are never used: every backward here is written by hand.
wp.set_module_options({"enable_backward": False})

# flag slots: one per failure, so the host can name the argument
F_MEANS = 0
F_QUATS = 1
F_QUATS_ZERO = 2
F_SCALES = 3
F_SCALES_NEG = 4
F_OPAC = 5
F_OPAC_RANGE = 6
F_COLORS = 7
F_VIEWMAT = 8
F_K = 9
N_FLAGS = 10

class InputValueError(ValueError):
    """Bad rasterizer input found by the device-side checks (the message names the argument)."""


FLAG_MESSAGES = {
    F_MEANS: "means contains NaN or Inf",
    F_QUATS: "quats contains NaN or Inf",
    F_QUATS_ZERO: "quats contains a zero-length quaternion",
    F_SCALES: "scales contains NaN or Inf",
    F_SCALES_NEG: "scales must be non-negative",
    F_OPAC: "opacities contains NaN or Inf",
    F_OPAC_RANGE: "opacities must lie in [0, 1]",
    F_COLORS: "colors contains NaN or Inf",
    F_VIEWMAT: "viewmat must be finite with last row (0, 0, 0, 1)",
    F_K: "K must be finite and invertible with positive focal lengths",
}


@wp.func
def _bad3(v: wp.vec3) -> bool:
    return not (wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2]))


@wp.kernel
def validate_gaussians_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    colors: wp.array2d(dtype=float),
    i0: int,
    flags: wp.array(dtype=wp.int32),
):
    """Set the flag of every kind of bad value among Gaussians [i0, i0 + dim). Only ever stores 1,
    so chunks may run concurrently."""
    i = wp.tid() + i0
    if _bad3(means[i]):
        flags[F_MEANS] = 1
    q = quats[i]
    if not (wp.isfinite(q[0]) and wp.isfinite(q[1]) and wp.isfinite(q[2]) and wp.isfinite(q[3])):
        flags[F_QUATS] = 1
    elif wp.dot(q, q) <= 0.0:
        flags[F_QUATS_ZERO] = 1
    s = scales[i]
    if _bad3(s):
        flags[F_SCALES] = 1
    elif s[0] < 0.0 or s[1] < 0.0 or s[2] < 0.0:
        flags[F_SCALES_NEG] = 1
    o = opacities[i]
    if not wp.isfinite(o):
        flags[F_OPAC] = 1
    elif o < 0.0 or o > 1.0:
        flags[F_OPAC_RANGE] = 1
    for k in range(colors.shape[1]):
        if not wp.isfinite(colors[i, k]):
            flags[F_COLORS] = 1


@wp.kernel
def validate_camera_kernel(viewmat: wp.array(dtype=wp.mat44), intrin: wp.array(dtype=wp.mat33),
                           flags: wp.array(dtype=wp.int32)):
    vm = viewmat[0]
    ok = True
    for a in range(4):
        for b in range(4):
            if not wp.isfinite(vm[a, b]):
                ok = False
    if vm[3, 0] != 0.0 or vm[3, 1] != 0.0 or vm[3, 2] != 0.0 or vm[3, 3] != 1.0:
        ok = False
    if not ok:
        flags[F_VIEWMAT] = 1
    K = intrin[0]
    kok = True
    for a in range(3):
        for b in range(3):
            if not wp.isfinite(K[a, b]):
                kok = False
    if kok:
        if not (K[0, 0] > 0.0 and K[1, 1] > 0.0) or wp.abs(wp.determinant(K)) < 1.0e-12:
            kok = False
    if not kok:
        flags[F_K] = 1
