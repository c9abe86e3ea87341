"""Per-tile front-to-back alpha compositing and its hand-written back-to-front adjoint.

Rules (gsplat 1.5 / Inria 3DGS): pixel centres at +0.5; ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``
with ``d = mean2d - pixel``; ``alpha = min(0.999, o exp(-sigma))``; Gaussians with ``sigma < 0`` or
``alpha < 1/255`` are skipped (exp is :func:`.native.exp_neg`, a branch-free polynomial that the
tile kernels vectorise; every kernel here uses it, so they all composite the same values);
compositing stops *before* a Gaussian that would make
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

from .native import bwd_row, bwd_row_pose, exp_neg, fwd_row, lane_sums, prefetch
from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN

#: slack on the log-cutoff so that float rounding never skips a pixel whose alpha reaches 1/255
SIGMA_SLACK = wp.constant(1.0e-3)

#: how many list entries ahead the tile kernels prefetch a Gaussian's record
PREFETCH_AHEAD = wp.constant(2)

#: px added on each side of the exact ellipse spans of the tile kernels (float rounding only)
SPAN_MARGIN = wp.constant(0.05)

vec6 = wp.types.vector(length=6, dtype=wp.float32)


@wp.func
def gauss_sigma(cn: wp.vec3, dx: float, dy: float) -> float:
    """sigma = 0.5 (a dx^2 + c dy^2) + b dx dy for conic (a, b, c) and d = mean2d - pixel."""
    return 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy


@wp.func
def alpha_grads(cn: wp.vec3, o: float, vis: float, v_a: float, dx: float, dy: float) -> vec6:
    """Adjoint of alpha = min(0.999, o exp(-sigma)) for the cotangent v_a: (v_conic a, b, c,
    v_mean2d x, y, v_opacity); zero where the 0.999 clamp is active."""
    if o * vis > ALPHA_MAX:
        return vec6()
    v_sigma = -o * vis * v_a
    return vec6(0.5 * v_sigma * dx * dx, v_sigma * dx * dy, 0.5 * v_sigma * dy * dy,
                v_sigma * (cn[0] * dx + cn[1] * dy), v_sigma * (cn[1] * dx + cn[2] * dy), vis * v_a)


@wp.kernel(enable_backward=False)
def composite_top_id(
    ranges: wp.array2d(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    width: int,
    tile: int,
    tiles_x: int,
    pix0: int,
    out_id: wp.array(dtype=wp.int32),
    out_weight: wp.array(dtype=float),
):
    """Per pixel, the Gaussian with the largest compositing weight alpha * T (-1 if none): the
    forward loop with the same skip and stop rules, keeping an argmax instead of a sum."""
    pix = wp.tid() + pix0
    px = pix % width
    py = pix // width
    t = (py // tile) * tiles_x + px // tile
    fx = float(px) + 0.5
    fy = float(py) + 0.5
    T = float(1.0)
    best = int(-1)
    best_w = float(0.0)
    for j in range(ranges[t, 0], ranges[t, 1]):
        if T <= best_w:
            break  # no later Gaussian can weigh more than the transmittance left
        g = ids[j]
        m = means2d[g]
        sigma = gauss_sigma(conics[g], m[0] - fx, m[1] - fy)
        if sigma < 0.0:
            continue
        alpha = wp.min(ALPHA_MAX, opacities[g] * exp_neg(sigma))
        if alpha < ALPHA_MIN:
            continue
        nT = T * (1.0 - alpha)
        if nT <= T_MIN:
            break
        w = alpha * T
        if w > best_w:
            best_w = w
            best = g
        T = nT
    out_id[pix] = best
    out_weight[pix] = best_w


# Module-level cache: the kernels of each channel count C are generated (and their Warp modules
# compiled) once per process.
@functools.cache
def composite_kernels(C: int):
    """Return ``(forward, backward, count)`` Warp kernels for C colour channels."""
    vecC = wp.types.vector(length=C, dtype=wp.float32)

    @wp.kernel(module="unique", enable_backward=False)
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
            sigma = gauss_sigma(cn, dx, dy)
            if sigma < 0.0:
                continue
            alpha = wp.min(ALPHA_MAX, opacities[g] * exp_neg(sigma))
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

    @wp.kernel(module="unique", enable_backward=False)
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
            sigma = gauss_sigma(cn, dx, dy)
            if sigma < 0.0:
                continue
            o = opacities[g]
            vis = exp_neg(sigma)
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
            gr = alpha_grads(cn, o, vis, v_a, dx, dy)
            wp.atomic_add(v_conics, g, wp.vec3(gr[0], gr[1], gr[2]))
            wp.atomic_add(v_means2d, g, wp.vec2(gr[3], gr[4]))
            wp.atomic_add(v_opacities, g, gr[5])

    @wp.kernel(module="unique", enable_backward=False)
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
            sigma = gauss_sigma(cn, dx, dy)
            if sigma < 0.0:
                continue
            alpha = wp.min(ALPHA_MAX, opacities[g] * exp_neg(sigma))
            if alpha < ALPHA_MIN:
                continue
            nT = T * (1.0 - alpha)
            if nT <= T_MIN:
                break
            T = nT
        evals[pix] = n

    return composite_fwd, composite_bwd, composite_count


@wp.func
def cutoff(o: float) -> float:
    """sigma above which alpha = o exp(-sigma) is surely below 1/255 (with a float-safety slack)."""
    return wp.log(o / ALPHA_MIN) + SIGMA_SLACK


@wp.func
def ellipse_shape(cn: wp.vec3, tcut: float) -> wp.vec4:
    """Per-Gaussian constants of the region sigma <= tcut, computed once in float64 so that the
    per-row spans below need one float32 sqrt: (ry, k1, A, B) with row half-height
    ry = sqrt(2 tcut c0 / det) (1 + 1e-3) + SPAN_MARGIN (huge when det <= 0) and, for a row offset dy, the dx interval
    k1 dy -/+ sqrt(A - B dy^2) (k1 = -c1 / c0, A = 2 tcut / c0, B = det / c0^2; A = -1 when
    c0 <= 0, an empty span)."""
    c0 = wp.float64(cn[0])
    c1 = wp.float64(cn[1])
    c2 = wp.float64(cn[2])
    det = c0 * c2 - c1 * c1
    ry = float(1.0e30)
    if det > wp.float64(0.0):
        ry = wp.float32(wp.sqrt(wp.float64(2.0) * wp.float64(tcut) * c0 / det)) * 1.001 + SPAN_MARGIN
    if c0 <= wp.float64(0.0):
        return wp.vec4(ry, 0.0, -1.0, 0.0)
    ic0 = wp.float64(1.0) / c0
    return wp.vec4(ry, wp.float32(-c1 * ic0), wp.float32(wp.float64(2.0) * wp.float64(tcut) * ic0),
                   wp.float32(det * ic0 * ic0))


@wp.func
def shape_rows(m: wp.vec2, sh: wp.vec4, y0: int, y1: int) -> wp.vec2i:
    """Inclusive pixel rows [lo, hi] within [y0, y1) where sigma <= tcut is possible."""
    ry = sh[0]
    lo = wp.max(y0, int(wp.ceil(wp.clamp(m[1] - 0.5 - ry, float(y0) - 1.0, float(y1)))))
    hi = wp.min(y1 - 1, int(wp.floor(wp.clamp(m[1] - 0.5 + ry, float(y0) - 1.0, float(y1)))))
    return wp.vec2i(lo, hi)


@wp.func
def shape_cols(m: wp.vec2, sh: wp.vec4, dy: float, x0: int, x1: int) -> wp.vec2i:
    """Inclusive pixel columns [lo, hi] within [x0, x1) of row offset dy = my - (py + 0.5) where
    sigma <= tcut is possible; lo > hi when the row misses the ellipse. The margin,
    SPAN_MARGIN px plus 1e-3 of the ellipse's half-width, and the 1e-5 relative tolerance of the
    emptiness test cover the float32 rounding of A - B dy^2; the rounding of sigma itself at a
    pixel is covered by SIGMA_SLACK in tcut."""
    A = sh[2]
    disc = A - sh[3] * dy * dy
    if disc < -1.0e-5 * wp.abs(A):
        return wp.vec2i(x0, x0 - 1)
    hw = wp.sqrt(wp.max(disc, 0.0)) + 1.0e-3 * wp.sqrt(wp.abs(A)) + SPAN_MARGIN
    # dx = mx - (px + 0.5) in [k1 dy - hw, k1 dy + hw]
    lo = wp.max(x0, int(wp.ceil(wp.clamp(m[0] - sh[1] * dy - hw - 0.5, float(x0) - 1.0, float(x1)))))
    hi = wp.min(x1 - 1, int(wp.floor(wp.clamp(m[0] - sh[1] * dy + hw - 0.5, float(x0) - 1.0, float(x1)))))
    return wp.vec2i(lo, hi)


#: lanes of the tile kernels' rows: the tile size they require
TILE_LANES = 16


def bwd_scratch_fields(C: int) -> int:
    """Per-pixel float fields of the tile backward's scratch for C channels (see :mod:`.native`)."""
    return 5 + 2 * C


#: fields of a splat record before the colour: mean x, y, conic a, b, c, opacity, cutoff, depth,
#: then the ellipse shape (ry, k1, A, B) of :func:`ellipse_shape`
REC_HEAD = 12


def splat_record_size(C: int) -> int:
    """Floats per Gaussian in the tile forward's records: ``REC_HEAD + C`` rounded up to a
    multiple of 4 (16 floats, one 64-byte cache line, for C <= 4)."""
    return (REC_HEAD + C + 3) // 4 * 4


@wp.kernel(enable_backward=False)
def splat_records_kernel(
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    depths: wp.array(dtype=float),
    colf: wp.array(dtype=float),
    radii: wp.array(dtype=wp.vec2i),
    C: int,
    RS: int,
    i0: int,
    rec: wp.array(dtype=float),
):
    """Everything the tile forward reads of Gaussian i, packed into ``rec[RS i:]`` (see
    ``REC_HEAD``): one cache line per intersection instead of five arrays, and the cutoff and
    ellipse shape computed once per Gaussian instead of once per tile. Culled Gaussians are
    never binned and get no record. The tile forward and backward read these records."""
    i = wp.tid() + i0
    r = radii[i]
    if r[0] <= 0 and r[1] <= 0:
        return
    m = means2d[i]
    cn = conics[i]
    o = opacities[i]
    tcut = cutoff(o)
    sh = ellipse_shape(cn, tcut)
    b = i * RS
    rec[b + 0] = m[0]
    rec[b + 1] = m[1]
    rec[b + 2] = cn[0]
    rec[b + 3] = cn[1]
    rec[b + 4] = cn[2]
    rec[b + 5] = o
    rec[b + 6] = tcut
    rec[b + 7] = depths[i]
    rec[b + 8] = sh[0]
    rec[b + 9] = sh[1]
    rec[b + 10] = sh[2]
    rec[b + 11] = sh[3]
    for ch in range(C):
        rec[b + REC_HEAD + ch] = colf[i * C + ch]


# Module-level cache: as for composite_kernels.
@functools.cache
def composite_tile_kernels(C: int):
    """Return ``(forward, backward)`` kernels with one thread per 16x16 tile (the CPU variant).

    Per Gaussian the thread visits only the rows where ``sigma <= ln(255 o)`` is possible and
    whose span of such pixels is not empty, and it processes each such row as 16 lanes at once
    (:func:`.native.fwd_row` / :func:`.native.bwd_row`: masks instead of branches, so the CPU
    compiler vectorises the row). Every lane is evaluated with exactly the arithmetic of the
    per-pixel kernels, so both give the same image; the skipped rows hold only pixels those
    kernels would skip after computing alpha < 1/255. Per-pixel state lives in per-tile scratch
    (16 lanes per row, structure of arrays) that the thread owns; the backward sums a Gaussian's
    gradient over the tile before one atomic add. The tile size must be 16 (``TILE_LANES``).
    """
    vecC = wp.types.vector(length=C, dtype=wp.float32)
    NF = bwd_scratch_fields(C)
    NG = 7 + C
    RS = splat_record_size(C)

    @wp.kernel(module="unique", enable_backward=False)
    def composite_fwd_tile(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        rec: wp.array(dtype=float),
        width: int,
        height: int,
        tiles_x: int,
        tile0: int,
        sT: wp.array(dtype=float),
        sD: wp.array(dtype=float),
        sL: wp.array(dtype=wp.int32),
        sC: wp.array(dtype=float),
        live: wp.array(dtype=wp.vec2i),
        out_color: wp.array(dtype=vecC),
        out_depth: wp.array(dtype=float),
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
    ):
        t = wp.tid() + tile0
        x0 = (t % tiles_x) * 16
        y0 = (t // tiles_x) * 16
        x1 = wp.min(x0 + 16, width)
        y1 = wp.min(y0 + 16, height)
        nk = x1 - x0
        start = ranges[t, 0]
        end = ranges[t, 1]
        tb = t * 256
        for q in range(256):
            sT[tb + q] = 1.0
            sD[tb + q] = 0.0
            sL[tb + q] = start - 1
        for q in range(256 * C):
            sC[tb * C + q] = 0.0
        for py in range(y0, y1):
            live[t * 16 + py - y0] = wp.vec2i(x0, x1 - 1)  # columns of row py not saturated yet
        ylo = y0  # rows [ylo, yhi] still hold an unsaturated pixel
        yhi = y1 - 1
        for j in range(start, end):
            if ylo > yhi:
                break  # every pixel of the tile is saturated
            if j + PREFETCH_AHEAD < end:
                prefetch(rec, ids[j + PREFETCH_AHEAD] * RS)
            b = ids[j] * RS
            m = wp.vec2(rec[b + 0], rec[b + 1])
            cn = wp.vec3(rec[b + 2], rec[b + 3], rec[b + 4])
            o = rec[b + 5]
            tcut = rec[b + 6]
            d = rec[b + 7]
            sh = wp.vec4(rec[b + 8], rec[b + 9], rec[b + 10], rec[b + 11])
            rows = shape_rows(m, sh, ylo, yhi + 1)
            for py in range(rows[0], rows[1] + 1):
                r = py - y0
                lv = live[t * 16 + r]
                if lv[0] > lv[1]:
                    continue
                dy = m[1] - (float(py) + 0.5)
                cols = shape_cols(m, sh, dy, lv[0], lv[1] + 1)
                if cols[0] > cols[1]:
                    continue
                nstop = fwd_row(sT, sD, sL, sC, rec, C, t, tb, r, x0, nk, m[0], dy, cn[0], cn[1], cn[2],
                                o, tcut, d, b + REC_HEAD, j)
                if nstop > 0:
                    # shrink the row's live columns, then the tile's live rows
                    lo = lv[0]
                    hi = lv[1]
                    while lo <= hi and sT[tb + 16 * r + lo - x0] < 0.0:
                        lo += 1
                    while hi >= lo and sT[tb + 16 * r + hi - x0] < 0.0:
                        hi -= 1
                    live[t * 16 + r] = wp.vec2i(lo, hi)
                    if lo > hi:
                        while ylo <= yhi and live[t * 16 + ylo - y0][0] > live[t * 16 + ylo - y0][1]:
                            ylo += 1
                        while yhi >= ylo and live[t * 16 + yhi - y0][0] > live[t * 16 + yhi - y0][1]:
                            yhi -= 1
        for py in range(y0, y1):
            for px in range(x0, x1):
                pix = py * width + px
                q = tb + 16 * (py - y0) + px - x0
                out_T[pix] = wp.abs(sT[q])
                out_depth[pix] = sD[q]
                out_last[pix] = sL[q]
                c = vecC()
                for ch in range(C):
                    c[ch] = sC[(t * C + ch) * 256 + q - tb]
                out_color[pix] = c

    @wp.kernel(module="unique", enable_backward=False)
    def composite_bwd_tile(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        rec: wp.array(dtype=float),
        width: int,
        height: int,
        tiles_x: int,
        tile0: int,
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=float),
        v_alpha: wp.array(dtype=float),
        bs: wp.array(dtype=float),
        bl: wp.array(dtype=wp.int32),
        gs: wp.array(dtype=float),
        gout: wp.array(dtype=float),
        row_last: wp.array(dtype=wp.int32),
        v_means2d: wp.array(dtype=wp.vec2),
        v_conics: wp.array(dtype=wp.vec3),
        v_opacities: wp.array(dtype=float),
        v_colors: wp.array(dtype=vecC),
        v_depths: wp.array(dtype=float),
    ):
        t = wp.tid() + tile0
        x0 = (t % tiles_x) * 16
        y0 = (t // tiles_x) * 16
        x1 = wp.min(x0 + 16, width)
        y1 = wp.min(y0 + 16, height)
        nk = x1 - x0
        start = ranges[t, 0]
        tb = t * 256
        fb = t * NF * 256
        for q in range(16 * NG):
            gs[t * NG * 16 + q] = 0.0
        for r in range(y1 - y0):
            row_last[t * 16 + r] = start - 1
        jmax = start - 1
        for q in range(16 * (y1 - y0)):  # rows past the image are never visited
            r = q // 16
            k = q % 16
            bs[fb + 2 * 256 + q] = 0.0
            for ch in range(C):
                bs[fb + (5 + ch) * 256 + q] = 0.0
            if k < nk:
                pix = (y0 + r) * width + x0 + k
                Tf = out_T[pix]
                bs[fb + q] = Tf
                bs[fb + 256 + q] = Tf
                bs[fb + 3 * 256 + q] = v_depth[pix]
                bs[fb + 4 * 256 + q] = v_alpha[pix]
                vc = v_color[pix]
                for ch in range(C):
                    bs[fb + (5 + C + ch) * 256 + q] = vc[ch]
                lp = out_last[pix]
                bl[tb + q] = lp
                row_last[t * 16 + r] = wp.max(row_last[t * 16 + r], lp)
                jmax = wp.max(jmax, lp)
            else:
                bs[fb + q] = 1.0
                bs[fb + 256 + q] = 1.0
                bs[fb + 3 * 256 + q] = 0.0
                bs[fb + 4 * 256 + q] = 0.0
                for ch in range(C):
                    bs[fb + (5 + C + ch) * 256 + q] = 0.0
                bl[tb + q] = start - 1
        for jj in range(jmax - start + 1):
            j = jmax - jj
            if j - PREFETCH_AHEAD >= start:
                prefetch(rec, ids[j - PREFETCH_AHEAD] * RS)
            g = ids[j]
            b = g * RS
            m = wp.vec2(rec[b + 0], rec[b + 1])
            cn = wp.vec3(rec[b + 2], rec[b + 3], rec[b + 4])
            o = rec[b + 5]
            tcut = rec[b + 6]
            d = rec[b + 7]
            sh = wp.vec4(rec[b + 8], rec[b + 9], rec[b + 10], rec[b + 11])
            rows = shape_rows(m, sh, y0, y1)
            hit = int(0)
            for py in range(rows[0], rows[1] + 1):
                r = py - y0
                if j > row_last[t * 16 + r]:
                    continue  # every pixel of the row stopped before j
                dy = m[1] - (float(py) + 0.5)
                cols = shape_cols(m, sh, dy, x0, x1)
                if cols[0] > cols[1]:
                    continue
                hit += bwd_row(bs, bl, gs, rec, C, NG, t, tb, r, x0, nk, m[0], dy, cn[0], cn[1], cn[2],
                               o, tcut, d, b + REC_HEAD, j)
            if hit != 0:
                lane_sums(gs, gout, t, NG)
                gb = t * NG
                g_c = vecC()
                for ch in range(C):
                    g_c[ch] = gout[gb + ch]
                wp.atomic_add(v_colors, g, g_c)
                wp.atomic_add(v_depths, g, gout[gb + C])
                wp.atomic_add(v_conics, g, wp.vec3(gout[gb + C + 1], gout[gb + C + 2], gout[gb + C + 3]))
                wp.atomic_add(v_means2d, g, wp.vec2(gout[gb + C + 4], gout[gb + C + 5]))
                wp.atomic_add(v_opacities, g, gout[gb + C + 6])

    return composite_fwd_tile, composite_bwd_tile


#: per-Gaussian quantities of the pose-only backward's accumulators: depth, conic a, b, c, mean x, y
POSE_NG = 6


# Module-level cache: as for composite_kernels.
@functools.cache
def composite_pose_kernels(C: int):
    """Return ``(pixel, tile)`` pose-only backward kernels for C colour channels.

    They are the adjoints of ``composite_fwd`` / ``composite_fwd_tile`` restricted to what the
    camera's gradient needs: per Gaussian the cotangents of its depth, conic and mean2d (the
    ``POSE_NG`` floats at ``acc[POSE_NG (acc_off + g):]``); colour and opacity gradients are not
    formed. Pixels whose cotangents are all zero (outside a loss mask) are skipped. The tile
    kernel covers the tile rows ``row0, row0 + row_step, ...`` in that order, so a host that gives
    every group of rows its own accumulator gets sums that do not depend on the thread count.
    """
    vecC = wp.types.vector(length=C, dtype=wp.float32)
    NF = bwd_scratch_fields(C)
    RS = splat_record_size(C)
    NGP = POSE_NG

    @wp.kernel(module="unique", enable_backward=False)
    def composite_bwd_pose(
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
        acc_off: int,
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=float),
        v_alpha: wp.array(dtype=float),
        acc: wp.array(dtype=float),
    ):
        pix = wp.tid() + pix0
        px = pix % width
        py = pix // width
        t = (py // tile) * tiles_x + px // tile
        start = ranges[t, 0]
        last = out_last[pix]
        if last < start:
            return
        vc = v_color[pix]
        vd = v_depth[pix]
        va = v_alpha[pix]
        live = int(0)  # a pixel without cotangent adds nothing
        if vd != 0.0 or va != 0.0:
            live = 1
        for ch in range(C):
            if vc[ch] != 0.0:
                live = 1
        if live == 0:
            return
        fx = float(px) + 0.5
        fy = float(py) + 0.5
        T_final = out_T[pix]
        T = T_final
        buf = vecC()
        bufd = float(0.0)
        for jj in range(last - start + 1):
            j = last - jj
            g = ids[j]
            m = means2d[g]
            cn = conics[g]
            dx = m[0] - fx
            dy = m[1] - fy
            sigma = gauss_sigma(cn, dx, dy)
            if sigma < 0.0:
                continue
            o = opacities[g]
            vis = exp_neg(sigma)
            alpha = wp.min(ALPHA_MAX, o * vis)
            if alpha < ALPHA_MIN:
                continue
            ra = 1.0 / (1.0 - alpha)
            T = T * ra
            fac = alpha * T
            c = colors[g]
            d = depths[g]
            v_a = wp.dot(c * T - buf * ra, vc) + (d * T - bufd * ra) * vd + T_final * ra * va
            buf = buf + c * fac
            bufd = bufd + d * fac
            gr = alpha_grads(cn, o, vis, v_a, dx, dy)
            b = (acc_off + g) * NGP
            wp.atomic_add(acc, b + 0, vd * fac)
            wp.atomic_add(acc, b + 1, gr[0])
            wp.atomic_add(acc, b + 2, gr[1])
            wp.atomic_add(acc, b + 3, gr[2])
            wp.atomic_add(acc, b + 4, gr[3])
            wp.atomic_add(acc, b + 5, gr[4])

    @wp.kernel(module="unique", enable_backward=False)
    def composite_bwd_tile_pose(
        ranges: wp.array2d(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        rec: wp.array(dtype=float),
        width: int,
        height: int,
        tiles_x: int,
        row0: int,
        row_step: int,
        acc_off: int,
        out_T: wp.array(dtype=float),
        out_last: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=float),
        v_alpha: wp.array(dtype=float),
        bs: wp.array(dtype=float),
        bl: wp.array(dtype=wp.int32),
        gs: wp.array(dtype=float),
        gout: wp.array(dtype=float),
        row_last: wp.array(dtype=wp.int32),
        acc: wp.array(dtype=float),
    ):
        k_t = wp.tid()
        t = (row0 + row_step * (k_t // tiles_x)) * tiles_x + k_t % tiles_x
        x0 = (t % tiles_x) * 16
        y0 = (t // tiles_x) * 16
        x1 = wp.min(x0 + 16, width)
        y1 = wp.min(y0 + 16, height)
        nk = x1 - x0
        start = ranges[t, 0]
        tb = t * 256
        fb = t * NF * 256
        for q in range(16 * NGP):
            gs[t * NGP * 16 + q] = 0.0
        for r in range(y1 - y0):
            row_last[t * 16 + r] = start - 1
        jmax = start - 1
        for q in range(16 * (y1 - y0)):  # rows past the image are never visited
            r = q // 16
            k = q % 16
            bs[fb + 2 * 256 + q] = 0.0
            for ch in range(C):
                bs[fb + (5 + ch) * 256 + q] = 0.0
            bl[tb + q] = start - 1
            bs[fb + q] = 1.0
            bs[fb + 256 + q] = 1.0
            bs[fb + 3 * 256 + q] = 0.0
            bs[fb + 4 * 256 + q] = 0.0
            for ch in range(C):
                bs[fb + (5 + C + ch) * 256 + q] = 0.0
            if k < nk:
                pix = (y0 + r) * width + x0 + k
                vc = vecC(v_color[pix])
                vd = v_depth[pix]
                va = v_alpha[pix]
                live = int(0)  # a pixel without cotangent stays out of the walk
                if vd != 0.0 or va != 0.0:
                    live = 1
                for ch in range(C):
                    if vc[ch] != 0.0:
                        live = 1
                if live != 0:
                    Tf = out_T[pix]
                    bs[fb + q] = Tf
                    bs[fb + 256 + q] = Tf
                    bs[fb + 3 * 256 + q] = vd
                    bs[fb + 4 * 256 + q] = va
                    for ch in range(C):
                        bs[fb + (5 + C + ch) * 256 + q] = vc[ch]
                    lp = out_last[pix]
                    bl[tb + q] = lp
                    row_last[t * 16 + r] = wp.max(row_last[t * 16 + r], lp)
                    jmax = wp.max(jmax, lp)
        for jj in range(jmax - start + 1):
            j = jmax - jj
            if j - PREFETCH_AHEAD >= start:
                prefetch(rec, ids[j - PREFETCH_AHEAD] * RS)
            g = ids[j]
            b = g * RS
            m = wp.vec2(rec[b + 0], rec[b + 1])
            cn = wp.vec3(rec[b + 2], rec[b + 3], rec[b + 4])
            o = rec[b + 5]
            tcut = rec[b + 6]
            d = rec[b + 7]
            sh = wp.vec4(rec[b + 8], rec[b + 9], rec[b + 10], rec[b + 11])
            rows = shape_rows(m, sh, y0, y1)
            hit = int(0)
            for py in range(rows[0], rows[1] + 1):
                r = py - y0
                if j > row_last[t * 16 + r]:
                    continue  # every pixel of the row stopped before j (or has no cotangent)
                dy = m[1] - (float(py) + 0.5)
                cols = shape_cols(m, sh, dy, x0, x1)
                if cols[0] > cols[1]:
                    continue
                hit += bwd_row_pose(bs, bl, gs, rec, C, NGP, t, tb, r, x0, nk, m[0], dy, cn[0], cn[1], cn[2],
                                    o, tcut, d, b + REC_HEAD, j)
            if hit != 0:
                lane_sums(gs, gout, t, NGP)
                gb = t * NGP
                ab = (acc_off + g) * NGP
                for q in range(NGP):
                    wp.atomic_add(acc, ab + q, gout[gb + q])

    return composite_bwd_pose, composite_bwd_tile_pose
