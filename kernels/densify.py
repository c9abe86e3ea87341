"""Densification (thesis eq 10, SplaTAM): new Gaussians where the map is missing or behind.

On a grid of every ``stride``-th pixel with valid observed depth, the mask is

    alpha < tau_o  OR  (D_obs < D_hat AND |D_obs - D_hat| > k * median |D_obs - D_hat|)

Each masked pixel becomes one Gaussian at the back-projected depth (pixel centre, +0.5) under
the camera pose, with the pixel's colour, scale ``pixel_scale * z / f`` (f = (fx + fy) / 2), unit
quaternion and opacity 0.5. ``pixel_scale = 1`` is SplaTAM's one-pixel footprint. Two launches
and a scan, with one host read of the count; the same kernels run on CPU and CUDA.

``surface_aligned=True`` gives each new Gaussian the shape of the surface patch its pixel block
sees instead: a flat ellipse in the plane of the back-projected neighbours, as long along each
image axis as the 3-D step to the next grid pixel (times ``pixel_scale / stride``, so a
fronto-parallel patch keeps the isotropic size) and thin along the normal. A floor seen at a
grazing angle then covers the ground between pixel rows; isotropic Gaussians leave it as stripes
with gaps that only a view from above shows (the NVSM's hemisphere views).
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def densify_mask_kernel(
    depth_obs: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    depth_hat: wp.array(dtype=float),
    width: int,
    height: int,
    stride: int,
    grid_w: int,
    tau_o: float,
    err_thresh: float,
    mask: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    px = (i % grid_w) * stride
    py = (i // grid_w) * stride
    m = int(0)
    if px < width and py < height:
        pix = py * width + px
        z = depth_obs[pix]
        if z > 0.0:
            dh = depth_hat[pix]
            if alpha[pix] < tau_o or (z < dh and wp.abs(z - dh) > err_thresh):
                m = 1
    mask[i] = m


@wp.kernel
def densify_write_kernel(
    mask: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    depth_obs: wp.array(dtype=float),
    rgb: wp.array(dtype=wp.vec3),
    c2w: wp.mat44,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    stride: int,
    grid_w: int,
    pixel_scale: float,
    means: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    log_scales: wp.array(dtype=float),
):
    i = wp.tid()
    if mask[i] == 0:
        return
    k = offsets[i] - 1  # inclusive scan
    px = (i % grid_w) * stride
    py = (i // grid_w) * stride
    pix = py * width + px
    z = depth_obs[pix]
    pc = wp.vec4((float(px) + 0.5 - cx) / fx * z, (float(py) + 0.5 - cy) / fy * z, z, 1.0)
    pw = c2w * pc
    means[k] = wp.vec3(pw[0], pw[1], pw[2])
    colors[k] = rgb[pix]
    log_scales[k] = wp.log(pixel_scale * z / (0.5 * (fx + fy)))


def densify(depth_obs: np.ndarray, alpha: np.ndarray, depth_hat: np.ndarray, rgb: np.ndarray, viewmat: np.ndarray,
            K: np.ndarray, *, tau_o: float = 0.5, k: float = 50.0, stride: int = 1, pixel_scale: float = 1.0,
            surface_aligned: bool = False, max_stretch: float = 6.0, device: str = "cpu") -> dict:
    """New Gaussians for one frame (eq 10).

    Args:
        depth_obs: (H, W) observed depth, metres, 0 = invalid.
        alpha: (H, W) rendered silhouette of the current map.
        depth_hat: (H, W) rendered depth D of the current map, metres.
        rgb: (H, W, 3) observed colours in [0, 1].
        viewmat: (4, 4) world-to-camera pose of the frame; K: (3, 3) intrinsics.
        tau_o, k: silhouette threshold and depth-error factor (SplaTAM: 0.5, 50).
        stride: use every stride-th pixel in x and y.
        pixel_scale: new scales are ``pixel_scale * z / f`` metres (1: one pixel, as SplaTAM).
        surface_aligned: flat Gaussians in the local surface plane (see the module docstring);
            max_stretch caps their length at this many times the isotropic scale (a grazing floor
            far away); pixels without a neighbour of valid depth keep the isotropic shape.

    Returns:
        dict of numpy arrays: means (n, 3), colors (n, 3), log_scales (n, 3), quats (n, 4),
        opacity_logits (n,), and ``mask`` (H, W) bool of the pixels that spawned a Gaussian.
    """
    depth_obs = np.ascontiguousarray(depth_obs, np.float32)
    H, W = depth_obs.shape
    for name, a, shape in (("alpha", alpha, (H, W)), ("depth_hat", depth_hat, (H, W)), ("rgb", rgb, (H, W, 3))):
        if np.shape(a) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {np.shape(a)}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale must be > 0, got {pixel_scale}")
    if not max_stretch > 0:
        raise ValueError(f"max_stretch must be > 0, got {max_stretch}")
    valid = depth_obs > 0
    err = np.abs(depth_obs - np.asarray(depth_hat, np.float32))[valid]
    thresh = float(k * np.median(err)) if err.size else np.inf
    gw, gh = (W + stride - 1) // stride, (H + stride - 1) // stride
    n_grid = gw * gh
    dev = wp.get_device(device)
    arr = lambda a, dt: wp.array(np.ascontiguousarray(a, np.float32).reshape(-1, *( (3,) if dt is wp.vec3 else ())), dtype=dt, device=dev)  # noqa: E731
    d_obs = arr(depth_obs, float)
    mask = wp.empty(n_grid, dtype=wp.int32, device=dev)
    wp.launch(densify_mask_kernel, dim=n_grid,
              inputs=[d_obs, arr(alpha, float), arr(depth_hat, float), W, H, stride, gw, float(tau_o), thresh],
              outputs=[mask], device=dev)
    offsets = wp.empty(n_grid, dtype=wp.int32, device=dev)
    wp.utils.array_scan(mask, offsets, inclusive=True)
    n = int(offsets[n_grid - 1:n_grid].numpy()[0])
    means = wp.empty(max(n, 1), dtype=wp.vec3, device=dev)
    colors = wp.empty(max(n, 1), dtype=wp.vec3, device=dev)
    log_s = wp.empty(max(n, 1), dtype=float, device=dev)
    c2w = np.linalg.inv(np.asarray(viewmat, np.float64)).astype(np.float32)
    K = np.asarray(K, np.float64)
    if n:
        wp.launch(densify_write_kernel, dim=n_grid,
                  inputs=[mask, offsets, d_obs, arr(rgb, wp.vec3), wp.mat44(*c2w.ravel()), float(K[0, 0]),
                          float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), W, stride, gw, float(pixel_scale)],
                  outputs=[means, colors, log_s], device=dev)
    m = mask.numpy().reshape(gh, gw).astype(bool)
    full = np.zeros((H, W), bool)
    full[::stride, ::stride] = m
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1
    log_scales = np.repeat(log_s.numpy()[:n, None], 3, 1)
    if surface_aligned and n:
        log_scales, quats = _surface_shapes(depth_obs, K, viewmat, stride, pixel_scale, max_stretch, m, log_scales,
                                             quats)
    return {
        "means": means.numpy()[:n].copy(), "colors": colors.numpy()[:n].copy(),
        "log_scales": log_scales, "quats": quats,
        "opacity_logits": np.zeros(n, np.float32), "mask": full,
    }


def _surface_shapes(depth: np.ndarray, K: np.ndarray, viewmat: np.ndarray, stride: int, pixel_scale: float,
                    max_stretch: float, grid_mask: np.ndarray, log_scales: np.ndarray, quats: np.ndarray):
    """Log scales (n, 3) and wxyz quaternions (n, 4) of flat surface-aligned Gaussians for the
    masked grid pixels (row-major, as the write kernel orders them); rows without a usable
    neighbour keep the given isotropic shape."""
    from scipy.spatial.transform import Rotation

    from splatsearch.camera import pixels_to_world

    H, W = depth.shape
    ys, xs = np.mgrid[0:H:stride, 0:W:stride]
    z = depth[ys, xs].astype(np.float64)
    P = pixels_to_world(xs, ys, z, viewmat, K)
    iso = stride * z / (0.5 * (K[0, 0] + K[1, 1]))  # the 3-D grid step on a fronto-parallel surface

    def tangent(P: np.ndarray, z: np.ndarray, iso: np.ndarray) -> np.ndarray:
        """Step (gh, gw, 3) to the next grid pixel along axis 1, NaN without a valid neighbour."""
        step = P[:, 1:] - P[:, :-1]
        step[~((z[:, 1:] > 0) & (z[:, :-1] > 0))] = np.nan
        pad = np.full_like(P[:, :1], np.nan)
        fwd, bwd = np.concatenate([step, pad], 1), np.concatenate([pad, step], 1)
        lf, lb = np.linalg.norm(fwd, axis=-1), np.linalg.norm(bwd, axis=-1)
        # the shorter of the forward and backward steps: across a depth edge the step to the far
        # side is long, and the other side is the surface
        back = np.isnan(lf) | (lb < lf)
        t, length = np.where(back[..., None], bwd, fwd), np.where(back, lb, lf)
        # a far floor seen edge-on: capped, so one Gaussian does not smear a whole stripe
        return t * (np.minimum(length, max_stretch * iso) / length)[..., None]

    tu = tangent(P, z, iso)
    tv = tangent(P.swapaxes(0, 1), z.T, iso.T).swapaxes(0, 1)
    good = (z > 0) & np.all(np.isfinite(tu), -1) & np.all(np.isfinite(tv), -1)
    sel = good[grid_mask]  # masked grid pixels in write order (row-major)
    if not sel.any():
        return log_scales, quats
    tu, tv = tu[grid_mask][sel], tv[grid_mask][sel]
    lu = np.linalg.norm(tu, axis=-1)
    e1 = tu / lu[:, None]
    v_perp = tv - (tv * e1).sum(-1, keepdims=True) * e1
    lv = np.linalg.norm(v_perp, axis=-1)
    ok = lv > 1e-9
    idx = np.flatnonzero(sel)[ok]
    e1, e2, lu, lv = e1[ok], v_perp[ok] / lv[ok, None], lu[ok], lv[ok]
    R = np.stack([e1, e2, np.cross(e1, e2)], -1)  # columns: the ellipse's axes in the world
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    quats = quats.copy()
    quats[idx] = np.concatenate([q[:, 3:], q[:, :3]], 1).astype(np.float32)
    su, sv = (pixel_scale / stride) * lu, (pixel_scale / stride) * lv
    log_scales = log_scales.copy()
    log_scales[idx] = np.log(np.stack([su, sv, 0.1 * np.minimum(su, sv)], -1)).astype(np.float32)
    return log_scales, quats
