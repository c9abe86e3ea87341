"""Novel Viewpoint Synthesis Module (NVSM, thesis Section 4.2.3).

Cameras are placed on the upper hemisphere of radius ``r_v`` around an object's centroid at
fixed azimuth steps, each looking at the centroid, and the Gaussian map is rendered from them.
The renders have holes where the map is unobserved; :mod:`splatsearch.search.inpainting` fills
them before matching.

Object-centric renders (an addition to the thesis, see :func:`crop_box_for`): Gaussians outside a
box around the object can be hidden, so walls and floors, whose textures repeat across a house,
do not produce feature matches between the goal image and views of the wrong object.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from splatsearch.nav.grid import GridSpec

#: world z of the ceiling in the procedural houses is 2.6 m; cameras stay a little below it
DEFAULT_MAX_HEIGHT = 2.4
DEFAULT_MIN_HEIGHT = 0.2


def camera_pose(viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), optical axis (3,)) in world coordinates of a (4, 4) world-to-camera matrix:
    the centre is ``-R^T t`` and the axis is the camera's +z row of ``R`` (OpenCV frame)."""
    vm = np.asarray(viewmat, np.float64)
    R, t = vm[:3, :3], vm[:3, 3]
    return -R.T @ t, R[2].copy()


def _look_at_from(eye: np.ndarray, target: np.ndarray, az: float) -> np.ndarray:
    """World-to-camera (OpenCV) at ``eye`` looking at ``target`` with no roll. ``az`` is the camera's
    azimuth around the target; the right axis comes from it, so a camera straight above the target
    (where the usual cross product with world up degenerates) is still well defined."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.array([-np.sin(az), np.cos(az), 0.0])
    right = right - fwd * (right @ fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm


def hemisphere_viewpoints(centroid: Sequence[float], radius: float = 1.5, n_views: int = 12,
                          elevations_deg: Sequence[float] = (35.0,), azimuth0_deg: float = 0.0, *,
                          min_height: float | None = DEFAULT_MIN_HEIGHT,
                          max_height: float | None = DEFAULT_MAX_HEIGHT, min_rise: float = 0.1) -> np.ndarray:
    """Cameras on the upper hemisphere around ``centroid``, all looking at it.

    The ``n_views`` cameras are split over the elevation rings as evenly as possible (earlier
    rings get the remainder); each ring is sampled at fixed azimuth steps of 360 / n_ring
    degrees from ``azimuth0_deg``, odd rings shifted by half a step so rings interleave.

    A camera whose height would leave [``min_height``, ``max_height``] (floor and ceiling, in
    world metres) is moved vertically to the limit and horizontally so it stays ``radius`` from
    the centroid; every camera stays at least ``min_rise`` above the centroid, so all views look
    down on the object as a robot or a person would.

    Args:
        centroid: (3,) world position in metres.
        radius: r_v, camera distance in metres.
        n_views: N_R.
        elevations_deg: ring elevations above the horizontal through the centroid, in (0, 90].
        azimuth0_deg: azimuth of the first camera (degrees from +x, counter-clockwise).

    Returns:
        (n_views, 4, 4) float64 world-to-camera matrices (OpenCV frame).

    Raises:
        ValueError: for a bad centroid, radius, count or elevation, or when the ceiling leaves no
            room above the centroid.
    """
    c = np.asarray(centroid, np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"centroid must be a finite (3,) position, got {np.asarray(centroid)}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive (metres), got {radius}")
    if isinstance(n_views, bool) or int(n_views) != n_views or n_views < 1:
        raise ValueError(f"n_views must be an integer >= 1, got {n_views}")
    elev = np.radians(np.asarray(elevations_deg, np.float64).reshape(-1))
    if len(elev) == 0 or len(elev) > n_views or not np.all((elev > 0) & (elev <= np.pi / 2)):
        raise ValueError(f"need 1..n_views elevations in (0, 90] degrees, got {list(elevations_deg)}")
    if not 0 < min_rise < radius:
        raise ValueError(f"min_rise must be in (0, radius), got {min_rise}")
    z_lo = c[2] + min_rise
    if min_height is not None:
        z_lo = max(z_lo, float(min_height))
    z_hi = c[2] + radius if max_height is None else min(c[2] + radius, float(max_height))
    if z_hi < z_lo:
        raise ValueError(f"no room for cameras above the centroid (z = {c[2]:.2f} m) below max_height {max_height} m")
    n_views = int(n_views)
    counts = [n_views // len(elev) + (1 if i < n_views % len(elev) else 0) for i in range(len(elev))]
    out = []
    for ring, (e, n) in enumerate(zip(elev, counts)):
        step = 2 * np.pi / n
        dz = float(np.clip(radius * np.sin(e), z_lo - c[2], z_hi - c[2]))
        horiz = np.sqrt(max(radius * radius - dz * dz, 0.0))
        for k in range(n):
            az = np.radians(azimuth0_deg) + step * (k + 0.5 * (ring % 2))
            if horiz < 1e-9:
                eye = c + np.array([0.0, 0.0, dz])
            else:
                eye = c + np.array([horiz * np.cos(az), horiz * np.sin(az), dz])
            out.append(_look_at_from(eye, c, az))
    return np.stack(out)


def clear_viewpoints(viewmats: np.ndarray, blocked: np.ndarray, spec: GridSpec, target_xy: Sequence[float],
                     skip_radius: float = 0.0, free: np.ndarray | None = None) -> np.ndarray:
    """Which cameras see ``target_xy`` across a 2-D obstacle map: (V,) bool.

    A camera is kept when the cell under it is inside the map, not blocked (and ``free`` there,
    when a known-free mask is given: a camera over unknown space may be inside a wall), and no
    blocked cell lies on the segment from it to the target, ignoring the last ``skip_radius``
    metres (the object's own footprint). Hemisphere cameras behind a wall see the wall's back,
    which no goal image shows.

    Args:
        viewmats: (V, 4, 4) world-to-camera matrices.
        blocked: (H, W) bool obstacle cells on the grid ``spec`` (its origin, cell size, shape).
        spec: the grid's placement in metres (:class:`~splatsearch.nav.grid.GridSpec`).
        target_xy: (2,) world metres; skip_radius: metres around it not checked.
        free: optional (H, W) bool known-free cells.
    """
    vms = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    blocked = np.asarray(blocked, bool)
    if blocked.shape != spec.shape:
        raise ValueError(f"blocked must have the grid's shape {spec.shape}, got {blocked.shape}")
    t = np.asarray(target_xy, np.float64).reshape(2)
    keep = np.zeros(len(vms), bool)
    for i, vm in enumerate(vms):
        eye, _ = camera_pose(vm)
        seg = t - eye[:2]
        length = float(np.linalg.norm(seg))
        reach = max(length - skip_radius, 0.0)
        # samples every half cell, so no cell the segment crosses is skipped
        s = np.linspace(0.0, reach / max(length, 1e-9), max(2, int(np.ceil(reach / (0.5 * spec.cell_size))) + 1))
        rc = spec.world_to_cell(eye[:2] + s[:, None] * seg)
        if not spec.in_bounds(rc).all():
            continue
        if free is not None and not free[rc[0, 0], rc[0, 1]]:
            continue
        keep[i] = not blocked[rc[:, 0], rc[:, 1]].any()
    return keep


def crop_box_for(bbox_min: Sequence[float], bbox_max: Sequence[float], margin: float = 0.3,
                 floor_z: float | None = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A world box (lo (3,), hi (3,)) around an object's extent for object-centric renders:
    the extent grown by ``margin`` metres, with the bottom raised to ``floor_z`` (if given) so the
    floor, whose texture repeats across the house, is left out."""
    lo = np.asarray(bbox_min, np.float64).reshape(3) - margin
    hi = np.asarray(bbox_max, np.float64).reshape(3) + margin
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ValueError("bbox must be finite with bbox_min <= bbox_max")
    if floor_z is not None:
        lo[2] = max(lo[2], float(floor_z))
        hi[2] = max(hi[2], lo[2])
    return lo, hi


def _map_args(gmap: Any):
    if hasattr(gmap, "render_args"):
        return gmap.render_args()
    if isinstance(gmap, (tuple, list)) and len(gmap) == 5:
        return tuple(gmap)
    raise ValueError("gmap must be a GaussianMap or a (means, quats, scales, opacities, colors) tuple")


def render_novel_views(gmap: Any, viewmats: np.ndarray, K: np.ndarray, width: int, height: int, *,
                       crop_box: tuple[np.ndarray, np.ndarray] | None = None,
                       near_plane: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Render the Gaussian map from each camera.

    Args:
        gmap: a :class:`~splatsearch.gaussians.GaussianMap`, or its ``render_args()`` tuple
            (means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), colors (N, 3)).
        viewmats: (V, 4, 4) world-to-camera matrices (e.g. :func:`hemisphere_viewpoints`).
        K: (3, 3) intrinsics in pixels; width, height: image size in pixels.
        crop_box: optional world box (lo (3,), hi (3,)) in metres; Gaussians whose means lie
            outside get zero opacity (see :func:`crop_box_for`).
        near_plane: camera-depth culling distance in metres.

    Returns:
        (rgb (V, H, W, 3) float32 in [0, 1] on a black background, alpha (V, H, W) float32).
    """
    from splatsearch.rasterization import rasterize

    viewmats = np.asarray(viewmats, np.float32)
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or len(viewmats) == 0:
        raise ValueError(f"viewmats must have shape (V, 4, 4) with V >= 1, got {viewmats.shape}")
    means, quats, scales, opac, colors = _map_args(gmap)
    if crop_box is not None:
        lo, hi = (np.asarray(b, np.float32).reshape(3) for b in crop_box)
        m = np.asarray(means)
        inside = np.all((m >= lo) & (m <= hi), axis=1)
        opac = np.asarray(opac) * inside
    rgbs, alphas = [], []
    # one camera per call: the single-camera render is compiled once per map capacity, whereas a
    # batched call would compile again for every new number of views
    for vm in viewmats:
        out = rasterize(means, quats, scales, opac, colors, vm, K, width, height, render_mode="RGB",
                        near_plane=near_plane)
        rgbs.append(np.asarray(out.image))
        alphas.append(np.asarray(out.alpha)[..., 0])
    return np.clip(np.stack(rgbs), 0.0, 1.0).astype(np.float32), np.stack(alphas).astype(np.float32)


def composite_under(rgb: np.ndarray, alpha: np.ndarray, under_rgb: np.ndarray,
                    under_alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Composite renders over other renders of the same cameras (the "over" operator).

    Both come from :func:`render_novel_views`, i.e. are premultiplied over black, so the result
    is ``rgb + (1 - alpha) * under_rgb`` with opacity ``alpha + (1 - alpha) * under_alpha``: where
    the front render saw nothing, the one under it shows through; where it is opaque, it is kept.

    Args:
        rgb: (V, H, W, 3) front renders in [0, 1]; alpha: (V, H, W) their opacity.
        under_rgb, under_alpha: the same shapes, the renders to show through.

    Returns:
        (rgb (V, H, W, 3) float32 in [0, 1], alpha (V, H, W) float32).
    """
    rgb, alpha = np.asarray(rgb, np.float32), np.asarray(alpha, np.float32)
    under_rgb, under_alpha = np.asarray(under_rgb, np.float32), np.asarray(under_alpha, np.float32)
    if rgb.shape != under_rgb.shape or alpha.shape != under_alpha.shape or rgb.shape[:-1] != alpha.shape:
        raise ValueError(f"shapes differ: rgb {rgb.shape}, alpha {alpha.shape}, under {under_rgb.shape}, "
                         f"{under_alpha.shape}")
    t = 1.0 - alpha
    out = np.clip(rgb + t[..., None] * under_rgb, 0.0, 1.0).astype(np.float32)
    return out, np.clip(alpha + t * under_alpha, 0.0, 1.0).astype(np.float32)
