"""gsplat-style differentiable rasterization of 3-D Gaussians, in JAX over the Warp kernels.

``rasterize`` works eagerly, under ``jax.jit`` and under ``jax.grad``: the Warp forward and the
hand-written Warp backward are bound with ``wp.jax_callable`` (an XLA FFI call on CPU and CUDA,
zero-copy) and glued together with ``jax.custom_vjp``.
"""
# NOTE: no ``from __future__ import annotations`` here: wp.jax_callable reads the Warp type
# annotations of the callback functions at definition time.

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp

from splatsearch.kernels import pipeline as _pl

wp.config.quiet = True
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
#: what :func:`rasterize`'s backward differentiates: everything, or the camera pose alone
DIFFERENTIABLE = ("all", "viewmat")
#: compositing kernels; passed to the Warp callbacks as their index + 1 (0: the default)
_COMPOSITES = ("tile", "pixel")


def _composite_arg(code: int):
    return None if code == 0 else _COMPOSITES[code - 1]


class RasterOutput(NamedTuple):
    """Result of :func:`rasterize`. Leading camera axis present when several cameras are given.

    Attributes:
        image: (..., H, W, C) composited colours (background included), or None in "D"/"ED" mode.
        depth: (..., H, W, 1) z-depth in metres, "D" (sum w z) or "ED" (D / alpha); None in "RGB" mode.
            Each Gaussian counts as the point at its distance along the pixel's ray (z = distance
            x the ray's z per unit length), and Gaussians composite in order of that distance.
        alpha: (..., H, W, 1) accumulated opacity, 1 - T.
        meta: dict with ``radii`` (..., N, 2) int32 pixel radii (0 = culled), ``n_isect`` (...,)
            int32 tile intersections, ``width``, ``height``, ``tile_size``.
    """

    image: jax.Array | None
    depth: jax.Array | None
    alpha: jax.Array
    meta: dict


def _quiet_ffi_input_errors() -> None:
    """Warp's FFI wrapper prints the full traceback of any exception raised inside a callback, and
    only then does JAX raise its own error. For a failed input check the message is all the user
    needs, so those tracebacks are dropped (any other exception still prints its traceback). This
    reaches into Warp's private FFI module; if that moves, the traceback simply prints again."""
    import builtins

    try:
        from warp._src.jax import ffi as wffi
    except ImportError:
        return
    if getattr(wffi, "_splatsearch_quiet", False):
        return

    def _print(*args, **kwargs):
        text = args[0] if len(args) == 1 and isinstance(args[0], str) else ""
        if text.startswith("Traceback") and f"{_pl.InputValueError.__name__}: " in text:
            return
        builtins.print(*args, **kwargs)

    wffi.print = _print
    wffi._splatsearch_quiet = True


_quiet_ffi_input_errors()


# --------------------------------------------------------------------------------------------
# Warp callbacks, one pair per colour-channel count
# --------------------------------------------------------------------------------------------

# Module-level cache: one pair of jax_callable wrappers per channel count C, built on first use.
@functools.cache
def _callables(C: int):
    vecC = wp.types.vector(length=C, dtype=wp.float32)

    def fwd(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=wp.float32),
        colors: wp.array(dtype=vecC),
        viewmat: wp.array(dtype=wp.mat44),
        K: wp.array(dtype=wp.mat33),
        width: int,
        height: int,
        near: float,
        far: float,
        eps2d: float,
        validate: int,
        composite: int,
        threads: int,
        out_color: wp.array(dtype=vecC),
        out_depth: wp.array(dtype=wp.float32),
        out_T: wp.array(dtype=wp.float32),
        out_last: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=wp.float32),
        radii: wp.array(dtype=wp.vec2i),
        n_isect: wp.array(dtype=wp.int32),
        handle: wp.array(dtype=wp.int32),
    ):
        _pl.rasterize_forward(means, quats, scales, opacities, colors, viewmat, K, width, height,
                              near, far, eps2d, out_color, out_depth, out_T, out_last, means2d,
                              conics, depths, radii, n_isect, handle, validate=bool(validate),
                              composite=_composite_arg(composite), threads=threads or None)

    def bwd(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=wp.float32),
        colors: wp.array(dtype=vecC),
        viewmat: wp.array(dtype=wp.mat44),
        K: wp.array(dtype=wp.mat33),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=wp.float32),
        radii: wp.array(dtype=wp.vec2i),
        out_T: wp.array(dtype=wp.float32),
        out_last: wp.array(dtype=wp.int32),
        handle: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=wp.float32),
        v_alpha: wp.array(dtype=wp.float32),
        width: int,
        height: int,
        eps2d: float,
        composite: int,
        threads: int,
        v_means: wp.array(dtype=wp.vec3),
        v_quats: wp.array(dtype=wp.vec4),
        v_scales: wp.array(dtype=wp.vec3),
        v_opacities: wp.array(dtype=wp.float32),
        v_colors: wp.array(dtype=vecC),
        v_viewmat: wp.array(dtype=wp.float32),
    ):
        h = handle.numpy()
        _pl.rasterize_backward(means, quats, scales, opacities, colors, viewmat, K, width, height,
                               eps2d, means2d, conics, depths, radii, out_T, out_last,
                               (int(h[0]), int(h[1])), v_color, v_depth, v_alpha, v_means, v_quats,
                               v_scales, v_opacities, v_colors, v_viewmat,
                               composite=_composite_arg(composite), threads=threads or None)

    def bwd_pose(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=wp.float32),
        colors: wp.array(dtype=vecC),
        viewmat: wp.array(dtype=wp.mat44),
        K: wp.array(dtype=wp.mat33),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=wp.float32),
        radii: wp.array(dtype=wp.vec2i),
        out_T: wp.array(dtype=wp.float32),
        out_last: wp.array(dtype=wp.int32),
        handle: wp.array(dtype=wp.int32),
        v_color: wp.array(dtype=vecC),
        v_depth: wp.array(dtype=wp.float32),
        v_alpha: wp.array(dtype=wp.float32),
        width: int,
        height: int,
        composite: int,
        threads: int,
        v_viewmat: wp.array(dtype=wp.float32),
    ):
        h = handle.numpy()
        _pl.rasterize_backward_pose(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                    means2d, conics, depths, radii, out_T, out_last, (int(h[0]), int(h[1])),
                                    v_color, v_depth, v_alpha, v_viewmat, composite=_composite_arg(composite),
                                    threads=threads or None)

    mode = wp.JaxCallableGraphMode.NONE  # the forward reads the intersection count on the host
    return (wp.jax_callable(fwd, num_outputs=10, graph_mode=mode, vmap_method="sequential"),
            wp.jax_callable(bwd, num_outputs=6, graph_mode=mode, vmap_method="sequential"),
            wp.jax_callable(bwd_pose, num_outputs=1, graph_mode=mode, vmap_method="sequential"))


# --------------------------------------------------------------------------------------------
# custom_vjp core: one camera, full parameters
# --------------------------------------------------------------------------------------------

class _Cfg(NamedTuple):
    width: int
    height: int
    near: float
    far: float
    eps2d: float
    validate: bool
    composite: int = 0  # 0: default, else index into _COMPOSITES + 1
    threads: int = 0  # 0: default
    pose_only: bool = False  # differentiable="viewmat": the backward forms the viewmat gradient only


def _fwd_call(cfg: _Cfg, means, quats, scales, opacities, colors, viewmat, K):
    N, C = colors.shape
    HW = cfg.width * cfg.height
    fwd = _callables(C)[0]
    outs = fwd(means, quats, scales, opacities, colors, viewmat[None], K[None],
               cfg.width, cfg.height, cfg.near, cfg.far, cfg.eps2d, int(cfg.validate), cfg.composite, cfg.threads,
               output_dims={"out_color": (HW,), "out_depth": (HW,), "out_T": (HW,), "out_last": (HW,),
                            "means2d": (N,), "conics": (N,), "depths": (N,), "radii": (N,),
                            "n_isect": (1,), "handle": (2,)})
    return outs


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _core(cfg: _Cfg, means, quats, scales, opacities, colors, viewmat, K):
    return _core_fwd(cfg, means, quats, scales, opacities, colors, viewmat, K)[0]


def _shape_outputs(cfg: _Cfg, C: int, color, depth, T, radii, n_isect):
    H, W = cfg.height, cfg.width
    return (color.reshape(H, W, C), depth.reshape(H, W, 1), (1.0 - T).reshape(H, W, 1),
            radii.reshape(-1, 2), n_isect.reshape(()))


def _core_fwd(cfg: _Cfg, means, quats, scales, opacities, colors, viewmat, K):
    C = colors.shape[1]
    color, depth, T, last, means2d, conics, depths, radii, n_isect, handle = _fwd_call(
        cfg, means, quats, scales, opacities, colors, viewmat, K)
    out = _shape_outputs(cfg, C, color, depth, T, radii, n_isect)
    res = (means, quats, scales, opacities, colors, viewmat, K, means2d, conics, depths, radii, T,
           last, handle)
    return out, res


def _core_bwd(cfg: _Cfg, res, cts):
    (means, quats, scales, opacities, colors, viewmat, K, means2d, conics, depths, radii, T, last,
     handle) = res
    v_color, v_depth, v_alpha = cts[0], cts[1], cts[2]
    N, C = colors.shape
    HW = cfg.width * cfg.height
    v_color = v_color.reshape(HW, C).astype(jnp.float32)
    v_depth = v_depth.reshape(HW).astype(jnp.float32)
    v_alpha = v_alpha.reshape(HW).astype(jnp.float32)
    if cfg.pose_only:
        v_vm = _callables(C)[2](
            means, quats, scales, opacities, colors, viewmat[None], K[None], means2d, conics, depths, radii, T, last,
            handle, v_color, v_depth, v_alpha, cfg.width, cfg.height, cfg.composite, cfg.threads,
            output_dims={"v_viewmat": (16,)})
        v_vm = v_vm[0] if isinstance(v_vm, (list, tuple)) else v_vm
        # the Gaussians are constants here (unused zeros vanish under jit)
        return (jnp.zeros_like(means), jnp.zeros_like(quats), jnp.zeros_like(scales), jnp.zeros_like(opacities),
                jnp.zeros_like(colors), v_vm.reshape(4, 4), jnp.zeros_like(K))
    bwd = _callables(C)[1]
    v_means, v_quats, v_scales, v_opac, v_colors, v_vm = bwd(
        means, quats, scales, opacities, colors, viewmat[None], K[None], means2d, conics, depths,
        radii, T, last, handle, v_color, v_depth, v_alpha, cfg.width, cfg.height, cfg.eps2d, cfg.composite, cfg.threads,
        output_dims={"v_means": (N,), "v_quats": (N,), "v_scales": (N,), "v_opacities": (N,),
                     "v_colors": (N,), "v_viewmat": (16,)})
    return (v_means, v_quats, v_scales, v_opac, v_colors, v_vm.reshape(4, 4), jnp.zeros_like(K))


_core.defvjp(_core_fwd, _core_bwd)


# --------------------------------------------------------------------------------------------
# input checking
# --------------------------------------------------------------------------------------------

def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_float(name: str, x, shape_desc: str, ndim: int | None = None):
    if x is None:
        raise ValueError(f"{name} must be an array of shape {shape_desc}, got None")
    dtype = getattr(x, "dtype", None)
    if dtype is None:
        x = np.asarray(x)
        dtype = x.dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"{name} must have a floating dtype (shape {shape_desc}), got {dtype}")
    x = jnp.asarray(x, dtype=jnp.float32)
    if ndim is not None and x.ndim != ndim:
        raise ValueError(f"{name} must have shape {shape_desc}, got {tuple(x.shape)}")
    return x


def _check_values(name: str, x, *, nonneg: bool = False, unit: bool = False) -> None:
    if not _is_concrete(x):
        return
    a = np.asarray(x)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf")
    if nonneg and np.any(a < 0):
        raise ValueError(f"{name} must be non-negative (min {a.min():g})")
    if unit and a.size and (a.min() < 0 or a.max() > 1):
        raise ValueError(f"{name} must lie in [0, 1] (got range [{a.min():g}, {a.max():g}])")


def _check_run_options(composite, threads) -> tuple[int, int]:
    """(composite code, threads code) for :class:`_Cfg`; 0 means "the default"."""
    if composite is not None and composite not in _COMPOSITES:
        raise ValueError(f"composite must be one of {_COMPOSITES} or None, got {composite!r}")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1):
        raise ValueError(f"threads must be a positive integer or None, got {threads!r}")
    return (0 if composite is None else _COMPOSITES.index(composite) + 1), (0 if threads is None else int(threads))


def _check_camera(viewmat, K) -> None:
    if _is_concrete(viewmat):
        v = np.asarray(viewmat)
        if not np.all(np.isfinite(v)):
            raise ValueError("viewmat contains NaN or Inf")
        if not np.allclose(v[..., 3, :], [0, 0, 0, 1]):
            raise ValueError("viewmat must be a world-to-camera 4x4 with last row (0, 0, 0, 1)")
    if _is_concrete(K):
        k = np.asarray(K, dtype=np.float64)
        if not np.all(np.isfinite(k)):
            raise ValueError("K contains NaN or Inf")
        det = np.linalg.det(k)
        if np.any(np.abs(det) < 1e-12) or np.any(k[..., 0, 0] <= 0) or np.any(k[..., 1, 1] <= 0):
            raise ValueError("K must be invertible with positive focal lengths fx, fy")


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------

def rasterize(
    means: Any,
    quats: Any,
    scales: Any,
    opacities: Any,
    colors: Any,
    viewmat: Any,
    K: Any,
    width: int,
    height: int,
    render_mode: str = "RGB+D",
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    backgrounds: Any = None,
    validate: bool = True,
    composite: str | None = None,
    threads: int | None = None,
    differentiable: str = "all",
) -> RasterOutput:
    """Render 3-D Gaussians with the tile rasterizer (gsplat 1.5 / Inria 3DGS rules).

    Args:
        means: (N, 3) world positions in metres.
        quats: (N, 4) rotations as (w, x, y, z), normalised inside; None for isotropic Gaussians.
        scales: (N, 3) standard deviations in metres (non-negative), or (N,) / (N, 1) for
            isotropic Gaussians (one scale per Gaussian).
        opacities: (N,) opacities in [0, 1].
        colors: (N, C) per-Gaussian features (RGB in [0, 1] for C = 3; any C >= 1 works); may be
            None in the depth-only modes "D" and "ED", which do not composite colours.
        viewmat: (4, 4) world-to-camera matrix (OpenCV frame: x right, y down, z forward), or
            (B, 4, 4) for B cameras.
        K: (3, 3) pinhole intrinsics in pixels, or (B, 3, 3); pixel centres at +0.5.
        width, height: image size in pixels (static).
        render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED". "D" is the alpha-weighted depth
            sum, "ED" the expected depth D / alpha (see :class:`RasterOutput`).
        near_plane, far_plane: camera-depth culling range in metres.
        eps2d: low-pass added to the 2-D covariance diagonal, in px^2.
        backgrounds: optional (C,) or (B, C) colour composited behind the Gaussians.
        validate: check values (NaN/Inf, ranges, K) on the device when inputs are traced.
        composite: compositing kernel, "tile" (one thread per 16x16 tile; the rows each Gaussian's
            ellipse reaches are processed as 16 SIMD lanes; the CPU default) or "pixel" (one thread per pixel; the CUDA default). Both give
            the same images and gradients. None: the default, which ``SPLATSEARCH_COMPOSITE``
            may set (see :mod:`splatsearch.kernels.config`).
        threads: CPU worker threads (>= 1); None: the usable cores, or ``SPLATSEARCH_THREADS``.
            Ignored on CUDA.
        differentiable: "all" (gradients reach every input) or "viewmat": pose tracking against
            a frozen map. The Gaussians' parameters are then constants (zero gradient, like
            ``jax.lax.stop_gradient``) and the backward forms only the viewmat gradient: no
            per-Gaussian gradient arrays, pixels whose cotangents are all zero are skipped, and
            on the CPU the result is bitwise the same for any ``threads``. It equals the "all"
            backward's viewmat gradient up to float summation order.

    Returns:
        :class:`RasterOutput` ``(image, depth, alpha, meta)``; see its docstring for shapes.

    Raises:
        ValueError: naming the argument, for wrong shapes or dtypes, NaN or Inf, negative scales,
            opacities outside [0, 1], a non-positive image size, or a non-invertible K. Under
            ``jax.jit`` value errors surface as a ``JaxRuntimeError`` carrying the same message.

    Gradients (``jax.grad``) flow from image, depth and alpha into means, quats, scales,
    opacities, colors, backgrounds and viewmat (only viewmat and backgrounds with
    ``differentiable="viewmat"``); K receives zero gradient.
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    width, height = int(width), int(height)
    if not (0 < near_plane < far_plane):
        raise ValueError(f"need 0 < near_plane < far_plane, got {near_plane}, {far_plane}")
    if eps2d < 0:
        raise ValueError(f"eps2d must be non-negative, got {eps2d}")
    composite_code, threads_code = _check_run_options(composite, threads)
    if differentiable not in DIFFERENTIABLE:
        raise ValueError(f"differentiable must be one of {DIFFERENTIABLE}, got {differentiable!r}")

    means = _as_float("means", means, "(N, 3)", ndim=2)
    if means.shape[1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    N = means.shape[0]
    scales = _as_float("scales", scales, "(N, 3), (N, 1) or (N,)")
    if scales.shape in ((N,), (N, 1)):
        scales = jnp.broadcast_to(scales.reshape(N, 1), (N, 3))
    elif scales.shape != (N, 3):
        raise ValueError(f"scales must have shape (N, 3), (N, 1) or (N,) with N={N}, got {tuple(scales.shape)}")
    if quats is None:
        quats = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32), (N, 4))
    quats = _as_float("quats", quats, f"({N}, 4)", ndim=2)
    if quats.shape != (N, 4):
        raise ValueError(f"quats must have shape ({N}, 4), got {tuple(quats.shape)}")
    opacities = _as_float("opacities", opacities, f"({N},)")
    if opacities.shape == (N, 1):
        opacities = opacities.reshape(N)
    if opacities.shape != (N,):
        raise ValueError(f"opacities must have shape ({N},), got {tuple(opacities.shape)}")
    if "RGB" not in render_mode and colors is None:
        colors = jnp.zeros((N, 1), jnp.float32)  # depth-only: composite one dummy channel
    colors = _as_float("colors", colors, f"({N}, C)", ndim=2)
    if "RGB" not in render_mode:
        colors = jnp.zeros((N, 1), jnp.float32)
    if colors.shape[0] != N or colors.shape[1] < 1:
        raise ValueError(f"colors must have shape ({N}, C) with C >= 1, got {tuple(colors.shape)}")
    C = colors.shape[1]

    viewmat = _as_float("viewmat", viewmat, "(4, 4) or (B, 4, 4)")
    K = _as_float("K", K, "(3, 3) or (B, 3, 3)")
    if viewmat.shape[-2:] != (4, 4) or viewmat.ndim not in (2, 3):
        raise ValueError(f"viewmat must have shape (4, 4) or (B, 4, 4), got {tuple(viewmat.shape)}")
    if K.shape[-2:] != (3, 3) or K.ndim not in (2, 3):
        raise ValueError(f"K must have shape (3, 3) or (B, 3, 3), got {tuple(K.shape)}")
    batched = viewmat.ndim == 3 or K.ndim == 3
    B = max(viewmat.shape[0] if viewmat.ndim == 3 else 1, K.shape[0] if K.ndim == 3 else 1)
    for name, x in (("viewmat", viewmat), ("K", K)):
        if x.ndim == 3 and x.shape[0] != B:
            raise ValueError(f"{name} has {x.shape[0]} cameras but another argument has {B}")
    viewmats = jnp.broadcast_to(viewmat, (B, 4, 4))
    Ks = jnp.broadcast_to(K, (B, 3, 3))
    if backgrounds is not None:
        backgrounds = _as_float("backgrounds", backgrounds, "(C,) or (B, C)")
        if backgrounds.shape[-1] != C or backgrounds.ndim not in (1, 2):
            raise ValueError(f"backgrounds must have shape ({C},) or (B, {C}), got {tuple(backgrounds.shape)}")
        backgrounds = jnp.broadcast_to(backgrounds, (B, C))

    _check_values("means", means)
    _check_values("quats", quats)
    if _is_concrete(quats) and N and np.any(np.sum(np.asarray(quats) ** 2, axis=1) <= 0):
        raise ValueError("quats contains a zero-length quaternion")
    _check_values("scales", scales, nonneg=True)
    _check_values("opacities", opacities, unit=True)
    _check_values("colors", colors)
    _check_camera(viewmats, Ks)

    cfg = _Cfg(width, height, float(near_plane), float(far_plane), float(eps2d), bool(validate), composite_code,
               threads_code, differentiable == "viewmat")
    image, depth, alpha, radii, n_isect = _render_cameras(cfg, render_mode, batched, means, quats, scales, opacities,
                                                          colors, viewmats, Ks, backgrounds)
    meta = {"radii": radii, "n_isect": n_isect, "width": width, "height": height, "tile_size": _pl.TILE_SIZE}
    return RasterOutput(image, depth, alpha, meta)


def _z_per_distance(cfg: _Cfg, K):
    """(H, W, 1) z-depth per unit of distance along each pixel's ray (pixel centres at +0.5)."""
    K = jax.lax.stop_gradient(K)
    x = (jnp.arange(cfg.width, dtype=jnp.float32) + 0.5 - K[0, 2]) / K[0, 0]
    y = (jnp.arange(cfg.height, dtype=jnp.float32) + 0.5 - K[1, 2]) / K[1, 1]
    return jax.lax.rsqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)[..., None]


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _render_cameras(cfg: _Cfg, render_mode: str, batched: bool, means, quats, scales, opacities, colors, viewmats,
                    Ks, backgrounds):
    """All cameras of one call. Jitted so that eager callers run compiled code (a bare FFI call
    outside jit is re-lowered on every call); under an outer jit it is simply inlined."""
    images, depths_, alphas, radii, n_isects = [], [], [], [], []
    for b in range(viewmats.shape[0]):
        img, dep, alp, rad, nis = _core(cfg, means, quats, scales, opacities, colors, viewmats[b], Ks[b])
        dep = dep * _z_per_distance(cfg, Ks[b])
        if backgrounds is not None:
            img = img + (1.0 - alp) * backgrounds[b]
        if render_mode.endswith("ED"):
            dep = dep / jnp.maximum(alp, 1e-10)
        images.append(img)
        depths_.append(dep)
        alphas.append(alp)
        radii.append(rad)
        n_isects.append(nis)

    def pick(xs):
        return jnp.stack(xs) if batched else xs[0]

    image = pick(images) if "RGB" in render_mode else None
    depth = pick(depths_) if "D" in render_mode else None
    return image, depth, pick(alphas), pick(radii), pick(n_isects)


def rasterize_top_ids(
    means: Any,
    quats: Any,
    scales: Any,
    opacities: Any,
    viewmat: Any,
    K: Any,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    return_weights: bool = False,
    threads: int | None = None,
):
    """Per pixel, the index of the Gaussian that contributes most (largest alpha * T).

    Same inputs and rules as :func:`rasterize` for one camera (means (N, 3), quats (N, 4) wxyz or
    None, scales (N, 3) / (N,), opacities (N,), viewmat (4, 4), K (3, 3)). Used to lift 2-D
    detection masks onto the Gaussians behind them; it is not differentiable and runs on the
    host (numpy in, numpy out). ``threads``: CPU worker threads (None: the default).

    Returns:
        (H, W) int32 indices into the input arrays, -1 where no Gaussian contributes; with
        ``return_weights`` also the (H, W) float32 winning weights.
    """
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    width, height = int(width), int(height)
    means = np.asarray(means, np.float32)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {means.shape}")
    N = means.shape[0]
    scales = np.asarray(scales, np.float32)
    if scales.shape in ((N,), (N, 1)):
        scales = np.repeat(scales.reshape(N, 1), 3, 1)
    if scales.shape != (N, 3):
        raise ValueError(f"scales must have shape (N, 3), (N, 1) or (N,) with N={N}, got {scales.shape}")
    quats = np.tile(np.float32([1, 0, 0, 0]), (N, 1)) if quats is None else np.asarray(quats, np.float32)
    opacities = np.asarray(opacities, np.float32).reshape(-1)
    viewmat = np.asarray(viewmat, np.float32)
    K = np.asarray(K, np.float32)
    if quats.shape != (N, 4) or opacities.shape != (N,) or viewmat.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(f"expected quats ({N}, 4), opacities ({N},), viewmat (4, 4), K (3, 3); got "
                         f"{quats.shape}, {opacities.shape}, {viewmat.shape}, {K.shape}")
    for name, a in (("means", means), ("scales", scales), ("quats", quats), ("opacities", opacities),
                    ("viewmat", viewmat), ("K", K)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or Inf")
    device = "cuda" if jax.default_backend() == "gpu" and wp.is_cuda_available() else "cpu"
    arr = functools.partial(wp.array, device=device)
    ids, w = _pl.top_ids(arr(means, dtype=wp.vec3), arr(quats, dtype=wp.vec4), arr(scales, dtype=wp.vec3),
                         arr(opacities, dtype=wp.float32), arr(viewmat[None], dtype=wp.mat44),
                         arr(K[None], dtype=wp.mat33), width, height, float(near_plane), float(far_plane),
                         float(eps2d), threads=_check_run_options(None, threads)[1] or None)
    ids = ids.reshape(height, width)
    return (ids, w.reshape(height, width)) if return_weights else ids
