"""Per-tile front-to-back alpha compositing and its hand-written back-to-front adjoint.

Rules (gsplat 1.5 / Inria 3DGS): pixel centres at +0.5; ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``
with ``d = mean2d - pixel``; ``alpha = min(0.999, o exp(-sigma))``; Gaussians with ``sigma < 0`` or
``alpha < 1/255`` are skipped; compositing stops *before* a Gaussian that would make
``T <= 1e-4``. The forward saves the final transmittance T and the index (into the sorted
intersection list) of the last contributing Gaussian; the backward walks back from it and
recovers T before each Gaussian by dividing by ``1 - alpha``.

Kernels are generated per colour-channel count C (vector types are unrolled by Warp). Each
launch covers a contiguous range of pixel rows, so the host can split a frame over CPU threads.
On the CPU, Warp's atomics are plain adds, so every concurrently running launch writes its
gradients into its own accumulator set.
"""

from __future__ import annotations

import functools

import warp as wp

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN


@functools.cache
def composite_kernels(C: int):
    """Return ``(forward, backward, count)`` Warp kernels for C colour channels."""
    vecC = wp.types.vector(length=C, dtype=wp.float32)

    @wp.kernel(module="unique")
    def composite_fwd(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=vecC),
        depths: wp.array(dtype=float),
        width: int,
        tile: int,
        tiles_x: int,
        pix0: int,
        out_color: wp.array(dtype=vecC),
        out_depth: wp.array(dtype=float),
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
    ):
        pix = wp.tid() + pix0
        px = pix % width
        py = pix // width
        t = (py // tile) * tiles_x + px // tile
        start = ranges[t, 0]
        end = ranges[t, 1]
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        T = float(1.0)
        acc = vecC()
        dep = float(0.0)
        last = start - 1
        for j in range(start, end):
            g = ids[j]
            m = means2d[g]
            cn = conics[g]
            dx = m[0] - fx
            dy = m[1] - fy
            sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
            if sigma < 0.0:
                continue
            alpha = wp.min(ALPHA_MAX, opacities[g] * wp.exp(-sigma))
            if alpha < ALPHA_MIN:
                continue
            nT = T * (1.0 - alpha)
            if nT <= T_MIN:
                break
            w = alpha * T
            acc = acc + colors[g] * w
            dep = dep + depths[g] * w
            T = nT
            last = j
        out_color[pix] = acc
        out_depth[pix] = dep
        out_T[pix] = T
        out_last[pix] = last

    @wp.kernel(module="unique")
    def composite_bwd(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        colors: wp.array(dtype=vecC),
        depths: wp.array(dtype=float),
        width: int,
        tile: int,
        tiles_x: int,
        pix0: int,
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=float),
        v_alpha: wp.array(dtype=float),
        v_means2d: wp.array(dtype=wp.vec2),
        v_conics: wp.array(dtype=wp.vec3),
        v_opacities: wp.array(dtype=float),
        v_colors: wp.array(dtype=vecC),
        v_depths: wp.array(dtype=float),
    ):
        pix = wp.tid() + pix0
        px = pix % width
        py = pix // width
        t = (py // tile) * tiles_x + px // tile
        start = ranges[t, 0]
        last = out_last[pix]
        if last < start:
            return
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        T_final = out_T[pix]
        T = T_final
        vc = v_color[pix]
        vd = v_depth[pix]
        va = v_alpha[pix]
        buf = vecC()
        bufd = float(0.0)
        for jj in range(last - start + 1):
            j = last - jj
            g = ids[j]
            m = means2d[g]
            cn = conics[g]
            dx = m[0] - fx
            dy = m[1] - fy
            sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
            if sigma < 0.0:
                continue
            o = opacities[g]
            vis = wp.exp(-sigma)
            alpha = wp.min(ALPHA_MAX, o * vis)
            if alpha < ALPHA_MIN:
                continue
            ra = 1.0 / (1.0 - alpha)
            T = T * ra
            fac = alpha * T
            c = colors[g]
            d = depths[g]
            wp.atomic_add(v_colors, g, vc * fac)
            wp.atomic_add(v_depths, g, vd * fac)
            v_a = wp.dot(c * T - buf * ra, vc) + (d * T - bufd * ra) * vd + T_final * ra * va
            buf = buf + c * fac
            bufd = bufd + d * fac
            if o * vis <= ALPHA_MAX:
                v_sigma = -o * vis * v_a
                wp.atomic_add(v_conics, g, wp.vec3(0.5 * v_sigma * dx * dx, v_sigma * dx * dy, 0.5 * v_sigma * dy * dy))
                wp.atomic_add(v_means2d, g, wp.vec2(v_sigma * (cn[0] * dx + cn[1] * dy), v_sigma * (cn[1] * dx + cn[2] * dy)))
                wp.atomic_add(v_opacities, g, vis * v_a)

    @wp.kernel(module="unique")
    def composite_count(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        width: int,
        tile: int,
        tiles_x: int,
        evals: wp.array(dtype=wp.int32),
    ):
        """Exact number of Gaussian-pixel evaluations the forward loop performs per pixel."""
        pix = wp.tid()
        px = pix % width
        py = pix // width
        t = (py // tile) * tiles_x + px // tile
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        T = float(1.0)
        n = int(0)
        for j in range(ranges[t, 0], ranges[t, 1]):
            n += 1
            g = ids[j]
            m = means2d[g]
            cn = conics[g]
            dx = m[0] - fx
            dy = m[1] - fy
            sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
            if sigma < 0.0:
                continue
            alpha = wp.min(ALPHA_MAX, opacities[g] * wp.exp(-sigma))
            if alpha < ALPHA_MIN:
                continue
            nT = T * (1.0 - alpha)
            if nT <= T_MIN:
                break
            T = nT
        evals[pix] = n

    return composite_fwd, composite_bwd, composite_count
