"""C++ snippets (``wp.func_native``) of the compositing arithmetic: a branch-free exp and the
per-row work of the 16x16 tile kernels, written so that the CPU compiler vectorises across the 16
pixels of a tile row.

Warp's generated C++ for a per-pixel loop is scalar and branchy (an ``expf`` call, short-circuit
``and`` tests, one statement per operation, array accesses through runtime strides), which LLVM
does not vectorise. Here a tile row is a fixed-length loop over 16 lanes of contiguous scratch,
every test is a mask (``&`` of comparisons, selects instead of branches) and the exp is a
polynomial, so the loop becomes AVX-512 / AVX2 code. The same snippets compile for CUDA through
NVRTC (tests/test_cuda_aot.py).

The arithmetic of sigma, alpha and the blend is written operation by operation as in the Warp
kernels, with floating-point contraction off on the CPU, so the per-pixel kernels (which call
:func:`exp_neg` too) and the tile kernels composite the same values.

Scratch layout of one tile (16 rows x 16 lanes, lanes past the image's right edge are padding):
``tb = tile * 256``; a row's lane k of a per-pixel field f lives at ``(tile * NF + f) * 256 + 16
row + k`` (NF fields per tile).
"""

from __future__ import annotations

import warp as wp

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN

# exp(-s) for s in [0, 16): s = n + 0.5 + g with |g| <= 0.5; exp(-s) = e^-0.5 * P8(g) * prod of e^-(2^i)
# over the set bits of n (selects, no bit casts, so it vectorises and compiles for NVRTC as is);
# clamped to [0, 15.99] (e^-16 * 0.999 < 1/255: those alphas are skipped anyway). Max relative
# error 2.2e-7 (float32 expf: 6e-8), measured against float64 on [0, 6].
_EXP_NEG = r"""
    auto spl_exp_neg = [](float s_) -> float {
        float s = s_ < 0.0f ? 0.0f : (s_ > 15.99f ? 15.99f : s_);
        int n = (int)s;
        float g = s - (float)n;
        g = g - 0.5f;
        float p = g * 2.48015873015873e-05f;
        p = p + -0.0001984126984126984f; p = p * g;
        p = p + 0.001388888888888889f; p = p * g;
        p = p + -0.008333333333333333f; p = p * g;
        p = p + 0.041666666666666664f; p = p * g;
        p = p + -0.16666666666666666f; p = p * g;
        p = p + 0.5f; p = p * g;
        p = p + -1.0f; p = p * g;
        p = p + 1.0f;
        float b1 = (n & 1) ? 0.36787944117144233f : 1.0f;
        float b2 = (n & 2) ? 0.1353352832366127f : 1.0f;
        float b4 = (n & 4) ? 0.01831563888873418f : 1.0f;
        float b8 = (n & 8) ? 0.00033546262790251185f : 1.0f;
        float e = 0.6065306597126334f * p;
        e = e * (b1 * b2);
        return e * (b4 * b8);
    };
"""

# floating-point contraction (a * b + c -> fma) would make the C++ differ from Warp's one
# statement per operation code; NVRTC contracts anyway, the CUDA path does not compare bitwise.
_NO_CONTRACT = r"""
#if defined(__clang__) && !defined(__CUDACC__)
#pragma clang fp contract(off)
#endif
"""

_CONSTS = f"""
    const float spl_alpha_min = {float(ALPHA_MIN)!r}f;
    const float spl_alpha_max = {float(ALPHA_MAX)!r}f;
    const float spl_t_min = {float(T_MIN)!r}f;
"""


@wp.func_native("{" + _NO_CONTRACT + _EXP_NEG + "    return spl_exp_neg(s);\n}")
def exp_neg(s: float) -> float:
    """exp(-s) for the compositing alpha, s >= 0 (clamped to [0, 15.99]); relative error <= 2.2e-7."""
    ...


_PREFETCH = r"""{
#if !defined(__CUDACC__)
    __builtin_prefetch(a.data + i);
#endif
}
"""


@wp.func_native(_PREFETCH)
def prefetch(a: wp.array(dtype=float), i: int):
    """Hint the CPU to fetch the cache line of ``a[i]`` (a no-op on CUDA). The tile kernels read
    the next Gaussians' records this way: a record's first load is otherwise a cache miss that
    stalls the tile's thread (about a sixth of the forward's time on the heavy benchmark scene)."""
    ...


_FWD_ROW = "{" + _NO_CONTRACT + _EXP_NEG + _CONSTS + r"""
    const int rb = tb + 16 * r;
    float* T = sT.data + rb;
    float* D = sD.data + rb;
    int* L = sL.data + rb;
    float w[16];
    int nstop = 0;
    for (int k = 0; k < 16; ++k) {
        float dx = mx - ((float)(x0 + k) + 0.5f);
        float sigma = 0.5f * (cn0 * dx * dx + cn2 * dy * dy) + cn1 * dx * dy;
        float oe = o * spl_exp_neg(sigma);
        float alpha = spl_alpha_max < oe ? spl_alpha_max : oe;
        float Tk = T[k];
        bool valid = (k < nk) & (Tk > 0.0f) & (sigma >= 0.0f) & (sigma <= tcut) & (alpha >= spl_alpha_min);
        float nT = Tk * (1.0f - alpha);
        bool stop = valid & (nT <= spl_t_min);
        bool contrib = valid & !stop;
        float wk = contrib ? alpha * Tk : 0.0f;
        w[k] = wk;
        T[k] = contrib ? nT : (stop ? -Tk : Tk);
        L[k] = contrib ? j : L[k];
        D[k] = D[k] + d * wk;
        nstop += stop ? 1 : 0;
    }
    for (int ch = 0; ch < C; ++ch) {
        float* S = sC.data + (t * C + ch) * 256 + 16 * r;
        float cv = colf.data[cb + ch];
        for (int k = 0; k < 16; ++k)
            S[k] = S[k] + cv * w[k];
    }
    return nstop;
}
"""


@wp.func_native(_FWD_ROW)
def fwd_row(sT: wp.array(dtype=float), sD: wp.array(dtype=float), sL: wp.array(dtype=wp.int32),
            sC: wp.array(dtype=float), colf: wp.array(dtype=float), C: int, t: int, tb: int, r: int,
            x0: int, nk: int, mx: float, dy: float, cn0: float, cn1: float, cn2: float, o: float,
            tcut: float, d: float, cb: int, j: int) -> int:
    """Blend a Gaussian (sorted index j, colour at ``colf[cb:cb + C]``) into row r of tile t (lanes
    k < nk are pixels x0 + k; dy = my - (py + 0.5)); per-lane state T (negated once the pixel
    stopped), D, L and C colour fields; returns how many pixels of the row stopped at it."""
    ...


# Backward scratch fields per tile: 0 T (running, recovered back to front), 1 T_final, 2 bufd,
# 3 v_depth, 4 v_alpha, 5 .. 5+C-1 buf, 5+C .. 5+2C-1 v_color; ints: the last index per lane.
# Per-tile gradient sums of the current Gaussian, 16 lanes each (NG = 7 + C quantities): C colour,
# depth, conic a, b, c, mean x, y, opacity; :func:`lane_sums` reduces them once per Gaussian.
_BWD_ROW = "{" + _NO_CONTRACT + _EXP_NEG + _CONSTS + r"""
    const int NF = 5 + 2 * C;
    const int rb = 16 * r;
    float* Ts = bs.data + (t * NF + 0) * 256 + rb;
    const float* Tf = bs.data + (t * NF + 1) * 256 + rb;
    float* Bd = bs.data + (t * NF + 2) * 256 + rb;
    const float* Vd = bs.data + (t * NF + 3) * 256 + rb;
    const float* Va = bs.data + (t * NF + 4) * 256 + rb;
    const int* L = bl.data + tb + rb;
    float T_[16], f_[16], ra_[16], dx_[16], vis_[16], vdot[16];
    float gd[16], gcn0[16], gcn1[16], gcn2[16], gm0[16], gm1[16], go[16];
    bool vl[16];
    int hits = 0;
    for (int k = 0; k < 16; ++k) {
        float dx = mx - ((float)(x0 + k) + 0.5f);
        float sigma = 0.5f * (cn0 * dx * dx + cn2 * dy * dy) + cn1 * dx * dy;
        float vis = spl_exp_neg(sigma);
        float alpha = spl_alpha_max < o * vis ? spl_alpha_max : o * vis;
        bool valid = (k < nk) & (j <= L[k]) & (sigma >= 0.0f) & (sigma <= tcut) & (alpha >= spl_alpha_min);
        float ra = 1.0f / (1.0f - alpha);
        float T = Ts[k] * ra;
        vl[k] = valid;
        dx_[k] = dx;
        vis_[k] = vis;
        ra_[k] = ra;
        T_[k] = T;
        f_[k] = alpha * T;
        vdot[k] = 0.0f;
        Ts[k] = valid ? T : Ts[k];
        hits += valid ? 1 : 0;
    }
    if (hits == 0)
        return 0;
    for (int ch = 0; ch < C; ++ch) {
        float* B = bs.data + (t * NF + 5 + ch) * 256 + rb;
        const float* Vc = bs.data + (t * NF + 5 + C + ch) * 256 + rb;
        float cv = colf.data[cb + ch];
        float gc[16];
        for (int k = 0; k < 16; ++k) {
            float b = B[k];
            vdot[k] = vdot[k] + (cv * T_[k] - b * ra_[k]) * Vc[k];
            B[k] = vl[k] ? b + cv * f_[k] : b;
            gc[k] = vl[k] ? Vc[k] * f_[k] : 0.0f;
        }
        float* A = gs.data + (t * NG + ch) * 16;
        for (int k = 0; k < 16; ++k) A[k] = A[k] + gc[k];
    }
    for (int k = 0; k < 16; ++k) {
        float dx = dx_[k];
        float vis = vis_[k];
        float bd = Bd[k];
        float v_a = vdot[k] + (d * T_[k] - bd * ra_[k]) * Vd[k] + Tf[k] * ra_[k] * Va[k];
        Bd[k] = vl[k] ? bd + d * f_[k] : bd;
        gd[k] = vl[k] ? Vd[k] * f_[k] : 0.0f;
        bool vs = vl[k] & !(o * vis > spl_alpha_max);
        float v_sigma = -o * vis * v_a;
        gcn0[k] = vs ? 0.5f * v_sigma * dx * dx : 0.0f;
        gcn1[k] = vs ? v_sigma * dx * dy : 0.0f;
        gcn2[k] = vs ? 0.5f * v_sigma * dy * dy : 0.0f;
        gm0[k] = vs ? v_sigma * (cn0 * dx + cn1 * dy) : 0.0f;
        gm1[k] = vs ? v_sigma * (cn1 * dx + cn2 * dy) : 0.0f;
        go[k] = vs ? vis * v_a : 0.0f;
    }
    float* A = gs.data + (t * NG + C) * 16;
    for (int k = 0; k < 16; ++k) A[k] = A[k] + gd[k];
    for (int k = 0; k < 16; ++k) A[16 + k] = A[16 + k] + gcn0[k];
    for (int k = 0; k < 16; ++k) A[32 + k] = A[32 + k] + gcn1[k];
    for (int k = 0; k < 16; ++k) A[48 + k] = A[48 + k] + gcn2[k];
    for (int k = 0; k < 16; ++k) A[64 + k] = A[64 + k] + gm0[k];
    for (int k = 0; k < 16; ++k) A[80 + k] = A[80 + k] + gm1[k];
    for (int k = 0; k < 16; ++k) A[96 + k] = A[96 + k] + go[k];
    return hits;
}
"""


@wp.func_native(_BWD_ROW)
def bwd_row(bs: wp.array(dtype=float), bl: wp.array(dtype=wp.int32), gs: wp.array(dtype=float),
            colf: wp.array(dtype=float), C: int, NG: int, t: int, tb: int, r: int, x0: int, nk: int,
            mx: float, dy: float, cn0: float, cn1: float, cn2: float, o: float, tcut: float, d: float,
            cb: int, j: int) -> int:
    """Adjoint of :func:`fwd_row` for a Gaussian (sorted index j, colour at ``colf[cb:cb + C]``) on
    row r of tile t, walking back to front: recovers T before it per lane, updates the suffix sums
    buf, and adds the row's per-lane gradient sums into gs[16 t NG:]; returns how many lanes it
    contributed to."""
    ...


# The pose-only adjoint (:func:`bwd_row_pose`) needs what reaches the camera: per Gaussian the
# depth, conic and mean2d cotangents (NG = 6 quantities: depth, conic a, b, c, mean x, y); no
# colour or opacity sums. The colour enters alpha's cotangent only through
# sum_ch (c_ch T - buf_ch / (1 - alpha)) v_ch, and since a pixel's v_ch is fixed, the C suffix
# sums buf_ch collapse into one, bv = sum_ch buf_ch v_ch, kept in scratch field 5 (the first buf).
_BWD_ROW_POSE = "{" + _NO_CONTRACT + _EXP_NEG + _CONSTS + r"""
    const int NF = 5 + 2 * C;
    const int rb = 16 * r;
    float* Ts = bs.data + (t * NF + 0) * 256 + rb;
    const float* Tf = bs.data + (t * NF + 1) * 256 + rb;
    float* Bd = bs.data + (t * NF + 2) * 256 + rb;
    const float* Vd = bs.data + (t * NF + 3) * 256 + rb;
    const float* Va = bs.data + (t * NF + 4) * 256 + rb;
    float* Bv = bs.data + (t * NF + 5) * 256 + rb;
    const int* L = bl.data + tb + rb;
    float T_[16], f_[16], ra_[16], dx_[16], vis_[16], cv_[16];
    float gd[16], gcn0[16], gcn1[16], gcn2[16], gm0[16], gm1[16];
    bool vl[16];
    int hits = 0;
    for (int k = 0; k < 16; ++k) {
        float dx = mx - ((float)(x0 + k) + 0.5f);
        float sigma = 0.5f * (cn0 * dx * dx + cn2 * dy * dy) + cn1 * dx * dy;
        float vis = spl_exp_neg(sigma);
        float alpha = spl_alpha_max < o * vis ? spl_alpha_max : o * vis;
        bool valid = (k < nk) & (j <= L[k]) & (sigma >= 0.0f) & (sigma <= tcut) & (alpha >= spl_alpha_min);
        float ra = 1.0f / (1.0f - alpha);
        float T = Ts[k] * ra;
        vl[k] = valid;
        dx_[k] = dx;
        vis_[k] = vis;
        ra_[k] = ra;
        T_[k] = T;
        f_[k] = alpha * T;
        cv_[k] = 0.0f;
        Ts[k] = valid ? T : Ts[k];
        hits += valid ? 1 : 0;
    }
    if (hits == 0)
        return 0;
    for (int ch = 0; ch < C; ++ch) {
        const float* Vc = bs.data + (t * NF + 5 + C + ch) * 256 + rb;
        float cv = colf.data[cb + ch];
        for (int k = 0; k < 16; ++k)
            cv_[k] = cv_[k] + cv * Vc[k];
    }
    for (int k = 0; k < 16; ++k) {
        float dx = dx_[k];
        float vis = vis_[k];
        float bd = Bd[k];
        float bv = Bv[k];
        float v_a = (cv_[k] * T_[k] - bv * ra_[k]) + (d * T_[k] - bd * ra_[k]) * Vd[k] + Tf[k] * ra_[k] * Va[k];
        Bv[k] = vl[k] ? bv + cv_[k] * f_[k] : bv;
        Bd[k] = vl[k] ? bd + d * f_[k] : bd;
        gd[k] = vl[k] ? Vd[k] * f_[k] : 0.0f;
        bool vs = vl[k] & !(o * vis > spl_alpha_max);
        float v_sigma = -o * vis * v_a;
        gcn0[k] = vs ? 0.5f * v_sigma * dx * dx : 0.0f;
        gcn1[k] = vs ? v_sigma * dx * dy : 0.0f;
        gcn2[k] = vs ? 0.5f * v_sigma * dy * dy : 0.0f;
        gm0[k] = vs ? v_sigma * (cn0 * dx + cn1 * dy) : 0.0f;
        gm1[k] = vs ? v_sigma * (cn1 * dx + cn2 * dy) : 0.0f;
    }
    float* A = gs.data + t * NG * 16;
    for (int k = 0; k < 16; ++k) A[k] = A[k] + gd[k];
    for (int k = 0; k < 16; ++k) A[16 + k] = A[16 + k] + gcn0[k];
    for (int k = 0; k < 16; ++k) A[32 + k] = A[32 + k] + gcn1[k];
    for (int k = 0; k < 16; ++k) A[48 + k] = A[48 + k] + gcn2[k];
    for (int k = 0; k < 16; ++k) A[64 + k] = A[64 + k] + gm0[k];
    for (int k = 0; k < 16; ++k) A[80 + k] = A[80 + k] + gm1[k];
    return hits;
}
"""


@wp.func_native(_BWD_ROW_POSE)
def bwd_row_pose(bs: wp.array(dtype=float), bl: wp.array(dtype=wp.int32), gs: wp.array(dtype=float),
                 colf: wp.array(dtype=float), C: int, NG: int, t: int, tb: int, r: int, x0: int, nk: int,
                 mx: float, dy: float, cn0: float, cn1: float, cn2: float, o: float, tcut: float, d: float,
                 cb: int, j: int) -> int:
    """:func:`bwd_row` for the pose-only backward: the same per-lane walk back to front, with one
    colour suffix sum (the colour suffix sums dotted with the pixel's colour cotangent, field 5)
    instead of C; adds only the depth, conic and mean2d sums of the Gaussian, at quantities 0..5
    of gs[16 t NG:] (NG = 6)."""
    ...


_LANE_SUMS = r"""{
    float* A = gs.data + t * NG * 16;
    for (int q = 0; q < NG; ++q) {
        float a[16];
        for (int k = 0; k < 16; ++k) { a[k] = A[16 * q + k]; A[16 * q + k] = 0.0f; }
        for (int k = 0; k < 8; ++k) a[k] = a[k] + a[k + 8];
        for (int k = 0; k < 4; ++k) a[k] = a[k] + a[k + 4];
        a[0] = a[0] + a[2]; a[1] = a[1] + a[3];
        gout.data[t * NG + q] = a[0] + a[1];
    }
}
"""


@wp.func_native(_LANE_SUMS)
def lane_sums(gs: wp.array(dtype=float), gout: wp.array(dtype=float), t: int, NG: int):
    """gout[t NG + q] = the 16 lanes of gs's quantity q summed in a fixed tree order; zeroes gs's lanes."""
    ...
