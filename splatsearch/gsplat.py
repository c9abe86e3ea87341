"""gsplat's ``rasterization()`` call and return form, over splatsearch's rasterizer.

Code written against gsplat 1.x (``render_colors, render_alphas, meta = rasterization(...)``) runs
on splatsearch by changing the import to ``from splatsearch.gsplat import rasterization``;
:func:`splatsearch.rasterize` stays the native call. The
differences from gsplat are listed in :func:`rasterization`'s docstring. Everything here is JAX,
so ``jax.jit`` and ``jax.grad`` apply, and ``meta["means2d"]`` is differentiable w.r.t. ``means``
and ``viewmats``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from splatsearch.rasterization import RENDER_MODES, rasterize

# Real spherical-harmonics constants up to degree 3 (the 3DGS / gsplat convention).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def spherical_harmonics(degree: int, dirs: jax.Array, coeffs: jax.Array) -> jax.Array:
    """Colours (..., 3) of SH ``coeffs`` (..., K, 3), K >= (degree + 1)^2, seen along ``dirs`` (..., 3)
    (any length; normalised here), as gsplat's ``spherical_harmonics`` (add 0.5 for RGB)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    if coeffs.shape[-2] < (degree + 1) ** 2:
        raise ValueError(f"degree {degree} needs {(degree + 1) ** 2} coefficients, got {coeffs.shape[-2]}")
    d = dirs / jnp.maximum(jnp.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    c = coeffs
    out = SH_C0 * c[..., 0, :]
    if degree >= 1:
        out = out - SH_C1 * y * c[..., 1, :] + SH_C1 * z * c[..., 2, :] - SH_C1 * x * c[..., 3, :]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out = (out + SH_C2[0] * xy * c[..., 4, :] + SH_C2[1] * yz * c[..., 5, :]
               + SH_C2[2] * (2 * zz - xx - yy) * c[..., 6, :] + SH_C2[3] * xz * c[..., 7, :]
               + SH_C2[4] * (xx - yy) * c[..., 8, :])
    if degree >= 3:
        out = (out + SH_C3[0] * y * (3 * xx - yy) * c[..., 9, :] + SH_C3[1] * xy * z * c[..., 10, :]
               + SH_C3[2] * y * (4 * zz - xx - yy) * c[..., 11, :]
               + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * c[..., 12, :]
               + SH_C3[4] * x * (4 * zz - xx - yy) * c[..., 13, :] + SH_C3[5] * z * (xx - yy) * c[..., 14, :]
               + SH_C3[6] * x * (xx - 3 * yy) * c[..., 15, :])
    return out


def project_means(means: jax.Array, viewmats: jax.Array, Ks: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(means2d (C, N, 2) pixels, depths (C, N) metres) of world ``means`` (N, 3) seen by the
    ``viewmats`` (C, 4, 4) world-to-camera with intrinsics ``Ks`` (C, 3, 3)."""
    # HIGHEST: on GPUs a float32 einsum defaults to TF32 (10-bit mantissa), 0.01-0.05 px off here
    cam = jnp.einsum("cij,nj->cni", viewmats[:, :3, :3], means,
                     precision=jax.lax.Precision.HIGHEST) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    zs = jnp.where(jnp.abs(z) < 1e-8, 1e-8, z)
    u = Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]
    return jnp.stack([u, v], -1), z


def rasterization(
    means: Any,
    quats: Any,
    scales: Any,
    opacities: Any,
    colors: Any,
    viewmats: Any,
    Ks: Any,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    backgrounds: Any = None,
    render_mode: str = "RGB",
    **unsupported: Any,
) -> tuple[jax.Array, jax.Array, dict]:
    """gsplat 1.x ``rasterization`` on splatsearch's tile rasterizer.

    Args:
        means: (N, 3) metres. quats: (N, 4) wxyz. scales: (N, 3) metres. opacities: (N,) in [0, 1].
        colors: (N, D) or per camera (C, N, D) features; with ``sh_degree``, SH coefficients
            (N, K, 3) or (C, N, K, 3), evaluated per camera along the camera-to-Gaussian direction
            and offset by 0.5 then clamped at 0, as gsplat does.
        viewmats: (C, 4, 4) world-to-camera (OpenCV frame). Ks: (C, 3, 3) pixels.
        width, height: image size in pixels.
        near_plane, far_plane, eps2d: as gsplat (metres, metres, px^2).
        sh_degree: None for plain features, else 0..3.
        backgrounds: (C, D) or (D,) colour behind the Gaussians.
        render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED".

    Returns:
        ``render_colors`` (C, H, W, X) with X = D, 1 or D + 1 (depth last, as gsplat),
        ``render_alphas`` (C, H, W, 1), and ``meta`` with ``means2d`` (C, N, 2) px, ``depths``
        (C, N) m, ``radii`` (C, N, 2) int32 px (0 = culled), ``n_isect`` (C,) tile intersections,
        ``width``, ``height``, ``tile_size``, ``n_cameras``.

    Differences from gsplat: no leading batch dimensions beyond C, ``packed`` / ``sparse_grad`` /
    ``absgrad`` / ``rasterize_mode="antialiased"`` / camera models other than pinhole are not
    implemented and raise ``NotImplementedError`` when set to a non-default value.
    """
    defaults = {"packed": True, "sparse_grad": False, "absgrad": False, "rasterize_mode": "classic",
                "camera_model": "pinhole", "tile_size": 16, "radius_clip": 0.0, "distributed": False,
                "with_ut": False, "with_eval3d": False}
    for k, v in unsupported.items():
        if k not in defaults:
            raise TypeError(f"rasterization() got an unexpected keyword argument {k!r}")
        if v != defaults[k]:
            raise NotImplementedError(f"{k}={v!r} is not supported by splatsearch (only {defaults[k]!r})")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    means = jnp.asarray(means, jnp.float32)
    viewmats = jnp.asarray(viewmats, jnp.float32)
    Ks = jnp.asarray(Ks, jnp.float32)
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must have shape (C, 4, 4), got {tuple(viewmats.shape)}")
    if Ks.ndim != 3 or Ks.shape[1:] != (3, 3) or Ks.shape[0] != viewmats.shape[0]:
        raise ValueError(f"Ks must have shape ({viewmats.shape[0]}, 3, 3), got {tuple(Ks.shape)}")
    C = viewmats.shape[0]
    colors = None if colors is None else jnp.asarray(colors, jnp.float32)
    if colors is not None and sh_degree is not None:
        if colors.ndim not in (3, 4) or colors.shape[-1] != 3:
            raise ValueError(f"with sh_degree, colors must be SH coefficients (N, K, 3) or (C, N, K, 3), "
                             f"got {tuple(colors.shape)}")
        campos = jnp.linalg.inv(viewmats)[:, :3, 3]
        dirs = means[None] - campos[:, None]  # (C, N, 3)
        coeffs = colors if colors.ndim == 4 else jnp.broadcast_to(colors, (C,) + colors.shape)
        colors = jnp.maximum(spherical_harmonics(sh_degree, dirs, coeffs) + 0.5, 0.0)  # (C, N, 3)
    per_camera = colors is not None and colors.ndim == 3
    if backgrounds is not None:
        backgrounds = jnp.broadcast_to(jnp.asarray(backgrounds, jnp.float32),
                                       (C, jnp.asarray(backgrounds).shape[-1]))
    kw = dict(render_mode=render_mode, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d)
    if per_camera:
        outs = [rasterize(means, quats, scales, opacities, colors[c], viewmats[c], Ks[c], width, height,
                          backgrounds=None if backgrounds is None else backgrounds[c], **kw) for c in range(C)]
        image = jnp.stack([o.image for o in outs]) if "RGB" in render_mode else None
        depth = jnp.stack([o.depth for o in outs]) if "D" in render_mode else None
        alpha = jnp.stack([o.alpha for o in outs])
        radii = jnp.stack([o.meta["radii"] for o in outs])
        n_isect = jnp.stack([jnp.asarray(o.meta["n_isect"]).reshape(()) for o in outs])
        tile_size = outs[0].meta["tile_size"]
    else:
        out = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                        backgrounds=backgrounds, **kw)
        image, depth, alpha = out.image, out.depth, out.alpha
        radii, n_isect = out.meta["radii"], jnp.asarray(out.meta["n_isect"]).reshape(C)
        tile_size = out.meta["tile_size"]
    parts = ([image] if image is not None else []) + ([depth] if depth is not None else [])
    render_colors = parts[0] if len(parts) == 1 else jnp.concatenate(parts, -1)
    means2d, depths = project_means(means, viewmats, Ks)
    meta = {"means2d": means2d, "depths": depths, "radii": radii, "n_isect": n_isect, "width": width,
            "height": height, "tile_size": tile_size, "n_cameras": C}
    return render_colors, alpha, meta
